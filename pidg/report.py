"""``pidg report RUN_OR_SUITE...``: one self-contained HTML page about runs and suites.

For each suite folder (``suite.json``, from ``pidg bench suite``) or bench folder (``quality.json``): its tables. For
every run (given directly, or a suite's runs): its row of metrics, its training-PSNR curve against training time from
the TensorBoard scalars (one chart per scene, one line per variant), and pictures rendered from the trained model
at the middle test view: the render beside ground truth, and with a material field the projected velocity (colour
wheel and arrows), the stress magnitude and, for the middle training pair, motion | Gaussian | velocity flow; after
decoupling, the dynamic/static split. Pictures are embedded (base64 PNG) and also written beside the page.
"""
from __future__ import annotations

import base64
import html
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch

from pidg.bench.suite import SSIM_NAMES, Grid, efficiency_grid, quality_grid, row_label
from pidg.checkpoint import CHECKPOINT_FILE, CONFIG_FILE
from pidg.evaluation.charts import svg_chart
from pidg.evaluation.images import save_png
from pidg.evaluation.visualize import dynamic_split_image, flow_comparison, material_field_images
from pidg.flow import open_flow_cache
from pidg.physics.advection import Advection
from pidg.pipeline import load_run

logger = logging.getLogger(__name__)

CURVE_TAG = "train/psnr"
SMOOTHING = 0.9  # exponential moving average of the per-step training PSNR (as TensorBoard's smoothing slider)


@dataclass
class RunEntry:
    """A run folder and how the report names it."""

    path: Path
    scene: str
    label: str
    row: dict[str, Any] = field(default_factory=dict)


def is_run(path: Path) -> bool:
    return (path / CONFIG_FILE).is_file() and (path / CHECKPOINT_FILE).is_file()


def _run_label(row: dict[str, Any]) -> str:
    """A run's name in the report: its variant (one run serves every predictor of the future protocol)."""
    return row_label({**row, "predictor": None})


def collect(paths: Sequence[Path]) -> tuple[list[tuple[str, dict]], list[RunEntry]]:
    """Suites (name, suite.json) and runs named by the inputs; a path that is neither is an error naming it."""
    suites, runs = [], []
    for path in map(Path, paths):
        if (path / "suite.json").is_file():
            data = json.loads((path / "suite.json").read_text())
            suites.append((f"{data['suite']} ({path})", data))
            runs += [RunEntry(Path(r["run_dir"]), r["scene"], _run_label(r), r) for r in data["rows"] if not r.get("error")]
        elif (path / "quality.json").is_file():
            rows = json.loads((path / "quality.json").read_text())
            runs += [RunEntry(Path(r["run_dir"]), r["scene"], _run_label(r), r) for r in rows if not r.get("error")]
        elif is_run(path):
            config = json.loads((path / CONFIG_FILE).read_text())
            runs.append(RunEntry(path, Path(config["data"]["path"]).name, path.name))
        elif not path.exists():
            raise FileNotFoundError(f"{path}: no such file or folder")
        else:
            raise ValueError(f"{path}: not a run folder ({CONFIG_FILE} + {CHECKPOINT_FILE}) nor a suite (suite.json) "
                             "or bench folder (quality.json)")
    unique = {}
    for run in runs:  # a run named twice (as a run and within a suite) appears once, with the suite's row
        unique.setdefault(run.path.resolve(), run)
    return suites, list(unique.values())


