"""Forward + backward speed of Grid4D's hash grids: the numba kernel against the torch reference, interleaved.

``python -m pidg.bench.hash_grid`` prints median seconds per case and the kernel's speed-up.
"""
from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from pidg.bench.provenance import git_commit, machine, machine_line
from pidg.models.deformation.hash_grid import GRID4D_SPATIAL, GRID4D_TEMPORAL, HashGrid, HashGridBackend, hash_encode


def _fwd_bwd_seconds(grids: list[HashGrid], coords: list[Tensor], weights: list[Tensor], backend: HashGridBackend) -> float:
    """Seconds of one forward + backward of all grids (w.r.t. the tables, and coords if they require grad)."""
    for g in grids:
        g.table.grad = None
    start = time.perf_counter()
    loss = sum((hash_encode(c, g.table, g.layout, backend) * w).sum() for g, c, w in zip(grids, coords, weights))
    loss.backward()  # type: ignore[union-attr]
    return time.perf_counter() - start


def bench_hash_grid(n_points: int = 20_000, repeats: int = 3, seed: int = 0) -> dict[str, float]:
    """Forward + backward of Grid4D's four grids at ``n_points``: numba kernel vs torch reference.

    The machine this was written on is shared and its capacity swings between one and two cores, so kernel and
    reference runs are interleaved and the speed-up is the ratio of their medians in the same run. Prints and
    returns median seconds per case (kernel: spatial grid, the three temporal grids, all four, all four with
    coordinate gradients; reference: all four) and the speed-up.
    Run: ``python -m pidg.bench.hash_grid``.
    """
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    grids = [HashGrid(GRID4D_SPATIAL)] + [HashGrid(GRID4D_TEMPORAL) for _ in range(3)]
    coords = [torch.rand(n_points, 3, generator=gen) for _ in grids]
    coords_grad = [c.clone().requires_grad_(True) for c in coords]
    weights = [torch.randn(n_points, g.out_dim, generator=gen) for g in grids]
    cases = {
        "kernel_spatial": lambda: _fwd_bwd_seconds(grids[:1], coords[:1], weights[:1], "cpu"),
        "kernel_temporal_x3": lambda: _fwd_bwd_seconds(grids[1:], coords[1:], weights[1:], "cpu"),
        "kernel_all": lambda: _fwd_bwd_seconds(grids, coords, weights, "cpu"),
        "kernel_all_coord_grad": lambda: _fwd_bwd_seconds(grids, coords_grad, weights, "cpu"),
        "torch_all": lambda: _fwd_bwd_seconds(grids, coords, weights, "torch"),
    }
    for run in cases.values():  # compile / load the kernels, warm the allocator
        run()
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, run in cases.items():
            times[name].extend(run() for _ in range(1 if name == "torch_all" else 5))
    results = {name: float(np.median(t)) for name, t in times.items()}
    results["speedup"] = results["torch_all"] / results["kernel_all"]
    print(f"hash grids (Grid4D config), {n_points} points, forward + backward, median seconds; "
          f"{machine_line(machine(), git_commit())}")
    for name, value in results.items():
        print(f"  {name:24s} {value:8.4f}" + ("x" if name == "speedup" else " s"))
    return results


if __name__ == "__main__":
    bench_hash_grid()
