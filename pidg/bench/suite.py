"""``pidg bench suite NAME``: the paper's tables, reproduced by one command.

A suite is a named set of scenes x variants under one budget and seed. Its scenes are the dataset folders found in
a folder (``--data DIR``: a user with all eight D-NeRF scenes gets the whole table), its variants the paper's rows
(:data:`pidg.training.config.ABLATION_VARIANTS`). Every scene x variant is one :class:`Job`; a job is a plain,
picklable description, so the same function runs it in this process, in a process pool or as a Ray task
(:mod:`pidg.bench.executors`). A job that fails becomes a row with its error; the others are not lost.

Results: ``OUT/suite.json`` (every row, each with its resolved config, the git commit and the machine) and
``OUT/suite.md`` (the tables, shaped like the paper's: per scene and average, best in bold). SSIM in the tables is
the zero-padded convention of the 3DGS family's tables unless ``ssim="valid"``; the header names it.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Sequence

from pidg.bench.executors import run_local
from pidg.bench.provenance import git_commit, machine
from pidg.config_tools import apply_overrides, from_jsonable, to_jsonable
from pidg.data import dataset_layout, detect_format, load_scene
from pidg.data.motion_gt import has_motion_gt
from pidg.data.scene import parse_downscale
from pidg.evaluation.evaluate import flow_end_point_errors
from pidg.evaluation.future import evaluate_future
from pidg.flow import open_flow_cache
from pidg.metrics import SSIM_KEYS, NetName, SSIMPadding, lpips_weights_available
from pidg.pipeline import evaluate_and_save, evaluate_motion_and_save
from pidg.training.config import ABLATION_VARIANTS, TrainConfig
from pidg.training.run_folder import claim_run_folder
from pidg.training.trainer import Trainer

logger = logging.getLogger(__name__)

Protocol = Literal["interpolation", "future"]

#: Paper names of the variants (row labels of the tables).
VARIANT_LABELS = {
    "base": "PIDG w/o (CMR + LPFM)",
    "cmr": "PIDG w/o LPFM",
    "full": "PIDG (full)",
    "nostress": "PIDG w/o LPFM, no stress",
    "lpfm": "PIDG w/o CMR",
    "mlp": "MLP deformation",
    "mlp_cmr": "MLP deformation + L_CMR",
}


@dataclass(frozen=True)
class SuiteSpec:
    """One of the paper's tables: which scenes count, which rows, which protocol and metrics."""

    layout: str
    """Dataset kind whose folders are the suite's scenes (``pidg.data.dataset_layout``: dnerf, pidg, hypernerf)."""
    variants: tuple[str, ...]
    """Rows: keys of ABLATION_VARIANTS."""
    metrics: tuple[str, ...]
    """Quality columns per scene: psnr, ssim, ms_ssim, lpips_alex, lpips_vgg (ssim follows the suite's convention)."""
    options: dict[str, str] = field(default_factory=dict)
    """Config options every job of the suite gets (before the user's)."""
    protocol: Protocol = "interpolation"
    """interpolation: the dataset's test split; future: train up to data.train_until, predict the rest."""
    description: str = ""


SUITES: dict[str, SuiteSpec] = {
    "dnerf": SuiteSpec(
        "dnerf", ("base", "cmr", "nostress", "mlp", "mlp_cmr"), ("psnr", "ssim", "lpips_vgg"),
        {"data.background": "white"},
        description="D-NeRF synthetic scenes (paper Tab. 3 and supp. Tab. A5: PSNR, SSIM, LPIPS-VGG; the MLP "
        "rows are the CMR plug-in on a plain deformation network; no LPFM row: the captures jump between "
        "viewpoints, so the flow loss is refused there, as the paper leaves it out)",
    ),
    "pidg": SuiteSpec(
        "pidg", ("base", "cmr", "full", "nostress"), ("psnr", "ssim", "lpips_vgg"), {"data.background": "black"},
        description="PIDG-style physics scenes, monocular orbit (paper Tab. 1)",
    ),
    "hypernerf": SuiteSpec(
        "hypernerf", ("base", "cmr", "full"), ("psnr", "ms_ssim", "lpips_vgg"),
        description="HyperNeRF real captures, vrig split (paper Tab. 2: PSNR, MS-SSIM)",
    ),
    "future": SuiteSpec(
        "dnerf", ("base", "cmr", "mlp", "mlp_cmr"), ("psnr", "ssim", "lpips_vgg"),
        {"data.background": "white", "data.train_until": "0.8"}, protocol="future",
        description="future prediction on D-NeRF (paper Tab. 3 and supp. Tab. A6): train on t in [0, 0.8], "
        "predict t in (0.8, 1] with the deformation field, and (pidg's addition) by advecting the particles with "
        "the material field's velocity",
    ),
}


