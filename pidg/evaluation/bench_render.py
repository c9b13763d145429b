"""``pidg bench render``: speed and memory of the CPU kernel against the torch reference, in one run.

This machine class is shared and noisy, so absolute times drift; the ratios printed here are measured in the
same process, back to back, and are the figures to compare.
"""
from __future__ import annotations

import json
import os
import statistics
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import torch

from pidg.render import rasterize
from pidg.render.projection import project_gaussians
from pidg.render.rasterize_cpu import bin_gaussians, count_pixel_gaussian_pairs
from pidg.render.scenes import GaussianScene, orbit_camera, random_scene


@dataclass
class RenderBenchCase:
    name: str
    n_gaussians: int
    size: int  # square image side
    run_reference: bool = True


@dataclass
class RenderBenchConfig:
    cases: list[RenderBenchCase] = field(
        default_factory=lambda: [
            RenderBenchCase("a", 2_000, 128),
            RenderBenchCase("b", 20_000, 256),
            RenderBenchCase("c", 100_000, 512, run_reference=False),
        ]
    )
    repeats: int = 7
    reference_repeats: int = 3
    feature_channels: tuple[int, ...] = (0, 8, 32)  # C sweep on case b, kernel only
    seed: int = 0


class PeakRSS:
    """Peak resident memory above the level at entry, sampled every millisecond in a background thread.

    torch's CPU allocations are invisible to tracemalloc, so the process RSS is the honest measure.
    """

    def __init__(self) -> None:
        self.peak = 0
        self._stop = threading.Event()

    @staticmethod
    def _rss() -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self) -> "PeakRSS":
        self.base = self._rss()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss() - self.base)
            time.sleep(0.001)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss() - self.base)


def _median_time(fn: Callable[[], None], repeats: int) -> tuple[float, int]:
    """Median wall time (s) over ``repeats`` calls after one warm-up, and the peak RSS growth (bytes)."""
    fn()
    times = []
    with PeakRSS() as mem:
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return statistics.median(times), mem.peak


def _render_fns(scene: GaussianScene, size: int, backend: str) -> tuple[Callable[[], None], Callable[[], None]]:
    camera = orbit_camera(size, size)
    params = [t.detach().clone().requires_grad_(True) for t in scene.params()]
    means, quats, scales, opacities, colors, *rest = params
    features = rest[0] if rest else None
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))

    def render():
        return rasterize(means, quats, opacities, colors, camera, scales=scales, features=features, backend=backend)

    def forward() -> None:
        with torch.no_grad():
            render()

    def forward_backward() -> None:
        out = render()
        loss = (out.rgb * weights).sum() + out.depth.mean() + (out.features.sum() if out.features is not None else 0.0)
        loss.backward()
        for p in params:
            p.grad = None

    return forward, forward_backward


def _composite_fn(scene: GaussianScene, size: int, backend: str) -> Callable[[], None]:
    """Compositing alone (binning, forward, backward) on fixed projection results: what the kernel replaces."""
    from pidg.render.rasterize_cpu import composite_cpu
    from pidg.render.rasterize_torch import composite_reference

    camera = orbit_camera(size, size)
    with torch.no_grad():
        proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    feats = torch.cat([scene.colors, proj.depths.unsqueeze(-1)] + ([scene.features] if scene.features is not None else []), -1)
    leaves = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, scene.opacities, feats)]
    composite = composite_cpu if backend == "cpu" else composite_reference
    weights = torch.rand(size, size, feats.shape[1], generator=torch.Generator().manual_seed(1))

    def forward_backward() -> None:
        image, alpha = composite(*leaves, proj.depths, proj.radii, size, size)
        ((image * weights).sum() + alpha.sum()).backward()
        for t in leaves:
            t.grad = None

    return forward_backward


def _pairs(scene: GaussianScene, size: int) -> tuple[int, int]:
    camera = orbit_camera(size, size)
    with torch.no_grad():
        proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, size, size)
    return count_pixel_gaussian_pairs(bins, size, size), bins.num_intersections


