"""Multiresolution 3D hash encoding (Instant-NGP), with a numba CPU kernel and a torch reference.

Geometry of one grid (all choices follow Instant-NGP / tiny-cuda-nn unless said otherwise):
  * Inputs are points ``u`` in the unit box [0, 1]^3; the caller normalises them (Grid4D maps the scene box and
    the time range onto it). Points outside the box are clamped onto it: their features are those of the nearest
    box point (continuous, and the coordinate gradient is zero along a clamped axis). tiny-cuda-nn lets them wrap
    around and torch-ngp (Grid4D's encoder) returns zero features there; both are discontinuous at the boundary.
  * Level ``l`` of ``L`` has, per axis ``d``, the scale ``s[l, d] = base[d] * b[d] ** l - 1`` with the growth
    factor ``b[d] = (finest[d] / base[d]) ** (1 / (L - 1))``: resolutions may differ per axis (Grid4D's temporal
    grids go from (8, 8, 8) to (32, 32, 16)) and need not be integers or powers of two.
  * A point's lattice position is ``p = u * s + 0.5`` (the half-cell offset keeps the levels' lattices from all
    sharing a vertex at the origin). Its cell is ``floor(p)`` and its 8 corners are blended trilinearly with the
    weights ``p - floor(p)``. Level ``l`` has ``n[l, d] = floor(s[l, d] + 0.5) + 2`` vertices along axis ``d``.
  * A level whose ``prod(n)`` vertices fit in the table of ``2**log2_table_size`` rows is stored densely (row
    ``x + n_x * (y + n_y * z)``); a finer level uses exactly that many rows, indexed by the spatial hash
    ``(x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod 2**log2_table_size`` (uint32 products; only the low bits
    survive the modulo, so int64 products give the same rows).
  * All levels live in one parameter tensor [rows, F]; level ``l`` owns rows ``offsets[l]:offsets[l + 1]``.
    The output is [N, L * F], level 0's F features first.

Two implementations behind ``hash_encode``:
  * ``hash_encode_reference``: plain torch, vectorised over levels, autograd for everything (table and
    coordinates, any order). Runs on any device; it is what CUDA tensors use.
  * ``_HashEncodeCPU``: numba kernels, float32, first derivatives only (use the reference for higher ones).
    Forward: one parallel task per level and chunk of points (a level's rows stay in cache), into a level-major
    buffer that one more parallel pass turns point-major. Backward w.r.t. the table: one parallel task per *level*.
    Tasks are dealt round-robin to the threads (``round_robin_workers``).
    Levels own disjoint table rows, so each thread adds into its own levels' rows: no atomics, no per-thread
    copies of the (up to 49 MB) table gradient to reduce, and a deterministic result. Backward w.r.t. the
    coordinates (only when they require grad): a point-parallel pass that re-reads the 8 corner values per
    level, about the cost of a forward pass.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal, get_args

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, Range, validate_config
from pidg.kernel_math import ZEROED_BUFFERS, float32_array, round_robin_workers

HASH_PRIMES = (1, 2654435761, 805459861)
#: Which hash-encoding implementation runs: "cpu" (numba kernel), "torch" (reference, any device), "auto" (by device).
HashGridBackend = Literal["auto", "cpu", "torch"]
Resolution = int | tuple[int, int, int]
LANES = 16  # points processed together in the kernels' inner loops
_CHUNK = 512  # points per parallel task of the point-parallel kernels (a multiple of LANES)
_LEVEL_CHUNK = 4096  # points per parallel task of the forward pass, which runs level by level (a multiple of LANES)


@dataclass(frozen=True)
class HashGridConfig:
    """One 3D multiresolution hash grid. Defaults: Grid4D's spatial grid G_xyz."""

    n_levels: Annotated[int, AT_LEAST_ONE] = 16
    """Resolution levels L (the output has L * n_features columns)."""
    n_features: Annotated[int, AT_LEAST_ONE] = 2
    """Features per level."""
    log2_table_size: Annotated[int, Range(1, 30)] = 19
    """log2 of the rows of a hashed level (coarse levels that fit are stored densely)."""
    base_resolution: Annotated[Resolution, AT_LEAST_ONE] = 16
    """Vertices per axis of the coarsest level (one int, or 3 for x y z of the grid's unit box)."""
    finest_resolution: Annotated[Resolution, AT_LEAST_ONE] = 2048
    """Vertices per axis of the finest level (one int, or 3)."""
    init_range: Annotated[float, NON_NEGATIVE] = 1e-4
    """Table entries start uniform in [-init_range, init_range] (Instant-NGP)."""

    def __post_init__(self) -> None:
        validate_config(self)
        base, finest = _per_axis(self.base_resolution), _per_axis(self.finest_resolution)
        if min(base) < 1 or any(f < b for f, b in zip(finest, base)):
            raise ValueError(f"HashGridConfig: need 1 <= base <= finest per axis, got {base} -> {finest}")


