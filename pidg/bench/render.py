"""``pidg bench render``: speed and memory of the CPU kernel against the torch reference, in one run.

This machine class is shared and noisy, so absolute times drift; the ratios printed here are measured in the
same process, back to back, and are the figures to compare.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import torch

from pidg.bench.provenance import git_commit, machine, machine_line
from pidg.bench.timing import interleaved_medians, peak_rss_growth_mib
from pidg.render import rasterize
from pidg.render.projection import TILE_SIZE, project_gaussians, tile_grid, tiles_touched
from pidg.render.rasterize_cpu import bin_gaussians, composite_cpu, count_pixel_gaussian_pairs
from pidg.render.rasterize_torch import composite_reference
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
    feature_tile_share: float = 0.05
    """The sweep also renders its first C > 0 read at a centred square of about this share of the 16x16 tiles only
    (``feature_pixels``), as the flow loss reads its features: the render pays for those tiles' features only."""
    seed: int = 0


def _peak_memory_mb(n_gaussians: int, size: int, seed: int, backend: str) -> float:
    """Peak RSS growth (MiB) over one forward+backward in a fresh process (NaN if the probe fails)."""
    setup = (
        "from pidg.bench.render import _render_fns\n"
        "from pidg.render.scenes import orbit_camera, random_scene\n"
        "small = random_scene(50, orbit_camera(32, 32), seed=0)\n"
        f"_render_fns(small, 32, '{backend}')[1]()  # load kernels before the baseline\n"
        f"scene = random_scene({n_gaussians}, orbit_camera({size}, {size}), seed={seed})\n"
        f"fwd, fwd_bwd = _render_fns(scene, {size}, '{backend}')\n"
    )
    try:
        return peak_rss_growth_mib(setup, "fwd_bwd()")
    except RuntimeError:
        return float("nan")


def _render_fns(
    scene: GaussianScene, size: int, backend: str, feature_pixels: torch.Tensor | None = None
) -> tuple[Callable[[], None], Callable[[], None]]:
    """Forward, and forward + backward of a loss on every output, of ``rasterize`` (its features read at
    ``feature_pixels`` only when given)."""
    camera = orbit_camera(size, size)
    params = [t.detach().clone().requires_grad_(True) for t in scene.params()]
    means, quats, scales, opacities, colors, *rest = params
    features = rest[0] if rest else None
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))

    def render():
        return rasterize(means, quats, opacities, colors, camera, scales=scales, features=features, backend=backend,
                         feature_pixels=feature_pixels)

    def forward() -> None:
        with torch.no_grad():
            render()

    def forward_backward() -> None:
        out = render()
        features_read = out.features if feature_pixels is None or out.features is None else out.features[feature_pixels]
        loss = (out.rgb * weights).sum() + out.depth.mean() + (features_read.sum() if features_read is not None else 0.0)
        loss.backward()
        for p in params:
            p.grad = None

    return forward, forward_backward


def _composite_fn(scene: GaussianScene, size: int, backend: str) -> Callable[[], None]:
    """Compositing alone (binning, forward, backward) on fixed projection results: what the kernel replaces."""
    camera = orbit_camera(size, size)
    with torch.no_grad():
        proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    feats = torch.cat([scene.colors, proj.depths.unsqueeze(-1)] + ([scene.features] if scene.features is not None else []), -1)
    leaves = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, scene.opacities, feats)]
    composite = composite_cpu if backend == "cpu" else composite_reference
    weights = torch.rand(size, size, feats.shape[1], generator=torch.Generator().manual_seed(1))

    def forward_backward() -> None:
        image, alpha, _ = composite(*leaves, proj.depths, proj.radii, size, size)
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
    log("fwd, fwd+bwd: a whole rasterize() call (projection in torch autograd + compositing).")
    log("composite: binning + compositing forward + backward alone, on fixed projections: the part the kernel implements.")
    log("Times are medians of interleaved repetitions; peak MB is the RSS growth of one fwd+bwd in a fresh process.")
    here, commit = machine(), git_commit()
    log(machine_line(here, commit))
    header = (f"{'case':<5}{'N':>8}{'px':>6}{'pairs':>12}{'backend':>9}{'fwd ms':>9}{'fwd+bwd ms':>12}"
              f"{'composite ms':>14}{'peak MB':>9}")
    log(header)
    rows = []
    for case in config.cases:
        camera = orbit_camera(case.size, case.size)
        scene = random_scene(case.n_gaussians, camera, seed=config.seed)
        pairs, isects = _pairs(scene, case.size)
        row: dict = {"case": case.name, "n_gaussians": case.n_gaussians, "size": case.size, "pixel_gaussian_pairs": pairs, "intersections": isects}
        backends = ["cpu", "torch"] if case.run_reference else ["cpu"]
        fns, reps = {}, {}
        for backend in backends:
            fwd, fwd_bwd = _render_fns(scene, case.size, backend)
            n = config.repeats if backend == "cpu" else config.reference_repeats
            fns.update({f"{backend}/fwd": fwd, f"{backend}/fwd_bwd": fwd_bwd, f"{backend}/composite": _composite_fn(scene, case.size, backend)})
            reps.update({f"{backend}/fwd": n, f"{backend}/fwd_bwd": n, f"{backend}/composite": n})
        med = interleaved_medians(fns, reps)
        for backend in backends:
            peak = _peak_memory_mb(case.n_gaussians, case.size, config.seed, backend)
            row[backend] = {
                "forward_ms": 1e3 * med[f"{backend}/fwd"],
                "forward_backward_ms": 1e3 * med[f"{backend}/fwd_bwd"],
                "composite_forward_backward_ms": 1e3 * med[f"{backend}/composite"],
                "peak_mb": peak,
            }
            r = row[backend]
            log(f"{case.name:<5}{case.n_gaussians:>8}{case.size:>6}{pairs:>12}{backend:>9}{r['forward_ms']:>9.1f}"
                f"{r['forward_backward_ms']:>12.1f}{r['composite_forward_backward_ms']:>14.1f}{peak:>9.1f}")
        if case.run_reference:
            row["ratio_reference_over_kernel"] = row["torch"]["forward_backward_ms"] / row["cpu"]["forward_backward_ms"]
            row["ratio_reference_over_kernel_composite"] = (
                row["torch"]["composite_forward_backward_ms"] / row["cpu"]["composite_forward_backward_ms"]
            )
            log(f"      case {case.name}: reference / kernel, same run: whole rasterize fwd+bwd "
                f"{row['ratio_reference_over_kernel']:.1f}x, compositing fwd+bwd {row['ratio_reference_over_kernel_composite']:.1f}x")
        else:
            row["torch"] = None
            log(f"{case.name:<5}{case.n_gaussians:>8}{case.size:>6}{pairs:>12}{'torch':>9}   skipped (the reference is too slow at this size)")
        rows.append(row)

    scaling = _scaling(config, rows, log)
    sweep = _feature_sweep(config, log)
    result = {"config": asdict(config), "git_commit": commit, "machine": here, "rows": rows, "scaling": scaling,
              "feature_sweep": sweep}
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(result, indent=2))
        log(f"wrote {out_path}")
    return result


