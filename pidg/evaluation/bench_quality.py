"""``pidg bench quality``: train and evaluate a list of scenes under one budget, and print one table."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable

from pidg.data import load_scene
from pidg.data.scene import parse_downscale
from pidg.evaluation.lpips import lpips_weights_available
from pidg.training.config import TrainConfig


def run_quality_bench(
    scenes: list[Path],
    out_root: Path,
    base: TrainConfig,
    downscale: str | None = None,
    minutes: float | None = 30.0,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """For each scene: train with ``base`` (same seed and budget for all), evaluate its test split."""
    from pidg.pipeline import evaluate_run
    from pidg.training.trainer import Trainer

    rows = []
    nets = tuple(n for n in ("alex", "vgg") if lpips_weights_available((n,)))
    for path in scenes:
        data = dataclasses.replace(base.data, path=path, progress=False)
        if downscale:
            data = dataclasses.replace(data, downscale=parse_downscale(downscale))
        run_dir = out_root / Path(path).name
        optim = dataclasses.replace(base.optim, time_budget_minutes=minutes)
        config = dataclasses.replace(base, data=data, optim=optim, output=dataclasses.replace(base.output, dir=run_dir))
        summary = Trainer(config, load_scene(data)).train()
        metrics = evaluate_run(run_dir, "test", lpips_nets=nets)
        row = {
            "scene": Path(path).name,
            **{k: metrics["mean"].get(k) for k in ("psnr", "ssim", "ms_ssim", "lpips_alex", "lpips_vgg")},
            "train_minutes": summary["train_minutes"],
            "iterations": summary["iterations"],
            "iterations_per_second": summary["iterations_per_second"],
            "gaussians": summary["gaussians"],
            "step_breakdown_ms": summary["step_breakdown_ms"],
        }
        rows.append(row)
        log(format_table(rows))
    (out_root / "quality.json").write_text(json.dumps(rows, indent=2))
    return rows


def format_table(rows: list[dict]) -> str:
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "-"

    lines = [f"{'scene':<16}{'PSNR':>8}{'SSIM':>8}{'LPIPS-A':>9}{'LPIPS-V':>9}{'min':>7}{'iters':>8}{'it/s':>7}{'Gaussians':>11}"]
    for r in rows:
        lines.append(
            f"{r['scene']:<16}{f(r['psnr'], '.2f'):>8}{f(r['ssim'], '.4f'):>8}{f(r['lpips_alex'], '.4f'):>9}"
            f"{f(r['lpips_vgg'], '.4f'):>9}{f(r['train_minutes'], '.1f'):>7}{r['iterations']:>8}"
            f"{f(r['iterations_per_second'], '.2f'):>7}{r['gaussians']:>11}"
        )
    return "\n".join(lines)
