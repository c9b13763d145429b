"""``pidg bench quality``: train and evaluate scenes x variants under one budget and seed, and print one table.

Variants are the paper's ablation rows, one flag apart (``--variants base cmr full``): every run of a bench uses
the same base config, seed and budget, so the rows differ only by the variant's options.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from pidg.bench.executors import run_local
from pidg.bench.suite import MOTION, crashed_job, make_jobs, run_job
from pidg.training.config import TrainConfig


def run_quality_bench(
    scenes: list[Path],
    out_root: Path,
    base: TrainConfig,
    downscale: str | None = None,
    minutes: float | None = 30.0,
    variants: list[str] | None = None,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """For each scene and variant: train with ``base`` + the variant's options, then evaluate the test split (the
    jobs of :mod:`pidg.bench.suite`, run here one after the other). With ``variants`` None the base config runs
    as given (one row per scene, variant "-"). Rows go to ``OUT/quality.json`` as they arrive."""
    jobs = make_jobs(scenes, variants or [None], base, out_root, minutes, downscale=downscale)
    rows: list[dict] = []

    def collect(new_rows: list[dict]) -> None:
        rows.extend(new_rows)
        log(format_table(rows))
        out_root.mkdir(parents=True, exist_ok=True)
        (out_root / "quality.json").write_text(json.dumps(rows, indent=2, default=str))

    run_local(jobs, run_job, crashed_job, collect)
    return rows


#: Columns against ground-truth motion, shown when a scene carries it (pidg.evaluation.motion): motion-flow,
#: velocity-flow and zero-motion EPE (px), relative 3D velocity error of the deformation and of v, vertex coverage,
#: and the EPE (px) of the flow target LPFM trains against (training pairs).
MOTION_COLUMNS = tuple((key, short, fmt) for (key, _, fmt), short in
                       zip(MOTION, ("gtEPE-m", "gtEPE-v", "gtEPE-0", "relV-def", "relV-v", "cover", "gtEPE-tgt"), strict=True))


def format_table(rows: list[dict]) -> str:
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "-"

    motion = any(k in r for r in rows for k, _, _ in MOTION_COLUMNS)  # a scene carries ground-truth motion
    lines = [
        f"{'scene':<15}{'variant':>9}{'PSNR':>8}{'SSIM':>8}{'LPIPS-A':>9}{'LPIPS-V':>9}{'min':>7}{'iters':>7}"
        f"{'it/s':>7}{'Gaussians':>10}{'CMR':>10}{'EPE-v':>8}" + ("".join(f"{name:>9}" for _, name, _ in MOTION_COLUMNS) if motion else "")
    ]
    for r in rows:
        if r.get("error"):
            lines.append(f"{r['scene']:<15}{r.get('variant', '-'):>9}  failed: {r['error']}")
            continue
        lines.append(
            f"{r['scene']:<15}{r.get('variant', '-'):>9}{f(r['psnr'], '.2f'):>8}{f(r['ssim'], '.4f'):>8}"
            f"{f(r.get('lpips_alex'), '.4f'):>9}{f(r.get('lpips_vgg'), '.4f'):>9}{f(r['train_minutes'], '.1f'):>7}"
            f"{r['iterations']:>7}{f(r['iterations_per_second'], '.2f'):>7}{r['gaussians']:>10}"
            f"{f(r.get('cmr_final'), '.3g'):>10}{f(r.get('velocity_flow_epe'), '.2f'):>8}"
            + ("".join(f"{f(r.get(k), fmt):>9}" for k, _, fmt in MOTION_COLUMNS) if motion else "")
        )
    return "\n".join(lines)