def _per_axis(r: Resolution) -> tuple[float, float, float]:
    values = (r, r, r) if isinstance(r, (int, float)) else tuple(r)
    if len(values) != 3:
        raise ValueError(f"a resolution is an int or 3 ints, got {r!r}")
    return tuple(float(v) for v in values)  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class GridLayout:
    """Per-level lattice constants shared by both implementations (numpy, so the kernels can take them)."""

    scales: np.ndarray  # [L, 3] float32: p = u * scale + 0.5
    sizes: np.ndarray  # [L, 3] int64: vertices per axis
    offsets: np.ndarray  # [L + 1] int64: first table row of each level
    hashed: np.ndarray  # [L] bool
    table_size: int  # rows of a hashed level (a power of two)
    n_features: int
    _torch_cache: dict = field(default_factory=dict, repr=False)

    @property
    def n_levels(self) -> int:
        return int(self.scales.shape[0])

    @property
    def n_rows(self) -> int:
        return int(self.offsets[-1])

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def torch_constants(self, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(scales, sizes, offsets, hashed) as tensors on ``device``, cached per device."""
        key = str(device)
        if key not in self._torch_cache:
            self._torch_cache[key] = tuple(
                torch.from_numpy(a).to(device) for a in (self.scales, self.sizes, self.offsets[:-1], self.hashed)
            )
        return self._torch_cache[key]


def grid_layout(config: HashGridConfig) -> GridLayout:
    """Level scales, vertex counts and table offsets of a grid (see the module docstring)."""
    base = np.array(_per_axis(config.base_resolution))
    finest = np.array(_per_axis(config.finest_resolution))
    levels = np.arange(config.n_levels, dtype=np.float64)[:, None]
    growth = (finest / base) ** (1.0 / (config.n_levels - 1)) if config.n_levels > 1 else np.ones(3)
    scales = (base * growth**levels - 1.0).astype(np.float32)
    # from the float32 scale, exactly as the kernels compute p at u = 1, so floor(p) + 1 < n always holds
    sizes = np.floor(scales + np.float32(0.5)).astype(np.int64) + 2
    table_size = 1 << config.log2_table_size
    dense_rows = sizes.prod(axis=1)
    hashed = dense_rows > table_size
    rows = np.where(hashed, table_size, dense_rows)
    offsets = np.concatenate([[0], np.cumsum(rows)]).astype(np.int64)
    return GridLayout(scales, sizes, offsets, hashed, table_size, config.n_features)


# ----------------------------------------------------------------------------------------------------------------
# torch reference


def spatial_hash(ix: Tensor, iy: Tensor, iz: Tensor, table_size: int) -> Tensor:
    """Instant-NGP's hash of integer vertex coordinates into ``table_size`` (a power of two) rows."""
    return (ix * HASH_PRIMES[0] ^ iy * HASH_PRIMES[1] ^ iz * HASH_PRIMES[2]) & (table_size - 1)


_CORNERS = [(cx, cy, cz) for cz in (0, 1) for cy in (0, 1) for cx in (0, 1)]


def hash_encode_reference(coords: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """Readable torch version: coords [N, 3] in [0, 1]^3, table [rows, F] -> features [N, L * F].

    Vectorised over levels (one gather for all of them) so that autograd builds one table-sized gradient, not
    one per level and corner. Differentiable w.r.t. coords and table to any order.
    """
    scales, sizes, offsets, hashed = layout.torch_constants(coords.device)
    n = coords.shape[0]
    u = coords.clamp(0.0, 1.0)[:, None, :]  # [N, 1, 3]
    p = u * scales.to(coords.dtype) + 0.5  # [N, L, 3]
    # the clamps only guard NaN inputs (row 0, NaN output, as in the kernel); finite inputs never need them
    cell_f = torch.minimum(torch.floor(p).nan_to_num(0.0).clamp_min(0.0), (sizes - 2).to(p.dtype))
    frac = p - cell_f
    cell = cell_f.long()
    indices, weights = [], []
    for corner in _CORNERS:
        v = cell + torch.tensor(corner, device=coords.device)  # [N, L, 3]
        dense = v[..., 0] + sizes[:, 0] * (v[..., 1] + sizes[:, 1] * v[..., 2])
        hashed_row = spatial_hash(v[..., 0], v[..., 1], v[..., 2], layout.table_size)
        indices.append(offsets + torch.where(hashed, hashed_row, dense))
        w = [frac[..., d] if corner[d] else 1.0 - frac[..., d] for d in range(3)]
        weights.append(w[0] * w[1] * w[2])
    index = torch.stack(indices, dim=-1)  # [N, L, 8]
    weight = torch.stack(weights, dim=-1)  # [N, L, 8]
    values = table[index.reshape(-1)].reshape(n, layout.n_levels, 8, table.shape[1])
    return (values * weight.unsqueeze(-1).to(table.dtype)).sum(dim=2).reshape(n, -1)


# ----------------------------------------------------------------------------------------------------------------
# numba kernels
#
# Points are processed LANES at a time per level: a block first computes the cells, weights and 8 corner rows of
# all its lanes, then gathers (forward) or scatters (backward). Separating the address computation from the
# memory accesses lets the CPU keep many independent cache misses in flight: the hashed levels of a 2^19 table
# are 4 MB each, and a forward pass that interleaved arithmetic and loads point by point was 2x slower on them
# (measured).


@njit(cache=True, inline="always")
def _block_cells(u, start, n, scales, sizes, lvl, cell, frac):  # pragma: no cover - compiled
    """Cells (lower corners) and blend weights of LANES points from ``start``; lanes past n repeat the last point."""
    for d in range(3):
        s = scales[lvl, d]
        hi = np.float32(sizes[lvl, d] - 2)
        for k in range(LANES):
            p = u[d, min(start + k, n - 1)] * s + np.float32(0.5)
            c = np.floor(p)
            c = c if c >= np.float32(0.0) else np.float32(0.0)  # NaN lands here too: rows stay in range
            c = c if c <= hi else hi
            cell[d, k] = np.int64(c)
            frac[d, k] = p - c


@njit(cache=True, inline="always")
def _block_rows(cell, sizes, lvl, offset, is_hashed, mask, n_feat, rows):  # pragma: no cover - compiled
    """Flat table positions (row * F) [8, LANES] of the cell corners; corner j = (x, y, z) = bits of j.

    Stored as uint64 so that indexing with them skips numba's negative-index fix-up, and pre-multiplied by F so
    a feature is one add away: together 4 fewer instructions per table access (1.4x faster blend, measured).
    """
    if is_hashed:  # (x * 1) ^ (y * 2654435761) ^ (z * 805459861), low bits only
        for k in range(LANES):
            x0, x1 = cell[0, k], cell[0, k] + 1
            y0, y1 = cell[1, k] * np.int64(2654435761), (cell[1, k] + 1) * np.int64(2654435761)
            z0, z1 = cell[2, k] * np.int64(805459861), (cell[2, k] + 1) * np.int64(805459861)
            rows[0, k] = np.uint64((offset + ((x0 ^ y0 ^ z0) & mask)) * n_feat)
            rows[1, k] = np.uint64((offset + ((x1 ^ y0 ^ z0) & mask)) * n_feat)
            rows[2, k] = np.uint64((offset + ((x0 ^ y1 ^ z0) & mask)) * n_feat)
            rows[3, k] = np.uint64((offset + ((x1 ^ y1 ^ z0) & mask)) * n_feat)
            rows[4, k] = np.uint64((offset + ((x0 ^ y0 ^ z1) & mask)) * n_feat)
            rows[5, k] = np.uint64((offset + ((x1 ^ y0 ^ z1) & mask)) * n_feat)
            rows[6, k] = np.uint64((offset + ((x0 ^ y1 ^ z1) & mask)) * n_feat)
            rows[7, k] = np.uint64((offset + ((x1 ^ y1 ^ z1) & mask)) * n_feat)
    else:  # x + n_x * (y + n_y * z)
        sx = sizes[lvl, 0] * n_feat
        sxy = sx * sizes[lvl, 1]
        for k in range(LANES):
            r = (offset + cell[0, k]) * n_feat + sx * cell[1, k] + sxy * cell[2, k]
            rows[0, k] = np.uint64(r)
            rows[1, k] = np.uint64(r + n_feat)
            rows[2, k] = np.uint64(r + sx)
            rows[3, k] = np.uint64(r + sx + n_feat)
            rows[4, k] = np.uint64(r + sxy)
            rows[5, k] = np.uint64(r + sxy + n_feat)
            rows[6, k] = np.uint64(r + sxy + sx)
            rows[7, k] = np.uint64(r + sxy + sx + n_feat)


@njit(cache=True, inline="always")
def _gather_level(flat, frac, rows, n_feat, acc):  # pragma: no cover - compiled
    """acc [F, LANES]: the trilinear blend of the 8 corner rows' features of a block of points (one level)."""
    for f in range(n_feat):
        fu = np.uint64(f)
        for k in range(LANES):  # blend along x, then y, then z
            w0, w1, w2 = frac[0, k], frac[1, k], frac[2, k]
            v0, v1, v2 = np.float32(1.0) - w0, np.float32(1.0) - w1, np.float32(1.0) - w2
            x00 = v0 * flat[rows[0, k] + fu] + w0 * flat[rows[1, k] + fu]
            x10 = v0 * flat[rows[2, k] + fu] + w0 * flat[rows[3, k] + fu]
            x01 = v0 * flat[rows[4, k] + fu] + w0 * flat[rows[5, k] + fu]
            x11 = v0 * flat[rows[6, k] + fu] + w0 * flat[rows[7, k] + fu]
            acc[f, k] = v2 * (v1 * x00 + w1 * x10) + w2 * (v1 * x01 + w1 * x11)


@njit(cache=True, inline="always")
def _scatter_level(flat, grad_out, start, cnt, col0, rows, corner_w, n_feat):  # pragma: no cover - compiled
    """Add the block's incoming gradients (columns col0 .. col0 + F of grad_out) times the corner weights into
    the corner rows, point by point and corner by corner, a corner's F features together (one cache line)."""
    for k in range(cnt):
        for f in range(n_feat):
            g, fu = grad_out[start + k, col0 + f], np.uint64(f)
            for j in range(8):
                flat[rows[j, k] + fu] += corner_w[j, k] * g


# Grid4D's grids have two features per level. The kernels call the inlined level functions above once with the
# literal 2 and once with the runtime count, so that the common case is compiled with the count as a constant
# (unrolled feature loops, a shift for the row stride): forward 1.11-1.14x and table gradient 1.23-1.30x faster
# on a trained bouncingballs model's points (measured against the one-feature-at-a-time kernels; the backward's gain
# is also from adding a corner's features together instead of one feature over all corners and then the next).


@njit(parallel=True, cache=True, nogil=True)
def _encode_forward(u, table, scales, sizes, offsets, hashed, table_size, out, workers):  # pragma: no cover - compiled
    """u [3, N] (clamped), table [R, F] -> out [L * F, N] (level-major). One task per (level, chunk of _LEVEL_CHUNK
    points), level by level, so that a thread reads one level's rows (up to 2^16 x 2 floats, about its L2 cache) for
    many points in a row, as the table gradient's tasks do; ``_encode`` deals the tasks round-robin (levels differ in
    cost). Level-major, a task writes whole cache lines of its own: into a point-major [N, L * F] output every level
    wrote 8 bytes of each point's row, so the two cores took each row's cache lines from each other level after
    level (two threads: 3.07 -> 2.10 ms for the cpu preset's spatial grid at 18k points, 2.77 -> 1.80 for a temporal
    one; one thread: unchanged). ``_points_major`` then turns it point-major, which the next layer's matrix product
    needs (reading the transposed view in place made the products 1.5x slower)."""
    n = u.shape[1]
    n_levels = scales.shape[0]
    n_feat = table.shape[1]
    flat = table.reshape(-1)
    mask = np.int64(table_size - 1)
    n_chunks = (n + _LEVEL_CHUNK - 1) // _LEVEL_CHUNK
    for worker in prange(workers):  # tasks dealt round-robin (see kernel_math.round_robin_workers)
        for task in range(worker, n_levels * n_chunks, workers):
            lvl = task // n_chunks
            chunk = task - lvl * n_chunks
            stop = min(n, (chunk + 1) * _LEVEL_CHUNK)
            if n_feat == 2:
                _encode_level(u, flat, scales, sizes, offsets, hashed, mask, lvl, chunk * _LEVEL_CHUNK, stop, 2, out)
            else:
                _encode_level(u, flat, scales, sizes, offsets, hashed, mask, lvl, chunk * _LEVEL_CHUNK, stop, n_feat, out)


@njit(cache=True, inline="always")
def _encode_level(u, flat, scales, sizes, offsets, hashed, mask, lvl, first, stop, n_feat, out):  # pragma: no cover - compiled
    """out[level lvl's F rows, first:stop]: the forward pass's task."""
    n = u.shape[1]
    cell = np.empty((3, LANES), dtype=np.int64)
    frac = np.empty((3, LANES), dtype=np.float32)
    rows = np.empty((8, LANES), dtype=np.uint64)
    acc = np.empty((n_feat, LANES), dtype=np.float32)
    for start in range(first, stop, LANES):
        _block_cells(u, start, n, scales, sizes, lvl, cell, frac)
        _block_rows(cell, sizes, lvl, offsets[lvl], hashed[lvl], mask, n_feat, rows)
        _gather_level(flat, frac, rows, n_feat, acc)
        for f in range(n_feat):
            for k in range(min(LANES, n - start)):
                out[lvl * n_feat + f, start + k] = acc[f, k]


_TRANSPOSE_BLOCK = 64  # points per task of ``_transpose_kernel``: 64 points of 32 features are 8 KB


@njit(parallel=True, cache=True, nogil=True)
def _transpose_kernel(src, dst):  # pragma: no cover - compiled
    """dst[:, :n] = src.T for src [n, C] (any strides), a block of points per task, a point's C values together.
    Both turns of the hash features go through it: point-major to level-major directly, level-major to point-major
    on transposed views (``_points_major``; 0.10 against 0.17 ms at 16k points x 32 features for a loop that wrote
    one feature column at a time)."""
    n, n_cols = src.shape
    for block in prange((n + _TRANSPOSE_BLOCK - 1) // _TRANSPOSE_BLOCK):
        for i in range(block * _TRANSPOSE_BLOCK, min(n, (block + 1) * _TRANSPOSE_BLOCK)):
            for c in range(n_cols):
                dst[c, i] = src[i, c]


def _points_major(level_major: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` points' features [n, C] of a level-major [C, N] buffer, as a C-contiguous array."""
    out = np.empty((n, level_major.shape[0]), dtype=level_major.dtype)
    _transpose_kernel(level_major[:, :n].T, out.T)
    return out


def _level_major(grad: np.ndarray, n_total: int | None = None) -> np.ndarray:
    """A point-major gradient [n, C] as a level-major [C, n_total] array (columns past n left unset), the layout
    the table kernel reads in runs (1.8 against 2.7 ms for a temporal grid's table gradient at 16k points)."""
    out = np.empty((grad.shape[1], grad.shape[0] if n_total is None else n_total), dtype=np.float32)
    _transpose_kernel(grad, out)
    return out


@njit(parallel=True, cache=True, nogil=True)
def _encode_backward_table(u, grad_out, scales, sizes, offsets, hashed, table_size, grad_table, workers):  # pragma: no cover - compiled
    """grad_out [N, L * F] (any strides: a level-major gradient is read in runs) -> grad_table [R, F] (zeroed by the
    caller). One task per level: levels own disjoint rows, so no two threads ever add into the same row, and each
    row's sum has a fixed order."""
    n = u.shape[1]
    n_levels = scales.shape[0]
    n_feat = grad_table.shape[1]
    flat = grad_table.reshape(-1)
    mask = np.int64(table_size - 1)
    for worker in prange(workers):  # levels dealt round-robin (see kernel_math.round_robin_workers)
        for lvl in range(worker, n_levels, workers):
            cell = np.empty((3, LANES), dtype=np.int64)
            frac = np.empty((3, LANES), dtype=np.float32)
            rows = np.empty((8, LANES), dtype=np.uint64)
            corner_w = np.empty((8, LANES), dtype=np.float32)
            off = offsets[lvl]
            col0 = lvl * n_feat
            for start in range(0, n, LANES):
                _block_cells(u, start, n, scales, sizes, lvl, cell, frac)
                cnt = min(LANES, n - start)
                for k in range(LANES):  # trilinear corner weights, corner j = (x, y, z) = bits of j
                    w0, w1, w2 = frac[0, k], frac[1, k], frac[2, k]
                    v0, v1, v2 = np.float32(1.0) - w0, np.float32(1.0) - w1, np.float32(1.0) - w2
                    corner_w[0, k] = v0 * v1 * v2
                    corner_w[1, k] = w0 * v1 * v2
                    corner_w[2, k] = v0 * w1 * v2
                    corner_w[3, k] = w0 * w1 * v2
                    corner_w[4, k] = v0 * v1 * w2
                    corner_w[5, k] = w0 * v1 * w2
                    corner_w[6, k] = v0 * w1 * w2
                    corner_w[7, k] = w0 * w1 * w2
                if n_feat == 2:
                    _block_rows(cell, sizes, lvl, off, hashed[lvl], mask, 2, rows)
                    _scatter_level(flat, grad_out, start, cnt, col0, rows, corner_w, 2)
                else:
                    _block_rows(cell, sizes, lvl, off, hashed[lvl], mask, n_feat, rows)
                    _scatter_level(flat, grad_out, start, cnt, col0, rows, corner_w, n_feat)


@njit(parallel=True, cache=True, nogil=True)
def _encode_backward_coords(u, table, grad_out, scales, sizes, offsets, hashed, table_size, grad_u):  # pragma: no cover - compiled
    """grad_out [N, L * F] -> grad_u [N, 3], the gradient w.r.t. the clamped coordinates."""
    n = u.shape[1]
    n_levels = scales.shape[0]
    n_feat = table.shape[1]
    flat = table.reshape(-1)
    mask = np.int64(table_size - 1)
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        cell = np.empty((3, LANES), dtype=np.int64)
        frac = np.empty((3, LANES), dtype=np.float32)
        rows = np.empty((8, LANES), dtype=np.uint64)
        acc = np.empty((3, LANES), dtype=np.float32)
        total = np.empty((3, LANES), dtype=np.float32)
        for start in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK), LANES):
            for k in range(LANES):
                total[0, k] = 0.0
                total[1, k] = 0.0
                total[2, k] = 0.0
            for lvl in range(n_levels):
                _block_cells(u, start, n, scales, sizes, lvl, cell, frac)
                _block_rows(cell, sizes, lvl, offsets[lvl], hashed[lvl], mask, n_feat, rows)
                for k in range(LANES):
                    acc[0, k] = 0.0
                    acc[1, k] = 0.0
                    acc[2, k] = 0.0
                for f in range(n_feat):
                    col = lvl * n_feat + f
                    fu = np.uint64(f)
                    for k in range(LANES):  # derivative of the trilinear blend along each axis
                        g = grad_out[min(start + k, n - 1), col]
                        w0, w1, w2 = frac[0, k], frac[1, k], frac[2, k]
                        v0, v1, v2 = np.float32(1.0) - w0, np.float32(1.0) - w1, np.float32(1.0) - w2
                        e0, e1, e2, e3 = flat[rows[0, k] + fu], flat[rows[1, k] + fu], flat[rows[2, k] + fu], flat[rows[3, k] + fu]
                        e4, e5, e6, e7 = flat[rows[4, k] + fu], flat[rows[5, k] + fu], flat[rows[6, k] + fu], flat[rows[7, k] + fu]
                        acc[0, k] += g * (v2 * (v1 * (e1 - e0) + w1 * (e3 - e2)) + w2 * (v1 * (e5 - e4) + w1 * (e7 - e6)))
                        acc[1, k] += g * (v2 * (v0 * (e2 - e0) + w0 * (e3 - e1)) + w2 * (v0 * (e6 - e4) + w0 * (e7 - e5)))
                        acc[2, k] += g * (v1 * (v0 * (e4 - e0) + w0 * (e5 - e1)) + w1 * (v0 * (e6 - e2) + w0 * (e7 - e3)))
                for d in range(3):  # dp/du = scale
                    s = scales[lvl, d]
                    for k in range(LANES):
                        total[d, k] += acc[d, k] * s
            for k in range(min(LANES, n - start)):
                for d in range(3):
                    grad_u[start + k, d] = total[d, k]




def _f32_rows(t: Tensor) -> np.ndarray:
    """float32 [N, C] with unit column stride, as a view when it already is one: the incoming gradient is usually a
    column block of the concatenated features' gradient, which the kernels read in place instead of copying."""
    t = t.detach()
    return t.numpy() if t.dtype == torch.float32 and t.stride(-1) == 1 else float32_array(t)


def _unit_soa(*blocks: Tensor) -> np.ndarray:
    """The blocks' points [Ni, 3], clamped, as one float32 [3, N1 + N2 + ...] array, the layout the lane loops read
    (numpy: no torch operation, whose thread wake-up would cost more than the copy)."""
    u = np.empty((3, sum(b.shape[0] for b in blocks)), dtype=np.float32)
    start = 0
    for b in blocks:
        end = start + b.shape[0]
        np.clip(b.detach().to(torch.float32).numpy().T, 0.0, 1.0, out=u[:, start:end])
        start = end
    return u


def _encode(u: np.ndarray, table: Tensor, layout: GridLayout) -> np.ndarray:
    """The forward kernel's features of the clamped points ``u`` [3, N], level-major [L * F, N], its tasks dealt
    round-robin."""
    out = np.empty((layout.out_dim, u.shape[1]), dtype=np.float32)
    _encode_forward(u, float32_array(table), layout.scales, layout.sizes, layout.offsets, layout.hashed, layout.table_size, out,
                    round_robin_workers())
    return out


class _HashEncodeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coords: Tensor, table: Tensor, layout: GridLayout) -> Tensor:  # type: ignore[override]
        u = _unit_soa(coords)
        out = _points_major(_encode(u, table, layout), u.shape[1])
        ctx.save_for_backward(coords, table)
        ctx.layout = layout
        ctx.unit_soa = u  # the backward reads the same clamped [3, N] copy (small), instead of making it again
        return torch.from_numpy(out).to(table.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        coords, table = ctx.saved_tensors
        layout: GridLayout = ctx.layout
        u, g = ctx.unit_soa, _f32_rows(grad_out)
        consts = (layout.scales, layout.sizes, layout.offsets, layout.hashed, layout.table_size)
        grad_coords = grad_table = None
        if ctx.needs_input_grad[1]:
            g_tab = ZEROED_BUFFERS.zeros(layout.n_rows, layout.n_features)
            _encode_backward_table(u, _level_major(g).T, *consts, g_tab, round_robin_workers())
            grad_table = torch.from_numpy(g_tab).to(table.dtype)
        if ctx.needs_input_grad[0]:
            g_u = np.empty((u.shape[1], 3), dtype=np.float32)
            _encode_backward_coords(u, float32_array(table), g, *consts, g_u)
            inside = (coords >= 0) & (coords <= 1)  # torch.clamp's convention: the boundary passes the gradient
            grad_coords = torch.from_numpy(g_u).to(coords.dtype) * inside
        return grad_coords, grad_table, None


def hash_encode_cpu(coords: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """The numba kernel: same contract as ``hash_encode_reference`` (float32 arithmetic, first derivatives)."""
    return _HashEncodeCPU.apply(coords, table, layout)


def resolve_backend(backend: HashGridBackend, table: Tensor) -> Literal["cpu", "torch"]:
    """auto: the kernel for float32 CPU tables, the torch reference otherwise (CUDA, or float64 for checks)."""
    if backend == "auto":
        return "cpu" if table.device.type == "cpu" and table.dtype == torch.float32 else "torch"
    if backend == "cpu" and table.device.type != "cpu":
        raise ValueError(f"hash_encode: backend 'cpu' needs CPU tensors, got {table.device}")
    if backend not in get_args(HashGridBackend):
        raise ValueError(f"hash_encode: unknown backend {backend!r} ({', '.join(get_args(HashGridBackend))})")
    return backend


def _check_encode_inputs(coords: Tensor, table: Tensor, layout: GridLayout, what: str = "hash_encode") -> None:
    if coords.dim() != 2 or coords.shape[1] != 3:
        raise ValueError(f"{what}: coords must be [N, 3], got {list(coords.shape)}")
    if tuple(table.shape) != (layout.n_rows, layout.n_features):
        raise ValueError(f"{what}: table must be [{layout.n_rows}, {layout.n_features}], got {list(table.shape)}")
    if coords.device != table.device:
        raise ValueError(f"{what}: coords on {coords.device} but table on {table.device}")


def hash_encode(coords: Tensor, table: Tensor, layout: GridLayout, backend: HashGridBackend = "auto") -> Tensor:
    """Encode points coords [N, 3] (unit box, see module docstring) with ``table`` -> [N, L * F]."""
    _check_encode_inputs(coords, table, layout)
    if resolve_backend(backend, table) == "cpu":
        return hash_encode_cpu(coords, table, layout)
    return hash_encode_reference(coords.to(table.dtype), table, layout)


# ----------------------------------------------------------------------------------------------------------------
# Encoding with a smoothness term (Grid4D's regulariser)


@njit(cache=True, nogil=True)
def _change_rows(out, n, rows, change):  # pragma: no cover - compiled
    """change [C, M] = out[:, n + i] - out[:, rows[i]] of a level-major out [C, N + M] (level-major too); returns the
    sum of its squares (float64 accumulator)."""
    total = 0.0
    for f in range(out.shape[0]):
        for i in range(rows.shape[0]):
            c = out[f, n + i] - out[f, rows[i]]
            change[f, i] = c
            total += np.float64(c) * c
    return total


@njit(parallel=True, cache=True, nogil=True)
def _smoothness_gradient(n, change, scale, rows, g_all):  # pragma: no cover - compiled
    """Into g_all [C, N + M], level-major, whose first N columns hold the features' gradient: d term /
    d G(jittered) = scale * change (level-major [C, M]) in the last M, and minus that added into each sample's own
    column (rows may repeat: one feature row is one task, so its sums keep their order)."""
    for f in prange(change.shape[0]):
        for i in range(rows.shape[0]):
            g = scale * change[f, i]
            g_all[f, n + i] = g
            g_all[f, rows[i]] -= g


class _HashEncodeSmoothCPU(torch.autograd.Function):
    """``hash_encode_with_smoothness`` on the numba kernels, as one autograd node.

    The sample's own features are the pass's rows ``features[rows]`` (the kernel encodes every point alone, so they
    are the same values bit for bit), so only the perturbed copies are encoded besides the points: N + M points
    through each kernel instead of N + 2M. The backward folds the term's gradient into the points' gradient rows
    and the perturbed copies' rows and runs the table kernel once, into one buffer: no split of a joint output
    (whose backward concatenates the pieces' gradients) and no second table-sized gradient to add. Coordinates get
    the gradient of the features only: the sample is detached, as in the reference. The small work around the
    kernels is numpy and numba, not torch ops: each parallel torch op costs ~0.1 ms of thread wake-up here.
    """

    @staticmethod
    def forward(ctx, coords: Tensor, jittered: Tensor, rows: Tensor, table: Tensor, layout: GridLayout):  # type: ignore[override]
        n = coords.shape[0]
        u = _unit_soa(coords, jittered)  # [3, N + M]
        out = _encode(u, table, layout)
        rows_np = rows.detach().cpu().numpy().astype(np.int64)
        change = np.empty((layout.out_dim, rows_np.shape[0]), dtype=np.float32)  # G(u_i + d_i) - G(u_i), level-major
        total = _change_rows(out, n, rows_np, change)
        ctx.save_for_backward(coords, table)
        ctx.layout, ctx.unit_soa, ctx.change, ctx.rows = layout, u, change, rows_np
        features = _points_major(out, n)
        return torch.from_numpy(features).to(table.dtype), torch.tensor(total, dtype=table.dtype)

    @staticmethod
    def backward(ctx, grad_features: Tensor, grad_term: Tensor):  # type: ignore[override]
        coords, table = ctx.saved_tensors
        layout: GridLayout = ctx.layout
        u, n = ctx.unit_soa, coords.shape[0]
        consts = (layout.scales, layout.sizes, layout.offsets, layout.hashed, layout.table_size)
        g_main = _f32_rows(grad_features)
        grad_coords = grad_table = None
        if ctx.needs_input_grad[3]:
            g_all = _level_major(g_main, u.shape[1])
            _smoothness_gradient(n, ctx.change, np.float32(2.0 * float(grad_term)), ctx.rows, g_all)
            g_tab = ZEROED_BUFFERS.zeros(layout.n_rows, layout.n_features)
            _encode_backward_table(u, g_all.T, *consts, g_tab, round_robin_workers())
            grad_table = torch.from_numpy(g_tab).to(table.dtype)
        if ctx.needs_input_grad[0]:
            g_u = np.empty((n, 3), dtype=np.float32)
            _encode_backward_coords(np.ascontiguousarray(u[:, :n]), float32_array(table), g_main, *consts, g_u)
            inside = (coords >= 0) & (coords <= 1)
            grad_coords = torch.from_numpy(g_u).to(coords.dtype) * inside
        return grad_coords, None, None, grad_table, None


def hash_encode_with_smoothness(
    coords: Tensor, jittered: Tensor, rows: Tensor, table: Tensor, layout: GridLayout, backend: HashGridBackend = "auto"
) -> tuple[Tensor, Tensor]:
    """(features [N, L * F] of ``coords`` [N, 3], the scalar sum over i and f of (G(jittered_i) - G(coords[rows_i]))^2)
    for perturbed copies ``jittered`` [M, 3] of the sampled rows ``rows`` [M]: Grid4D's smoothness term before its
    weight and mean. The sample enters detached (its coordinates get no gradient through the term; the table does).
    The torch path encodes points, sample and copies in one reference call; the numba path is one node
    (``_HashEncodeSmoothCPU``) that encodes N + M points."""
    _check_encode_inputs(coords, table, layout, "hash_encode_with_smoothness")
    if jittered.dim() != 2 or jittered.shape[1] != 3 or rows.shape != (jittered.shape[0],):
        raise ValueError(f"hash_encode_with_smoothness: jittered must be [M, 3] and rows [M], got {list(jittered.shape)} "
                         f"and {list(rows.shape)}")
    if resolve_backend(backend, table) == "cpu":
        return _HashEncodeSmoothCPU.apply(coords, jittered.detach(), rows, table, layout)
    n, m = coords.shape[0], jittered.shape[0]
    sample = coords.detach().index_select(0, rows)
    out = hash_encode_reference(torch.cat([coords, sample, jittered.detach()]).to(table.dtype), table, layout)
    features, base, moved = out.split([n, m, m])
    return features, (moved - base).square().sum()


class HashGrid(nn.Module):
    """A learnable multiresolution hash grid: unit-box points [N, 3] -> features [N, n_levels * n_features]."""

    def __init__(self, config: HashGridConfig = HashGridConfig(), backend: HashGridBackend = "auto") -> None:
        super().__init__()
        self.config = config
        self.backend: HashGridBackend = backend
        self.layout = grid_layout(config)
        table = torch.empty(self.layout.n_rows, config.n_features).uniform_(-config.init_range, config.init_range)
        self.table = nn.Parameter(table)

    @property
    def out_dim(self) -> int:
        return self.layout.out_dim

    def forward(self, coords: Tensor) -> Tensor:
        return hash_encode(coords, self.table, self.layout, self.backend)

    def with_smoothness(self, coords: Tensor, jittered: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
        """``forward(coords)`` and the smoothness sum of ``hash_encode_with_smoothness``."""
        return hash_encode_with_smoothness(coords, jittered, rows, self.table, self.layout, self.backend)

    def extra_repr(self) -> str:
        lay = self.layout
        return (
            f"levels={lay.n_levels}, features={lay.n_features}, table=2^{self.config.log2_table_size}, "
            f"res {self.config.base_resolution}->{self.config.finest_resolution}, "
            f"dense levels={int((~lay.hashed).sum())}, rows={lay.n_rows}"
        )


# ----------------------------------------------------------------------------------------------------------------
# Grid4D's grids (the paper's sizes)

GRID4D_SPATIAL = HashGridConfig(16, 2, 19, 16, 2048)
GRID4D_TEMPORAL = HashGridConfig(32, 2, 19, (8, 8, 8), (32, 32, 16))