# ---- curves -------------------------------------------------------------------------------------------------------
def psnr_curve(run_dir: Path) -> list[tuple[float, float]]:
    """(training minutes, smoothed training PSNR in dB) from the run's TensorBoard scalars; [] without them."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # a dependency; heavy import

    folder = run_dir / "tensorboard"
    if not folder.is_dir():
        return []
    accumulator = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    accumulator.Reload()
    if CURVE_TAG not in accumulator.Tags().get("scalars", []):
        return []
    events = accumulator.Scalars(CURVE_TAG)
    start, smooth, points = events[0].wall_time, None, []
    for e in events:
        smooth = e.value if smooth is None else SMOOTHING * smooth + (1 - SMOOTHING) * e.value
        points.append(((e.wall_time - start) / 60.0, smooth))
    return points


# ---- pictures -----------------------------------------------------------------------------------------------------
@torch.no_grad()
def run_pictures(run_dir: Path, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Named [H, W, 3] pictures of a run at its middle test view (see the module docstring)."""
    run = load_run(run_dir, ("test",), device)
    model, frames = run.model, run.scene.test
    frame = frames[len(frames) // 2]
    out = model.render(frame.camera, frame.time)
    future = run.config.data.train_until is not None  # the test frames lie after training: the render is a prediction
    what = "deformation's prediction" if future else "render"
    pictures = {f"{what} | ground truth (t = {frame.time:.3f})": torch.cat([out.rgb.clamp(0, 1), frame.image.to(out.rgb.device)], dim=1)}
    if future and model.material_field is not None:
        advected = Advection(model, max(f.time for f in run.scene.train)).at(frame.time)
        prediction = model.render_state(advected, frame.camera).rgb.clamp(0, 1)
        pictures[f"advection's prediction | ground truth (t = {frame.time:.3f})"] = torch.cat([prediction, frame.image.to(prediction.device)], dim=1)
    if model.material_field is not None:
        field_images = material_field_images(model, frame, model.time_axis.frame_dt)
        pictures[f"velocity, px per frame interval (max {field_images.max_velocity_px:.2f})"] = field_images.velocity
        pictures["velocity arrows"] = field_images.quiver
        pictures[f"stress magnitude |sigma|_F (max {field_images.max_stress:.3g})"] = field_images.stress
        cache = open_flow_cache(run.scene, run.config.flow, run.run_dir / "flow_cache", progress=False)
        if len(cache):
            k = len(cache) // 2
            panel, errors = flow_comparison(model, cache.pair(k), run.config.flow)
            pictures[f"training pair {k}: motion | Gaussian | velocity flow (EPE {errors['gaussian_flow_epe']:.2f} | "
                     f"{errors['velocity_flow_epe']:.2f} px)"] = panel
    if model.dynamic_mask is not None:
        pictures["dynamic (red) / static (blue)"] = dynamic_split_image(model, frame)
    return {name: image.detach().cpu() for name, image in pictures.items()}


# ---- the page -----------------------------------------------------------------------------------------------------
def _grid_html(grid: Grid) -> str:
    header, rows = grid
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{'<b>' if bold else ''}{html.escape(t)}{'</b>' if bold else ''}</td>" for t, bold in row) + "</tr>"
        for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


RUN_COLUMNS = (("psnr", ".2f"), ("ssim", ".4f"), ("ssim_zeros", ".4f"), ("lpips_vgg", ".4f"), ("train_minutes", ".1f"),
               ("iterations", "d"), ("gaussians", "d"))


def _run_row(run: RunEntry) -> dict[str, Any]:
    """The run's figures: its suite row, else its eval_test/metrics.json and train_summary.json."""
    if run.row:
        return run.row
    row: dict[str, Any] = {}
    for name in ("train_summary.json", "eval_test/metrics.json"):
        path = run.path / name
        if path.is_file():
            data = json.loads(path.read_text())
            row.update(data.get("mean", {}) if "mean" in data else data)
    return row


def build_report(paths: Sequence[Path], out: Path, device: str = "cpu", pictures: bool = True) -> Path:
    """Write the HTML page to ``out`` (pictures also as PNGs in ``out``'s folder, under ``<stem>_pictures/``)."""
    suites, runs = collect(paths)
    out = Path(out)
    picture_dir = out.parent / f"{out.stem}_pictures"
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>pidg report</title><style>",
             "body{font-family:sans-serif;margin:24px;max-width:1400px} table{border-collapse:collapse;margin:8px 0 20px}",
             "td,th{border:1px solid #ccc;padding:3px 7px;text-align:right;font-size:13px} td:first-child,th:first-child{text-align:left}",
             "figure{display:inline-block;margin:6px;vertical-align:top} figcaption{font-size:12px;max-width:520px}",
             "img{image-rendering:pixelated;max-width:640px;border:1px solid #ddd}</style></head><body>",
             "<h1>pidg report</h1>"]
    for name, data in suites:
        tables = data["tables"]
        parts.append(f"<h2>Suite {html.escape(name)}</h2><p>{html.escape(data['spec'].get('description', ''))}. "
                     f"{html.escape(SSIM_NAMES[tables['ssim']])}; best of each column in bold.</p>")
        parts.append(_grid_html(quality_grid(tables)) + "<p>Efficiency (mean over scenes):</p>" + _grid_html(efficiency_grid(tables)))
        if tables["failures"]:
            parts.append("<p>Failed jobs:</p><ul>" + "".join(
                f"<li>{html.escape(f['scene'])} / {html.escape(f['method'])}: {html.escape(f['error'])}</li>" for f in tables["failures"]
            ) + "</ul>")
    if runs:
        parts.append("<h2>Runs</h2>")
        header = ["scene", "run", *(k for k, _ in RUN_COLUMNS)]
        rows = []
        for run in runs:
            row = _run_row(run)
            rows.append([(run.scene, False), (run.label, False)] + [
                (format(row[k], f) if isinstance(row.get(k), (int, float)) else "-", False) for k, f in RUN_COLUMNS
            ])
        parts.append(_grid_html((header, rows)))
        parts.append(f"<h2>Training PSNR against training time</h2><p>{CURVE_TAG} from TensorBoard, smoothed "
                     f"(EMA {SMOOTHING}); training views, so it measures the fit, not generalisation.</p>")
        for scene in dict.fromkeys(r.scene for r in runs):
            series = {r.label: psnr_curve(r.path) for r in runs if r.scene == scene}
            chart = svg_chart(series, "training minutes", "PSNR (dB)", empty_note="the runs have no TensorBoard scalars")
            parts.append(f"<h3>{html.escape(scene)}</h3>" + chart)
    if pictures and runs:
        parts.append("<h2>Pictures</h2>")
        for i, run in enumerate(runs):
            parts.append(f"<h3>{html.escape(run.scene)}: {html.escape(run.label)}</h3>")
            try:
                images = run_pictures(run.path, device)
            except Exception as err:  # noqa: BLE001 - a run that cannot be drawn is named, the report goes on
                parts.append(f"<p>pictures unavailable: {html.escape(type(err).__name__)}: {html.escape(str(err))}</p>")
                continue
            for j, (caption, image) in enumerate(images.items()):
                png = save_png(image, picture_dir / f"{i:02d}_{run.scene}_{j}.png").read_bytes()  # encoded once
                parts.append(f"<figure><img src='data:image/png;base64,{base64.b64encode(png).decode('ascii')}'>"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(parts))
    return out