def run_render_bench(config: RenderBenchConfig, out_path: Path | None = None, log: Callable[[str], None] = print) -> dict:
    """Run every case and print a table; returns (and optionally writes) the figures as a dict."""
    log("fwd, fwd+bwd: a whole rasterize() call (projection in torch autograd + compositing);"
        " composite: binning + compositing forward + backward alone, the part the kernel implements")
    log(f"torch threads: {torch.get_num_threads()}, numba threads: {_numba_threads()}, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    rows = []
    header = (f"{'case':<5}{'N':>8}{'px':>6}{'pairs':>12}{'backend':>9}{'fwd ms':>9}{'fwd+bwd ms':>12}{'peak MB':>9}"
              f"{'composite f+b ms':>18}{'ratio ref/kernel: f+b':>23}{'composite':>11}")
    log(header)
    for case in config.cases:
        camera = orbit_camera(case.size, case.size)
        scene = random_scene(case.n_gaussians, camera, seed=config.seed)
        pairs, isects = _pairs(scene, case.size)
        row = {"case": case.name, "n_gaussians": case.n_gaussians, "size": case.size, "pixel_gaussian_pairs": pairs, "intersections": isects}
        for backend in ("cpu", "torch"):
            if backend == "torch" and not case.run_reference:
                row["torch"] = None
                log(f"{case.name:<5}{case.n_gaussians:>8}{case.size:>6}{pairs:>12}{'torch':>9}   skipped (the reference is too slow at this size)")
                continue
            reps = config.repeats if backend == "cpu" else config.reference_repeats
            fwd, fwd_bwd = _render_fns(scene, case.size, backend)
            t_fwd, _ = _median_time(fwd, reps)
            t_fb, peak = _median_time(fwd_bwd, reps)
            t_comp, _ = _median_time(_composite_fn(scene, case.size, backend), reps)
            row[backend] = {
                "forward_ms": 1e3 * t_fwd,
                "forward_backward_ms": 1e3 * t_fb,
                "composite_forward_backward_ms": 1e3 * t_comp,
                "peak_mb": peak / 2**20,
            }
            ratios = ("", "")
            if backend == "torch":
                row["ratio_reference_over_kernel"] = row["torch"]["forward_backward_ms"] / row["cpu"]["forward_backward_ms"]
                row["ratio_reference_over_kernel_composite"] = (
                    row["torch"]["composite_forward_backward_ms"] / row["cpu"]["composite_forward_backward_ms"]
                )
                ratios = (f"{row['ratio_reference_over_kernel']:.1f}x", f"{row['ratio_reference_over_kernel_composite']:.1f}x")
            log(f"{case.name:<5}{case.n_gaussians:>8}{case.size:>6}{pairs:>12}{backend:>9}{1e3 * t_fwd:>9.1f}{1e3 * t_fb:>12.1f}"
                f"{peak / 2**20:>9.1f}{1e3 * t_comp:>18.1f}{ratios[0]:>23}{ratios[1]:>11}")
        rows.append(row)

    scaling = _scaling(rows)
    if scaling:
        log(f"scaling {scaling['from']}->{scaling['to']}: pairs x{scaling['pairs_ratio']:.2f}, kernel fwd+bwd time x{scaling['time_ratio']:.2f}"
            f" ({'OK' if scaling['time_ratio'] <= scaling['pairs_ratio'] else 'SLOWER than the pairs'})")

    sweep = []
    base_case = next((c for c in config.cases if c.name == "b"), config.cases[0])
    camera = orbit_camera(base_case.size, base_case.size)
    for n_feat in config.feature_channels:
        scene = random_scene(base_case.n_gaussians, camera, n_features=n_feat, seed=config.seed)
        _, fwd_bwd = _render_fns(scene, base_case.size, "cpu")
        t_fb, _ = _median_time(fwd_bwd, config.repeats)
        sweep.append({"channels": n_feat, "forward_backward_ms": 1e3 * t_fb})
        log(f"extra feature channels C={n_feat:>3} at case {base_case.name}: kernel fwd+bwd {1e3 * t_fb:.1f} ms")
    result = {"config": asdict(config), "rows": rows, "scaling": scaling, "feature_sweep": sweep}
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(result, indent=2))
        log(f"wrote {out_path}")
    return result


def _scaling(rows: list[dict]) -> dict | None:
    named = {r["case"]: r for r in rows}
    if "b" not in named or "c" not in named:
        return None
    b, c = named["b"], named["c"]
    return {
        "from": "b",
        "to": "c",
        "pairs_ratio": c["pixel_gaussian_pairs"] / b["pixel_gaussian_pairs"],
        "time_ratio": c["cpu"]["forward_backward_ms"] / b["cpu"]["forward_backward_ms"],
    }


def _numba_threads() -> int:
    import numba

    return numba.get_num_threads()
