"""``pidg bench quality``: train and evaluate scenes x variants under one budget and seed, and print one table.

Variants are the paper's ablation rows, one flag apart (``--variants base cmr full``): every run of a bench uses
the same base config, seed and budget, so the rows differ only by the variant's options.

``--seeds``: every scene x variant once per seed, and a spread line per scene x variant (mean, sample standard
deviation, min-max over the seeds). A run is chaotic: two runs that differ in nothing but the seed (or in the
order of floating-point sums) end ~1 dB apart on D-NeRF (docs/cpu-quality.md), so a difference between two single
runs smaller than that spread says nothing.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any, Callable, Sequence

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
    seeds: Sequence[int] | None = None,
) -> list[dict]:
    """For each scene and variant (and seed): train with ``base`` + the variant's options, then evaluate the test
    split (the jobs of :mod:`pidg.bench.suite`, run here one after the other). With ``variants`` None the base config
    runs as given (one row per scene, variant "-"). Rows go to ``OUT/quality.json`` as they arrive; with several
    ``seeds``, their spread per scene and variant to ``OUT/quality_seeds.json``."""
    if seeds is not None and (not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0):
        raise ValueError(f"--seeds: distinct non-negative integers, got {list(seeds)}")
    jobs = make_jobs(scenes, variants or [None], base, out_root, minutes, downscale=downscale, seeds=seeds)
    rows: list[dict] = []

    def collect(new_rows: list[dict]) -> None:
        rows.extend(new_rows)
        log(format_table(rows))
        out_root.mkdir(parents=True, exist_ok=True)
        (out_root / "quality.json").write_text(json.dumps(rows, indent=2, default=str))
        if seeds and len(seeds) > 1:
            (out_root / "quality_seeds.json").write_text(json.dumps(seed_spread(rows), indent=2))

    run_local(jobs, run_job, crashed_job, collect)
    return rows


#: Columns against ground-truth motion, shown when a scene carries it (pidg.evaluation.motion): motion-flow,
#: velocity-flow and zero-motion EPE (px), relative 3D velocity error of the deformation and of v, vertex coverage,
#: the EPE (px) of the flow target LPFM trains against (training pairs), the 3D tracking relative error (of every
#: match, and of those whose Gaussian the anchor's view sees), and the rigid objects' spin relative error.
MOTION_COLUMNS = tuple((key, short, fmt) for (key, _, fmt), short in
                       zip(MOTION, ("gtEPE-m", "gtEPE-v", "gtEPE-0", "relV-def", "relV-v", "cover", "gtEPE-tgt", "track",
                                    "track-seen", "spin"), strict=True))


#: what the seed spread summarises: the image metrics, the run's cost and the motion columns
SPREAD_KEYS = ("psnr", "ssim", "lpips_alex", "lpips_vgg", "train_minutes", "gaussians", "velocity_flow_epe") + tuple(
    key for key, _, _ in MOTION_COLUMNS)


def seed_spread(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scene x variant with at least two finished seeds: for each of ``SPREAD_KEYS`` present, the mean, the sample
    standard deviation, min and max over the seeds (failed runs are left out and counted)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r.get("variant", "-")), []).append(r)
    out = []
    for (scene, variant), members in groups.items():
        done = [r for r in members if not r.get("error")]
        if len(done) < 2:
            continue
        entry: dict[str, Any] = {"scene": scene, "variant": variant, "seeds": [r.get("seed") for r in done],
                                 "failed": len(members) - len(done)}
        for key in SPREAD_KEYS:
            values = [float(r[key]) for r in done if isinstance(r.get(key), (int, float))]
            if len(values) >= 2:
                entry[key] = {"mean": statistics.fmean(values), "sd": statistics.stdev(values), "min": min(values), "max": max(values)}
        out.append(entry)
    return out


def _width(name: str) -> int:
    """A motion column's width: 9, or its name and a space where the name is longer."""
    return max(9, len(name) + 1)


def format_table(rows: list[dict]) -> str:
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "-"

    motion = any(k in r for r in rows for k, _, _ in MOTION_COLUMNS)  # a scene carries ground-truth motion
    lines = [
        f"{'scene':<15}{'variant':>9}{'PSNR':>8}{'SSIM':>8}{'LPIPS-A':>9}{'LPIPS-V':>9}{'min':>7}{'iters':>7}"
        f"{'it/s':>7}{'Gaussians':>10}{'CMR':>10}{'EPE-v':>8}"
        + ("".join(f"{name:>{_width(name)}}" for _, name, _ in MOTION_COLUMNS) if motion else "")
    ]
    several_seeds = len({r.get("seed") for r in rows}) > 1

    def label(r: dict) -> str:
        return f"{r.get('variant', '-')}" + (f"/s{r.get('seed')}" if several_seeds else "")

    for r in rows:
        if r.get("error"):
            lines.append(f"{r['scene']:<15}{label(r):>9}  failed: {r['error']}")
            continue
        lines.append(
            f"{r['scene']:<15}{label(r):>9}{f(r['psnr'], '.2f'):>8}{f(r['ssim'], '.4f'):>8}"
            f"{f(r.get('lpips_alex'), '.4f'):>9}{f(r.get('lpips_vgg'), '.4f'):>9}{f(r['train_minutes'], '.1f'):>7}"
            f"{r['iterations']:>7}{f(r['iterations_per_second'], '.2f'):>7}{r['gaussians']:>10}"
            f"{f(r.get('cmr_final'), '.3g'):>10}{f(r.get('velocity_flow_epe'), '.2f'):>8}"
            + ("".join(f"{f(r.get(k), fmt):>{_width(name)}}" for k, name, fmt in MOTION_COLUMNS) if motion else "")
        )
    for entry in seed_spread(rows):
        parts = [f"{key} {v['mean']:.4g} +- {v['sd']:.2g} ({v['min']:.4g}-{v['max']:.4g})" for key, v in entry.items()
                 if key in ("psnr", "ssim", "lpips_alex", "velocity_flow_epe", "gt_velocity_flow_epe") and isinstance(v, dict)]
        lines.append(f"  {entry['scene']} {entry['variant']}, {len(entry['seeds'])} seeds: " + ", ".join(parts))
    return "\n".join(lines)
