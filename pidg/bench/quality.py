"""``pidg bench quality``: train and evaluate scenes x variants under one budget and seed, and print one table.

Variants are the paper's ablation rows, one flag apart (``--variants base cmr full``): every run of a bench uses
the same base config, seed and budget, so the rows differ only by the variant's options.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable

from pidg.config_tools import apply_overrides
from pidg.data import load_scene
from pidg.data.scene import parse_downscale
from pidg.evaluation.evaluate import flow_end_point_errors
from pidg.flow import open_flow_cache
from pidg.metrics import NetName, lpips_weights_available
from pidg.pipeline import evaluate_and_save
from pidg.training.config import ABLATION_VARIANTS, TrainConfig
from pidg.training.run_folder import claim_run_folder
from pidg.training.trainer import Trainer


def run_quality_bench(
    scenes: list[Path],
    out_root: Path,
    base: TrainConfig,
    downscale: str | None = None,
    minutes: float | None = 30.0,
    variants: list[str] | None = None,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """For each scene and variant: train with ``base`` + the variant's options, then evaluate the test split.

    With ``variants`` None the base config runs as given (one row per scene, variant "-").
    """
    unknown = [v for v in variants or [] if v not in ABLATION_VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; known: {', '.join(ABLATION_VARIANTS)}")
    rows = []
    nets: tuple[NetName, ...] = tuple(n for n in ("alex", "vgg") if lpips_weights_available((n,)))  # type: ignore[misc]
    for path in scenes:
        data = dataclasses.replace(base.data, path=path, progress=False)
        if downscale:
            data = dataclasses.replace(data, downscale=parse_downscale(downscale))
        scene = load_scene(data)
        for variant in variants or [None]:
            run_dir = out_root / Path(path).name / (variant or "")
            config = apply_overrides(base, ABLATION_VARIANTS[variant]) if variant else base
            optim = dataclasses.replace(config.optim, time_budget_minutes=minutes)
            config = dataclasses.replace(
                config, data=data, optim=optim, output=dataclasses.replace(config.output, dir=run_dir)
            )
            claim_run_folder(run_dir, overwrite=True)  # a bench replaces its own earlier runs
            trainer = Trainer(config, scene)
            summary = trainer.train()
            flow_errors = {}
            if config.needs_material_field:
                cache = trainer.flow_cache or open_flow_cache(trainer.scene, config.flow, run_dir / "flow_cache", progress=False)
                flow_errors = flow_end_point_errors(trainer.model, cache, config.flow)
            metrics = evaluate_and_save(trainer.model, trainer.scene, run_dir, "test", nets, trainer.step)  # the model just trained
            row = {
                "scene": Path(path).name,
                "variant": variant or "-",
                **{k: metrics["mean"].get(k) for k in ("psnr", "ssim", "ms_ssim", "lpips_alex", "lpips_vgg")},
                "train_minutes": summary["train_minutes"],
                "iterations": summary["iterations"],
                "iterations_per_second": summary["iterations_per_second"],
                "gaussians": summary["gaussians"],
                "render_fps": metrics["render_fps"],
                "device": summary["device"],
                "peak_rss_mb": summary["peak_rss_mb"],
                "peak_gpu_memory_mb": summary.get("peak_gpu_memory_mb"),
                "step_breakdown_ms": summary["step_breakdown_ms"],
                "cmr_final": summary.get("cmr_final"),
                "velocity_flow_epe": flow_errors.get("velocity_flow_epe"),
                "gaussian_flow_epe": flow_errors.get("gaussian_flow_epe"),
                "target_flow_px": flow_errors.get("target_flow_px"),
            }
            rows.append(row)
            log(format_table(rows))
            (out_root / "quality.json").write_text(json.dumps(rows, indent=2))
    return rows


def format_table(rows: list[dict]) -> str:
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "-"

    lines = [
        f"{'scene':<15}{'variant':>9}{'PSNR':>8}{'SSIM':>8}{'LPIPS-A':>9}{'LPIPS-V':>9}{'min':>7}{'iters':>7}"
        f"{'it/s':>7}{'Gaussians':>10}{'CMR':>10}{'EPE-v':>8}"
    ]
    for r in rows:
        lines.append(
            f"{r['scene']:<15}{r.get('variant', '-'):>9}{f(r['psnr'], '.2f'):>8}{f(r['ssim'], '.4f'):>8}"
            f"{f(r['lpips_alex'], '.4f'):>9}{f(r['lpips_vgg'], '.4f'):>9}{f(r['train_minutes'], '.1f'):>7}"
            f"{r['iterations']:>7}{f(r['iterations_per_second'], '.2f'):>7}{r['gaussians']:>10}"
            f"{f(r.get('cmr_final'), '.3g'):>10}{f(r.get('velocity_flow_epe'), '.2f'):>8}"
        )
    return "\n".join(lines)