def _feature_sweep(config: RenderBenchConfig, log: Callable[[str], None]) -> list[dict]:
    """Kernel fwd+bwd at case b for several extra-channel counts C, interleaved."""
    base_case = next((c for c in config.cases if c.name == "b"), config.cases[0])
    camera = orbit_camera(base_case.size, base_case.size)
    fns: dict[tuple[int, float], Callable[[], None]] = {}
    for n_feat in config.feature_channels:
        scene = random_scene(base_case.n_gaussians, camera, n_features=n_feat, seed=config.seed)
        fns[(n_feat, 1.0)] = _render_fns(scene, base_case.size, "cpu")[1]
    sparse = next((c for c in config.feature_channels if c > 0), None)
    if sparse is not None and config.feature_tile_share < 1:
        pixels = _centre_tiles(base_case.size, config.feature_tile_share)
        share = float(tiles_touched(pixels, TILE_SIZE).float().mean())
        scene = random_scene(base_case.n_gaussians, camera, n_features=sparse, seed=config.seed)
        fns[(sparse, share)] = _render_fns(scene, base_case.size, "cpu", feature_pixels=pixels)[1]
    med = interleaved_medians(fns, {k: config.repeats for k in fns})
    sweep = [{"channels": c, "tile_share": share, "forward_backward_ms": 1e3 * t} for (c, share), t in med.items()]
    log(f"extra feature channels at case {base_case.name} (kernel fwd+bwd): "
        + ", ".join(f"C={c}{'' if share == 1 else f' on {100 * share:.0f}% of the tiles'}: {1e3 * t:.1f} ms"
                    for (c, share), t in med.items()))
    return sweep


def _centre_tiles(size: int, share: float) -> torch.Tensor:
    """[size, size] bool: every pixel of a centred square of about ``share`` of the image's tiles (at least one)."""
    tiles, _ = tile_grid(size, size, TILE_SIZE)
    side = max(1, round((share * tiles * tiles) ** 0.5))
    lo = (tiles - side) // 2 * TILE_SIZE
    pixels = torch.zeros(size, size, dtype=torch.bool)
    pixels[lo:lo + side * TILE_SIZE, lo:lo + side * TILE_SIZE] = True
    return pixels


def _scaling(config: RenderBenchConfig, rows: list[dict], log: Callable[[str], None]) -> dict | None:
    """Kernel fwd+bwd time ratio from case b to case c against their ratio of pixel-Gaussian pairs, with the
    two cases measured interleaved so that a change of machine load between them cannot fake the result."""
    named = {c.name: c for c in config.cases}
    if "b" not in named or "c" not in named:
        return None
    fns = {}
    for name in ("b", "c"):
        case = named[name]
        scene = random_scene(case.n_gaussians, orbit_camera(case.size, case.size), seed=config.seed)
        fns[name] = _render_fns(scene, case.size, "cpu")[1]
    med = interleaved_medians(fns, {"b": config.repeats, "c": config.repeats})
    pairs = {r["case"]: r["pixel_gaussian_pairs"] for r in rows}
    out = {"from": "b", "to": "c", "pairs_ratio": pairs["c"] / pairs["b"], "time_ratio": med["c"] / med["b"],
           "b_ms": 1e3 * med["b"], "c_ms": 1e3 * med["c"]}
    verdict = "OK: no faster than the pairs" if out["time_ratio"] <= out["pairs_ratio"] else "SLOWER than the pairs"
    log(f"scaling b->c (interleaved): pairs x{out['pairs_ratio']:.2f}, kernel fwd+bwd time x{out['time_ratio']:.2f} "
        f"({out['b_ms']:.1f} -> {out['c_ms']:.1f} ms): {verdict}")
    return out