@dataclass(frozen=True)
class Job:
    """One scene x variant: everything a worker needs, as plain data (it crosses process and machine borders)."""

    scene: str
    variant: str
    config: dict[str, Any]
    """The resolved TrainConfig (variant, budget, data and output folder applied), as JSON."""
    protocol: Protocol = "interpolation"
    lpips_nets: tuple[str, ...] = ("alex", "vgg")
    integrator: str = "rk4"
    """Future protocol: the advection integrator (midpoint or rk4)."""

    @property
    def run_dir(self) -> Path:
        return Path(self.config["output"]["dir"])


def discover_scenes(root: Path | str, layout: str) -> list[Path]:
    """Dataset folders of ``layout`` in ``root`` (its sub-folders, or ``root`` itself when it is one), sorted."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder (give the folder that holds the suite's scenes)")
    candidates = [root] + sorted(p for p in root.iterdir() if p.is_dir())
    scenes = []
    for path in candidates:
        try:
            detect_format(path)
        except (ValueError, OSError):
            continue
        if dataset_layout(path) == layout:
            scenes.append(path)
    if not scenes:
        raise FileNotFoundError(f"{root}: no {layout} scene in it or in its sub-folders")
    return scenes if scenes[0] != root else [root]


def make_jobs(
    scenes: Sequence[Path], variants: Sequence[str | None], base: TrainConfig, out_root: Path, minutes: float | None,
    protocol: Protocol = "interpolation", downscale: str | None = None, integrator: str = "rk4",
    seeds: Sequence[int] | None = None,
) -> list[Job]:
    """One job per scene x variant (x seed): ``base`` + the variant's options, one budget (``minutes`` of training,
    or ``--optim.iterations`` without it), a run folder ``OUT/<scene>/<variant>``. ``seeds``: one job per seed in
    ``OUT/<scene>/<variant>/seed<S>`` (None: the base config's seed only)."""
    unknown = [v for v in variants if v is not None and v not in ABLATION_VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; known: {', '.join(ABLATION_VARIANTS)}")
    if protocol == "future" and base.data.train_until is None:
        raise ValueError("the future protocol needs data.train_until (the paper: 0.8)")
    nets = tuple(n for n in ("alex", "vgg") if lpips_weights_available((n,)))  # type: ignore[arg-type]
    jobs = []
    for scene in scenes:
        data = dataclasses.replace(base.data, path=Path(scene), progress=False)
        if downscale:
            data = dataclasses.replace(data, downscale=parse_downscale(downscale))
        for variant in variants:
            config = apply_overrides(base, ABLATION_VARIANTS[variant]) if variant else base
            for seed in seeds or [None]:
                run_dir = Path(out_root) / Path(scene).name / (variant or "") / ("" if seed is None else f"seed{seed}")
                optim = dataclasses.replace(config.optim, time_budget_minutes=minutes, seed=config.optim.seed if seed is None else seed)
                job_config = dataclasses.replace(config, data=data, optim=optim, output=dataclasses.replace(config.output, dir=run_dir))
                jobs.append(Job(str(scene), variant or "-", to_jsonable(job_config), protocol, nets, integrator))
    return jobs


def run_job(job: Job) -> list[dict[str, Any]]:
    """Train and evaluate one job; its rows (one, or one per predictor for future prediction). Never raises: a
    failure is a row with ``error`` (the traceback is in ``RUN/error.txt``)."""
    started = time.time()
    base_row = {"scene": Path(job.scene).name, "variant": job.variant, "protocol": job.protocol, "run_dir": str(job.run_dir),
                "seed": job.config["optim"]["seed"]}
    try:
        rows = _train_and_evaluate(job)
    except Exception as err:  # noqa: BLE001 - a failed job is reported in the table, the suite goes on
        text = f"{type(err).__name__}: {' '.join(str(err).split())}"
        logger.error("%s / %s failed: %s", base_row["scene"], job.variant, text)
        try:
            job.run_dir.mkdir(parents=True, exist_ok=True)
            (job.run_dir / "error.txt").write_text(traceback.format_exc())
        except OSError:
            pass
        rows = [{**base_row, "error": text}]
    provenance = {"git_commit": git_commit(), "machine": machine(), "config": job.config, "wall_seconds": time.time() - started}
    return [{**base_row, **row, **provenance} for row in rows]


def crashed_job(job: Job, message: str) -> list[dict[str, Any]]:
    """The row of a job whose worker died before it could report."""
    return [{"scene": Path(job.scene).name, "variant": job.variant, "protocol": job.protocol, "run_dir": str(job.run_dir),
             "seed": job.config["optim"]["seed"], "error": message, "git_commit": git_commit(), "config": job.config}]


def _train_and_evaluate(job: Job) -> list[dict[str, Any]]:
    config = from_jsonable(TrainConfig, job.config)
    scene = load_scene(config.data)
    claim_run_folder(config.output.dir, overwrite=True)  # a suite replaces its own earlier runs
    trainer = Trainer(config, scene)
    summary = trainer.train()
    model = trainer.model
    common = {
        "train_minutes": summary["train_minutes"],
        "iterations": summary["iterations"],
        "iterations_per_second": summary["iterations_per_second"],
        "gaussians": summary["gaussians"],
        "device": summary["device"],
        "peak_rss_mb": summary["peak_rss_mb"],
        "peak_gpu_memory_mb": summary.get("peak_gpu_memory_mb"),
        "cmr_final": summary.get("cmr_final"),
    }
    if config.needs_material_field:
        cache = trainer.flow_cache or open_flow_cache(trainer.scene, config.flow, config.output.dir / "flow_cache", progress=False)
        common.update(flow_end_point_errors(model, cache, config.flow))
    nets: tuple[NetName, ...] = tuple(job.lpips_nets)  # type: ignore[assignment]
    if job.protocol == "interpolation":
        metrics = evaluate_and_save(model, trainer.scene, config.output.dir, "test", nets, trainer.step)
        motion = {}
        if has_motion_gt(config.data.root):  # scored against the truth too (RUN/eval_test/motion_gt.json)
            motion = evaluate_motion_and_save(
                model, trainer.scene, config.output.dir, "test", flow=config.flow, flow_cache=trainer.flow_cache
            ).columns()
        return [{**common, **metrics["mean"], "render_fps": metrics["render_fps"], **motion}]
    t_last = max(f.time for f in trainer.scene.train)
    results = evaluate_future(
        model, trainer.scene.test, t_last, config.output.dir / "eval_future", nets, job.integrator  # type: ignore[arg-type]
    )
    return [
        {**common, **r["mean"], "render_fps": r["render_fps"], "predictor": name, "t_last": t_last}
        for name, r in results.items()
    ]


# ---- tables -------------------------------------------------------------------------------------------------------
METRIC_NAMES = {"psnr": "PSNR↑", "ssim": "SSIM↑", "ssim_zeros": "SSIM↑", "ms_ssim": "MS-SSIM↑",
                "lpips_alex": "LPIPS-A↓", "lpips_vgg": "LPIPS-V↓"}
LOWER_IS_BETTER = {"lpips_alex", "lpips_vgg"}
EFFICIENCY = (("train_minutes", "minutes", ".1f"), ("iterations_per_second", "it/s", ".2f"), ("gaussians", "Gaussians", ".0f"),
              ("peak_rss_mb", "peak RSS MB", ".0f"), ("peak_gpu_memory_mb", "peak GPU MB", ".0f"),
              ("render_fps", "render FPS", ".1f"))
#: Motion against ground-truth motion (scenes that carry it: pidg.evaluation.motion), mean over those scenes.
MOTION = (("gt_motion_flow_epe", "motion-flow EPE px", ".2f"), ("gt_velocity_flow_epe", "velocity-flow EPE px", ".2f"),
          ("gt_zero_motion_epe", "zero-motion EPE px", ".2f"), ("gt_velocity_rel_deformation", "3D velocity rel. error, deformation", ".3f"),
          ("gt_velocity_rel_field", "3D velocity rel. error, v", ".3f"), ("gt_coverage", "vertex coverage", ".3f"),
          ("gt_target_flow_epe", "flow-target EPE px (training pairs)", ".2f"),
          ("gt_track_rel", "3D tracking rel. error", ".3f"), ("gt_track_rel_seen", "3D tracking rel. error, seen Gaussians", ".3f"),
          ("gt_spin_rel", "rigid spin rel. error", ".3f"))
SSIM_NAMES = {"zeros": "SSIM: zero-padded Gaussian window (the 3DGS family's tables)",
              "valid": "SSIM: valid filtering (Wang et al. 2004, skimage)"}


def row_label(row: dict[str, Any]) -> str:
    label = VARIANT_LABELS.get(row["variant"], row["variant"])
    return f"{label} [{row['predictor']}]" if row.get("predictor") else label


def _metric_keys(metrics: Sequence[str], ssim: SSIMPadding) -> list[str]:
    return [SSIM_KEYS[ssim] if m == "ssim" else m for m in metrics]


def build_tables(rows: Sequence[dict[str, Any]], metrics: Sequence[str], ssim: SSIMPadding = "zeros") -> dict[str, Any]:
    """The paper's table as data: per method (variant, and predictor for future prediction) each scene's metrics and
    their average over the scenes, the best of each column, the mean efficiency figures, and the failed jobs.

    An average covers every scene: a method with a failed or missing scene has no average (``None``)."""
    keys = _metric_keys(metrics, ssim)
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = list(dict.fromkeys(row_label(r) for r in rows))
    good = [r for r in rows if not r.get("error")]
    cells: dict[str, dict[str, dict[str, float | None]]] = {m: {} for m in methods}
    for r in good:
        cells[row_label(r)][r["scene"]] = {k: r.get(k) for k in keys}
    average: dict[str, dict[str, float | None]] = {}
    for m in methods:
        per_scene = [cells[m].get(s) for s in scenes]
        average[m] = {
            k: (sum(c[k] for c in per_scene) / len(per_scene))  # type: ignore[index,misc]
            if all(c is not None and _finite(c.get(k)) for c in per_scene) else None
            for k in keys
        }
    best: dict[str, dict[str, float]] = {}
    for column in scenes + ["average"]:
        table = average if column == "average" else {m: cells[m].get(column) or {} for m in methods}
        best[column] = {}
        for k in keys:
            values = [v[k] for v in table.values() if _finite(v.get(k))]
            if values:
                best[column][k] = min(values) if k in LOWER_IS_BETTER else max(values)
    efficiency, motion = {}, {}
    for m in methods:
        mine = [r for r in good if row_label(r) == m]
        efficiency[m] = {k: _mean([r.get(k) for r in mine]) for k, _, _ in EFFICIENCY}
        motion[m] = {k: _mean([r.get(k) for r in mine]) for k, _, _ in MOTION}
    if not any(_finite(v) for values in motion.values() for v in values.values()):
        motion = {}  # no scene carries ground-truth motion: no such table
    failures = [{"scene": r["scene"], "method": row_label(r), "error": r["error"]} for r in rows if r.get("error")]
    return {"scenes": scenes, "methods": methods, "metrics": keys, "ssim": ssim, "cells": cells, "average": average,
            "best": best, "efficiency": efficiency, "motion": motion, "failures": failures}


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def _mean(values: Sequence[Any]) -> float | None:
    kept = [v for v in values if _finite(v)]
    return sum(kept) / len(kept) if kept else None


def _fmt(key: str, v: Any, best: float | None) -> tuple[str, bool]:
    """A cell's text and whether it is the best of its column (compared as printed, so ties are all bold)."""
    if not _finite(v):
        return "-", False
    text = f"{v:.2f}" if key == "psnr" else f"{v:.3f}"
    return text, best is not None and text == (f"{best:.2f}" if key == "psnr" else f"{best:.3f}")


Grid = tuple[list[str], list[list[tuple[str, bool]]]]
"""A table as (header, rows of (text, bold) cells); Markdown and HTML are two ways to print one."""


def quality_grid(tables: dict[str, Any]) -> Grid:
    """Quality per method: each scene's metrics and their average, the best of each column marked."""
    keys, columns = tables["metrics"], [*tables["scenes"], "average"]
    header = ["method"] + [f"{c} {METRIC_NAMES[k]}" for c in columns for k in keys]
    rows = []
    for m in tables["methods"]:
        cells = [(m, False)]
        for c in columns:
            cell = tables["average"][m] if c == "average" else tables["cells"][m].get(c) or {}
            cells += [_fmt(k, cell.get(k), tables["best"][c].get(k)) for k in keys]
        rows.append(cells)
    return header, rows


def efficiency_grid(tables: dict[str, Any]) -> Grid:
    """Mean training time, step rate, Gaussians, peak memory and render speed per method."""
    return _means_grid(tables["methods"], tables["efficiency"], EFFICIENCY)


def motion_grid(tables: dict[str, Any]) -> Grid:
    """Motion against ground-truth motion per method (mean over the scenes that carry it)."""
    return _means_grid(tables["methods"], tables["motion"], MOTION)


def _means_grid(methods: Sequence[str], means: dict[str, dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> Grid:
    header = ["method"] + [name for _, name, _ in columns]
    rows = []
    for m in methods:
        e = means[m]
        rows.append([(m, False)] + [(format(e[k], f) if _finite(e[k]) else "-", False) for k, _, f in columns])
    return header, rows


def grid_markdown(grid: Grid) -> list[str]:
    header, rows = grid
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    return lines + ["| " + " | ".join(f"**{t}**" if bold else t for t, bold in row) + " |" for row in rows]


def tables_markdown(tables: dict[str, Any], title: str, header: Sequence[str] = ()) -> str:
    """The tables as Markdown: quality per scene and average (best in bold), then efficiency, then failures."""
    lines = [f"# {title}", "", *header, f"{SSIM_NAMES[tables['ssim']]}. Best of each column in **bold**; "
             "an average needs every scene.", ""]
    lines += grid_markdown(quality_grid(tables))
    lines += ["", "Efficiency (mean over the method's scenes):", ""] + grid_markdown(efficiency_grid(tables))
    if tables.get("motion"):
        lines += ["", "Motion against ground-truth motion (mean over the scenes that carry it; EPE on visible dynamic "
                  "pixels, 3D velocity of the Gaussians nearest to the true vertices):", ""] + grid_markdown(motion_grid(tables))
    if tables["failures"]:
        lines += ["", "Failed jobs:", ""] + [f"- {f['scene']} / {f['method']}: {f['error']}" for f in tables["failures"]]
    return "\n".join(lines) + "\n"


# ---- the suite ----------------------------------------------------------------------------------------------------
def run_suite(
    name: str, data_root: Path, out_root: Path, base: TrainConfig, *, minutes: float | None, variants: Sequence[str] | None = None,
    scenes: Sequence[str] | None = None, downscale: str | None = None, ssim: SSIMPadding = "zeros",
    executor: Callable[..., None] = run_local, integrator: str = "rk4", log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run a named suite over the scenes in ``data_root`` and write ``OUT/suite.json`` and ``OUT/suite.md``.

    ``base`` should already carry the suite's options (:func:`suite_config` puts them in); ``executor`` runs the
    jobs (:mod:`pidg.bench.executors`; default: one after the other in this process) and hands over each job's rows
    as they arrive, so the files are rewritten as results come in."""
    spec = SUITES[name]
    found = discover_scenes(data_root, spec.layout)
    if scenes:
        missing = [s for s in scenes if s not in {p.name for p in found}]
        if missing:
            raise FileNotFoundError(f"{data_root}: no {spec.layout} scene named {', '.join(missing)} (found: "
                                    f"{', '.join(p.name for p in found)})")
        found = [p for p in found if p.name in scenes]
    jobs = make_jobs(found, list(variants or spec.variants), base, out_root, minutes, spec.protocol, downscale, integrator)
    out_root.mkdir(parents=True, exist_ok=True)
    log(f"suite {name}: {len(found)} scenes x {len(jobs) // max(len(found), 1)} variants = {len(jobs)} jobs -> {out_root}")
    rows: list[dict] = []
    budget = f"{minutes:g} min" if minutes else f"{base.optim.iterations} iterations"
    here = machine()
    header = [f"{spec.description}.", f"Budget per job: {budget}, seed {base.optim.seed}, commit {git_commit()}, "
              f"{here['platform']}, {here['cpu_model']} ({here['cpus']} CPUs, kernels for {here['cpu_target']}, "
              f"{here['vector_isa']}), GPU {here['gpu']}.", ""]

    def write(new_rows: list[dict]) -> None:
        rows.extend(new_rows)
        tables = build_tables(rows, spec.metrics, ssim)
        (out_root / "suite.json").write_text(json.dumps({"suite": name, "spec": dataclasses.asdict(spec), "ssim": ssim,
                                                         "tables": tables, "rows": rows}, indent=2, default=str))
        (out_root / "suite.md").write_text(tables_markdown(tables, f"pidg bench suite {name}", header))

    executor(jobs, run_job, crashed_job, write)
    text = (out_root / "suite.md").read_text()
    log(text)
    return json.loads((out_root / "suite.json").read_text())


def suite_config(name: str, base: TrainConfig, explicit: Sequence[str] = ()) -> TrainConfig:
    """``base`` with the suite's options, except those the user gave (``explicit`` option names) which win."""
    return apply_overrides(base, {k: v for k, v in SUITES[name].options.items() if k not in explicit})
