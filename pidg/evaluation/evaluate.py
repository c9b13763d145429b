"""Evaluate a scene model on a split: per-view and mean metrics, render speed, memory, pictures; and the errors of
its rendered flows against the flow targets of the training pairs."""
from __future__ import annotations

import json
import logging
import math
import time
from collections import defaultdict
from pathlib import Path
from typing import Callable, Sequence

import torch
from tqdm import tqdm

from pidg.data.scene import Frame
from pidg.device import peak_memory_mb, synchronize
from pidg.evaluation.charts import svg_chart
from pidg.evaluation.images import colorize_scalar, save_png
from pidg.flow import FlowCache, FlowConfig, render_pair_flows
from pidg.metrics import NetName, compute_metrics
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render import RenderOutput

logger = logging.getLogger(__name__)


@torch.no_grad()
def evaluate_views(
    render: Callable[[Frame], RenderOutput],
    frames: Sequence[Frame],
    out_dir: Path | None = None,
    lpips_nets: tuple[str, ...] = ("alex", "vgg"),
    save_images: bool = True,
    progress: bool = True,
    device: torch.device | None = None,
) -> dict:
    """Render every frame, compare with its image, and summarise.

    Render time is measured separately from metric time (LPIPS on CPU is far slower than rendering), as
    frames per second over the split. The caller decides which model is evaluated: never pick it with these
    numbers (test-set model selection is one of the reference code's defects). On CUDA the render time waits for
    the GPU. Memory: peak resident memory, and on CUDA peak GPU memory, of the process so far.
    """
    per_view = []
    render_seconds = 0.0
    device = device or (frames[0].image_u8.device if frames else torch.device("cpu"))  # where render() computes
    for i, frame in enumerate(tqdm(frames, desc="evaluating", disable=not progress)):
        synchronize(device)
        t0 = time.perf_counter()
        out = render(frame)
        synchronize(device)
        render_seconds += time.perf_counter() - t0
        pred = out.rgb.clamp(0, 1)
        metrics = compute_metrics(pred, frame.image.to(pred.device), lpips_nets=lpips_nets)
        per_view.append({"view": frame.name or str(i), "time": frame.time, **metrics})
        if out_dir is not None and save_images:
            stem = (frame.name or f"{i:04d}").replace("/", "_")
            save_png(pred, out_dir / "renders" / f"{stem}.png")
            save_png(frame.image, out_dir / "gt" / f"{stem}.png")
            save_png(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5), out_dir / "depth" / f"{stem}.png")
    keys = [k for k in per_view[0] if k not in ("view", "time")] if per_view else []
    mean = {}
    for key in keys:
        values = [v[key] for v in per_view if v[key] is not None and math.isfinite(v[key])]
        mean[key] = sum(values) / len(values) if values else None
    result = {
        "views": len(per_view),
        "mean": mean,
        "render_fps": len(per_view) / max(render_seconds, 1e-9),
        **peak_memory_mb(device),
        "per_view": per_view,
    }
    return result


def evaluate_model(
    model: DynamicGaussians, frames: Sequence[Frame], out_dir: Path | None = None,
    lpips_nets: tuple[NetName, ...] = ("alex", "vgg"), info: dict | None = None, progress: bool = True,
) -> dict:
    """:func:`evaluate_views` of the model's renders at each frame's camera and time, with its Gaussian count and
    ``info`` (facts to keep beside the metrics, e.g. the training steps); with ``out_dir``, the renders, ground
    truth and depth pictures, ``metrics.json`` and ``psnr_over_time.svg`` (:func:`psnr_over_time_chart`) go there."""
    result = evaluate_views(
        lambda frame: model.render(frame.camera, frame.time), frames, out_dir, lpips_nets, progress=progress, device=model.device
    )
    result.update(gaussians=model.num_gaussians, **(info or {}))
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(result, indent=2))
        (out_dir / "psnr_over_time.svg").write_text(psnr_over_time_chart(result["per_view"]))
    return result


def psnr_over_time_chart(per_view: Sequence[dict]) -> str:
    """Each view's PSNR (dB) against its time, in time order, as an SVG line chart: where in the recording a model is
    weak shows at a glance (on D-NeRF's bouncingballs, a fall learnt a frame or two late was a dip at t < 0.25,
    on the training views too)."""
    points = sorted((float(v["time"]), float(v["psnr"])) for v in per_view
                    if v.get("psnr") is not None and math.isfinite(v["psnr"]))
    return svg_chart({"PSNR of each view": points}, "time t (the dataset's, in [0, 1])", "PSNR (dB)",
                     empty_note="no view was scored")


@torch.no_grad()
def flow_end_point_errors(model: DynamicGaussians, cache: FlowCache, config: FlowConfig) -> dict[str, float]:
    """Mean end-point error (pixels) of the rendered Gaussian flow and velocity flow against flow_gt over all
    consecutive training pairs (supervised pixels only), and the target's mean size. The velocity flow needs a
    material field (absent in the no-physics, no-flow model)."""
    sums: dict[str, float] = defaultdict(float)
    pixels = 0
    for k in range(len(cache)):
        _, _, result = render_pair_flows(model, cache.pair(k), config)
        n = result.valid_pixels
        pixels += n
        sums["gaussian_flow_epe"] += result.epe_gaussian * n
        if result.epe_velocity is not None:
            sums["velocity_flow_epe"] += result.epe_velocity * n
        sums["target_flow_px"] += result.mean_target_px * n
    return {k: v / max(pixels, 1) for k, v in sums.items()} | {"flow_supervised_pixels": float(pixels)}
