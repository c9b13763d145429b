"""Evaluate a trained model on a split: per-view and mean metrics, render speed, memory, pictures."""
from __future__ import annotations

import json
import logging
import math
import resource
import time
from pathlib import Path
from typing import Callable, Sequence

import torch
from tqdm import tqdm

from pidg.data.scene import Frame
from pidg.evaluation.images import colorize_scalar, save_png
from pidg.evaluation.metrics import compute_metrics
from pidg.render import RenderOutput

logger = logging.getLogger(__name__)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@torch.no_grad()
def evaluate_views(
    render: Callable[[Frame], RenderOutput],
    frames: Sequence[Frame],
    out_dir: Path | None = None,
    lpips_nets: tuple[str, ...] = ("alex", "vgg"),
    save_images: bool = True,
    progress: bool = True,
) -> dict:
    """Render every frame, compare with its image, and summarise.

    Render time is measured separately from metric time (LPIPS on CPU is far slower than rendering), as
    frames per second over the split. The caller decides which model is evaluated: never pick it with these
    numbers (test-set model selection is one of the reference code's defects).
    """
    per_view = []
    render_seconds = 0.0
    for i, frame in enumerate(tqdm(frames, desc="evaluating", disable=not progress)):
        t0 = time.perf_counter()
        out = render(frame)
        render_seconds += time.perf_counter() - t0
        pred = out.rgb.clamp(0, 1)
        metrics = compute_metrics(pred, frame.image, lpips_nets=lpips_nets)
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
        "peak_rss_mb": peak_rss_mb(),
        "per_view": per_view,
    }
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(result, indent=2))
    return result
