"""Multi-threaded CPU compositor: numba kernels with a hand-written backward pass.

Why numba: it installs from PyPI as a wheel on every major platform, needs no compiler on the user's machine
(unlike a C++/OpenMP torch extension), and its parallel loops reach C speed (10-150x plain torch ops on a
2-core CPU). Kernels are compiled on first use and cached on disk.

Pipeline, with no Python loop over Gaussians:
  1. ``bin_gaussians``: each visible Gaussian's bounding box -> the 16x16 tiles it touches; a counting sort by
     tile of the depth-sorted Gaussians yields per-tile lists in front-to-back order (O(#intersections)).
  2. ``_forward_tiles``: one task per tile, the tiles dealt round-robin to the threads (``round_robin_workers``). A
     tile row of 16 pixels is processed as 16 SIMD lanes: the tile list is culled against the row 16 Gaussians at a
     time in one vector pass (the alpha >= 1/255 ellipse must reach the row), and for each Gaussian that does, alpha is
     computed for all lanes with a branch-free polynomial exp, so the compiler vectorises the lane loop and no
     per-pixel branch is mispredicted. Each pixel stops once its transmittance would fall below 1e-4; the row stops when
     all its pixels have (checked once per cull block). Per pixel it records the final transmittance and the end of its
     contributing prefix. A tile's table of Gaussians is filled as rows first reach them: in crowded tiles pixels
     saturate long before the list's end.
  3. ``_backward_tiles``: the same row/lane structure, back to front from that end, recovering each
     transmittance by division (alpha <= 0.99 keeps this stable). Gradients are summed per tile into one row
     per (tile, Gaussian) intersection, stored at that intersection's slot in Gaussian-major order, so that
     ``_reduce_per_gaussian`` sums contiguous rows per Gaussian: no atomics, and the result is deterministic
     whatever the thread schedule.
     The leading channels (colour and depth) go to the image and the rest (a loss's features) to an array of their
     own, so that a few feature tiles do not widen every pixel's row of the image: strided into one
     [H, W, 4 + 8] array, the image's and its gradient's cache lines tripled (~5 ms of a 400x400 step). Likewise
     the tiles read the two groups' per-Gaussian values from two arrays, and the extra channels' gradients are kept
     for their own tiles only and added per Gaussian in one serial pass over those tiles. Each tile row composites
     its own number of channels (``row_channels``): a loss that reads its features at a few pixels pays for the
     extra channels on those pixels' rows only.
  4. ``finish_image_cpu``: the composited colour and depth become rgb over the background and depth, each a
     contiguous array, in one pass; its backward assembles the image's gradient in one pass too.
  5. ``gaussians_reaching_cpu`` (not part of a render): the forward pass's hit and stop rules on a pixel mask only,
     marking the Gaussians that add to it, so a loss on a few pixels can skip the others' per-Gaussian work.
Arithmetic is float32 like gsplat (inputs are converted; outputs come back in the input dtype), with the
exp approximation accurate to 5e-7 relative; the torch reference is the float64-exact implementation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import ZEROED_BUFFERS, exp_nonpositive_unclamped, float32_array, round_robin_workers
from pidg.render.projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    image_channel_count,
    tile_grid,
    tiles_touched,
)

_N_PARAMS = 6  # gradient slots per Gaussian before its features: mean x, mean y, conic a, b, c, opacity
LANES = 16  # pixels of a tile row processed together; the tile size may not exceed it
_THRESHOLD_MARGIN = 1e-4  # slack on the log-alpha threshold so the exp approximation never drops a pair
_POWER_FLOOR = -5.6  # below log(1/255): lanes under it are masked, so exp() only needs [-5.6, 0]
# The backward may reassociate its lane sums (deterministic for a given build; no FMA contraction, so alpha is
# recomputed bit for bit as in the forward pass and the hit tests agree)
_REDUCE_FASTMATH = {"reassoc", "nsz"}
_MAX_TILE_LIST = 1 << 24  # a pixel's end in its tile list is kept as a float32 lane value: exact below 2^24

f32 = np.float32


@dataclass
class TileBins:
    """Per-tile, depth-sorted Gaussian lists (CSR) and, per Gaussian, where its intersections landed."""

    tile_offsets: np.ndarray  # [T+1] int64: intersections of tile t are isect_ids[tile_offsets[t]:tile_offsets[t+1]]
    isect_ids: np.ndarray  # [M] int64 Gaussian index, front to back within each tile
    gauss_offsets: np.ndarray  # [N+1] int64: Gaussian g's intersections are slots gauss_offsets[g]:gauss_offsets[g+1]
    slot_of_isect: np.ndarray  # [M] int64: the slot (Gaussian-major position) of intersection isect_ids[i]
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def num_intersections(self) -> int:
        return int(self.isect_ids.shape[0])


@njit(cache=True, nogil=True)
def _tile_rects(means2d, radii, tile_size, tiles_x, tiles_y):  # pragma: no cover - compiled
    """Each Gaussian's tile rectangle and tile count, and the indices of the visible ones (both radii > 0), in one
    pass over the projection's own arrays (float32 or float64 centres, any integer radii; the arithmetic in float64).
    In numpy the conversions and the visibility test took ~0.7 ms at 18k Gaussians, ``all(axis=1)`` most of it."""
    n = means2d.shape[0]
    rects = np.empty((n, 4), dtype=np.int64)  # x0, x1, y0, y1 inclusive; empty when x1 < x0
    counts = np.zeros(n, dtype=np.int64)
    visible = np.empty(n, dtype=np.int64)
    n_visible = 0
    for g in range(n):
        rx, ry = np.int64(radii[g, 0]), np.int64(radii[g, 1])
        if rx <= 0 or ry <= 0:
            rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = 0, -1, 0, -1
            continue
        visible[n_visible] = g
        n_visible += 1
        mx, my = np.float64(means2d[g, 0]), np.float64(means2d[g, 1])
        x0 = max(0, int(math.floor((mx - rx) / tile_size)))
        x1 = min(tiles_x - 1, int(math.floor((mx + rx) / tile_size)))
        y0 = max(0, int(math.floor((my - ry) / tile_size)))
        y1 = min(tiles_y - 1, int(math.floor((my + ry) / tile_size)))
        rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3] = x0, x1, y0, y1
        if x1 >= x0 and y1 >= y0:
            counts[g] = (x1 - x0 + 1) * (y1 - y0 + 1)
    return rects, counts, visible[:n_visible]


_BIN_CHUNKS = 8  # contiguous slices of the depth order, binned in parallel


@njit(parallel=True, cache=True, nogil=True)
def _bin_sorted(rects, counts, depth_order, tiles_x, n_tiles):  # pragma: no cover - compiled
    """Counting sort of (tile, Gaussian) pairs by tile, stable in depth order, in parallel.

    The depth order is cut into contiguous chunks; each chunk histograms its own tiles, and a chunk's entries
    of a tile are placed after those of all earlier (nearer) chunks, so every tile list stays front to back.
    """
    n = counts.shape[0]
    n_vis = depth_order.shape[0]
    n_chunks = _BIN_CHUNKS
    chunk_counts = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    for c in prange(n_chunks):
        for r in range(c * n_vis // n_chunks, (c + 1) * n_vis // n_chunks):
            g = depth_order[r]
            for ty in range(rects[g, 2], rects[g, 3] + 1):
                for tx in range(rects[g, 0], rects[g, 1] + 1):
                    chunk_counts[c, ty * tiles_x + tx] += 1
    tile_offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    cursors = np.empty((n_chunks, n_tiles), dtype=np.int64)
    for t in range(n_tiles):
        pos = tile_offsets[t]
        for c in range(n_chunks):
            cursors[c, t] = pos
            pos += chunk_counts[c, t]
        tile_offsets[t + 1] = pos
    gauss_offsets = np.zeros(n + 1, dtype=np.int64)
    for g in range(n):
        gauss_offsets[g + 1] = gauss_offsets[g] + counts[g]
    m = gauss_offsets[n]
    isect_ids = np.empty(m, dtype=np.int64)
    slot_of_isect = np.empty(m, dtype=np.int64)
    for c in prange(n_chunks):
        for r in range(c * n_vis // n_chunks, (c + 1) * n_vis // n_chunks):
            g = depth_order[r]
            j = gauss_offsets[g]
            for ty in range(rects[g, 2], rects[g, 3] + 1):
                for tx in range(rects[g, 0], rects[g, 1] + 1):
                    t = ty * tiles_x + tx
                    pos = cursors[c, t]
                    cursors[c, t] = pos + 1
                    isect_ids[pos] = g
                    slot_of_isect[pos] = j
                    j += 1
    return tile_offsets, isect_ids, gauss_offsets, slot_of_isect


def depth_order(depths: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """``indices`` sorted by depth, ties in index order: ``indices[argsort(depths[indices], stable)]``.

    float32 depths (training) are sorted as one 64-bit key per Gaussian (the depth's bits made order-preserving,
    then the index), which numpy sorts with SIMD: 7x faster than its stable float sort at 20k Gaussians. Other
    dtypes keep numpy's stable sort, so float64 depths are not rounded into ties.
    """
    if depths.dtype != np.float32:
        return indices[np.argsort(depths[indices], kind="stable")]
    bits = depths[indices].view(np.uint32)
    flip = np.where(bits >> np.uint32(31), np.uint32(0xFFFFFFFF), np.uint32(0x80000000))  # floats as ordered ints
    keys = ((bits ^ flip).astype(np.uint64) << np.uint64(32)) | indices.astype(np.uint64)
    return (np.sort(keys) & np.uint64(0xFFFFFFFF)).astype(np.int64)


def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """Assign visible Gaussians to the tiles their bounding boxes touch, depth-sorted within each tile."""
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    m2 = np.ascontiguousarray(means2d.detach().cpu().numpy())
    rad = np.ascontiguousarray(radii.detach().cpu().numpy())
    rects, counts, vis_idx = _tile_rects(m2, rad, tile_size, tiles_x, tiles_y)
    order = depth_order(depths.detach().cpu().numpy(), vis_idx)
    tile_offsets, isect_ids, gauss_offsets, slot_of_isect = _bin_sorted(rects, counts, order, tiles_x, tiles_x * tiles_y)
    return TileBins(tile_offsets, isect_ids, gauss_offsets, slot_of_isect, tiles_x, tiles_y, tile_size)


@njit(cache=True)
def _blend(mask, x, y):  # pragma: no cover - compiled
    """x where mask is 1, y where it is 0 (mask in {0, 1}; exact for finite x, y).

    A lane loop's "keep the old value unless ..." written as a ternary became a conditional store, which LLVM
    vectorises with masked stores (vmaskmovps), microcoded and slow on AMD Zen: this arithmetic select keeps the
    stores unconditional (the forward pass ran 1.9-2.4x faster, measured on znver1). Not inlined by numba, so a
    caller's fastmath flags cannot refactor it (reassociation would turn x*m + y*(1-m) into (x-y)*m + y).
    """
    return x * mask + y * (f32(1.0) - mask)


# Per-tile Gaussian table rows (float32, one column per Gaussian of the tile, so that a block of Gaussians is
# contiguous): centre x relative to the tile's first column, centre y, conic a, b, c, opacity, log-alpha
# threshold, the rows [y_lo, y_hi] the alpha >= 1/255 ellipse can reach, and 1/a, b/a, det/a for the per-row
# cull (divisions hoisted out of the row loop).
_MX, _MY, _CA, _CB, _CC, _OP, _TH, _YLO, _YHI, _INV_A, _B_OVER_A, _DET_OVER_A = range(12)
_N_COLS = 12
CULL_BLOCK = 16  # Gaussians culled together per row: one vectorised pass, then a compacted list of the hits
FILL_BLOCK = 4 * CULL_BLOCK  # table columns the forward pass fills at a time, when a row first needs them


@njit(cache=True, inline="always")
def _padded(n):  # pragma: no cover - compiled
    return (n + CULL_BLOCK - 1) // CULL_BLOCK * CULL_BLOCK


@njit(cache=True, inline="always")
def _fill_tile(means2d, conics, opacities, feats, extra_feats, isect_ids, start, x_lo, k_from, k_to, table, tfeat):  # pragma: no cover - compiled
    """Copy the tile's Gaussians k_from .. k_to - 1 into contiguous local arrays, with their per-Gaussian row bounds.

    Filled on demand: pixels saturate long before the end of a crowded tile's list (at a quarter of it on the
    render bench's case b, where filling whole lists took about a third of the forward pass). The table has
    room for whole cull blocks; columns past the tile's list are padding that reaches no row, so a block needs no
    tail test. The caller allocates the arrays: arrays *returned* from an inlined function cost a 2.5x slowdown
    of the lane loops (measured), apparently because the compiler can no longer prove they do not alias.
    """
    dim = tfeat.shape[1]  # the tile's channels: the image's (feats), then the extra ones (extra_feats)
    n_image = min(dim, feats.shape[1])
    n = tfeat.shape[0]
    for k in range(k_from, min(k_to, n)):
        g = isect_ids[start + k]
        a, b, c, o = conics[g, 0], conics[g, 1], conics[g, 2], opacities[g]
        threshold = math.log(ALPHA_MIN / o) - _THRESHOLD_MARGIN  # alpha >= 1/255  <=>  power >= log(1/(255 o))
        # rows within reach: max over x of the power on a row at offset dy is -dy^2 det / (2a)
        det = a * c - b * b
        reach_y = math.sqrt(max(-2.0 * threshold, 0.0) * a / det) + 1e-3
        table[_MX, k] = means2d[g, 0] - x_lo
        table[_MY, k] = means2d[g, 1]
        table[_CA, k] = a
        table[_CB, k] = b
        table[_CC, k] = c
        table[_OP, k] = o
        table[_TH, k] = threshold
        table[_YLO, k] = means2d[g, 1] - reach_y
        table[_YHI, k] = means2d[g, 1] + reach_y
        table[_INV_A, k] = 1.0 / a
        table[_B_OVER_A, k] = b / a
        table[_DET_OVER_A, k] = det / a
        for d in range(n_image):
            tfeat[k, d] = feats[g, d]
        for d in range(n_image, dim):
            tfeat[k, d] = extra_feats[g, d - n_image]
    for k in range(max(k_from, n), k_to):  # padding: finite values, and an empty row range
        for col in range(_N_COLS):
            table[col, k] = 0.0
        table[_YLO, k] = 1.0
        table[_YHI, k] = -1.0


@njit(cache=True)
def _cull_block(table, k0, k_limit, pyc, n_lanes, misses, hits):  # pragma: no cover - compiled
    """The Gaussians k0 .. min(k0 + CULL_BLOCK, k_limit) - 1 that reach this row, in order, into ``hits``;
    returns their count.

    One branch-free pass (vectorised) instead of a test and an unpredictable branch per Gaussian. Gaussian k
    misses the row when it cannot reach alpha >= 1/255 on any of its pixels (an exact test). The table's rows are
    read as 1-D slices: indexed as table[row, k] the loop stayed scalar (a square root per Gaussian).
    """
    stop = k0 + CULL_BLOCK
    mx, my, th = table[_MX, k0:stop], table[_MY, k0:stop], table[_TH, k0:stop]
    y_lo, y_hi = table[_YLO, k0:stop], table[_YHI, k0:stop]
    inv_a, b_over_a, det_over_a = table[_INV_A, k0:stop], table[_B_OVER_A, k0:stop], table[_DET_OVER_A, k0:stop]
    right = f32(n_lanes) - f32(0.5)
    for j in range(CULL_BLOCK):
        dy = my[j] - pyc
        # the row's largest power is -dy^2 det / (2a); alpha >= 1/255 where it is above the threshold
        reach = max(f32(-0.5) * dy * dy * det_over_a[j] - th[j], f32(0.0))
        half_width = math.sqrt(f32(2.0) * reach * inv_a[j]) + f32(1e-3)
        centre = mx[j] + b_over_a[j] * dy  # where the row's maximum lies, tile-local pixels
        outside = (centre + half_width < f32(0.5)) | (centre - half_width > right)
        misses[j] = f32(outside | (pyc < y_lo[j]) | (pyc > y_hi[j]) | (reach <= f32(0.0)) | (k0 + j >= k_limit))
    count = 0
    for j in range(CULL_BLOCK):
        hits[count] = k0 + j
        count += 1 - np.int64(misses[j])
    return count


@njit(cache=True, inline="always")
def _tile_box(tile, tiles_x, tile_size, width, height):  # pragma: no cover - compiled
    """Tile ``tile``'s pixels (row-major tiles): x_lo, y_lo, x_hi, y_hi (exclusive) and its row's lane count."""
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    x_lo, y_lo = tx * tile_size, ty * tile_size
    x_hi, y_hi = min(x_lo + tile_size, width), min(y_lo + tile_size, height)
    return x_lo, y_lo, x_hi, y_hi, x_hi - x_lo


@njit(cache=True, inline="always")
def _add_to_lanes(table, k, pyc, xs, trans, live, stop, weight):  # pragma: no cover - compiled
    """Gaussian k of a tile's table over one row's lanes, front to back: weight[lane] = its alpha x transmittance
    where it adds to the pixel, else 0 (it misses the pixel, the pixel is closed, or it would take the
    transmittance below 1e-4, which closes the pixel); trans, live and stop (the end of the pixel's contributing
    prefix in the tile list) move on. The forward pass and the reaching pass share it, so they agree bit for bit."""
    mx, dy = table[_MX, k], table[_MY, k] - pyc
    a, b, o, threshold = table[_CA, k], table[_CB, k], table[_OP, k], table[_TH, k]
    c_term = f32(-0.5) * table[_CC, k] * dy * dy
    end_if_added = f32(k + 1)
    for lane in range(LANES):  # vectorised: no branches, and every store unconditional
        dx = mx - xs[lane]
        power = f32(-0.5) * a * dx * dx - b * dx * dy + c_term
        alpha = min(f32(ALPHA_MAX), o * exp_nonpositive_unclamped(min(max(power, f32(_POWER_FLOOR)), f32(0.0))))
        t = trans[lane]
        hit = (live[lane] > f32(0.0)) & (power >= threshold) & (power <= f32(0.0)) & (alpha >= f32(ALPHA_MIN))
        next_trans = t * (f32(1.0) - alpha)
        adds = f32(hit & (next_trans >= f32(TRANSMITTANCE_MIN)))
        saturates = f32(hit & (next_trans < f32(TRANSMITTANCE_MIN)))  # the pixel is done
        live[lane] = live[lane] * (f32(1.0) - saturates)
        weight[lane] = alpha * t * adds
        trans[lane] = _blend(adds, next_trans, t)
        stop[lane] = _blend(adds, end_if_added, stop[lane])


@njit(parallel=True, cache=True, nogil=True)
def _forward_tiles(
    means2d, conics, opacities, feats, extra_feats, tile_offsets, isect_ids, tile_dims, row_dims, width, height, tile_size, tiles_x,
    out_img, out_extra, out_trans, out_end, workers
):  # pragma: no cover - compiled
    n_tiles = tile_offsets.shape[0] - 1
    n_image = out_img.shape[2]  # channels 0 .. n_image - 1 go to out_img, the rest to out_extra
    for worker in prange(workers):  # tiles dealt round-robin (see kernel_math.round_robin_workers)
        for tile in range(worker, n_tiles, workers):
            start, end = tile_offsets[tile], tile_offsets[tile + 1]
            x_lo, y_lo, x_hi, y_hi, n_lanes = _tile_box(tile, tiles_x, tile_size, width, height)
            tx = tile % tiles_x
            dim = tile_dims[tile]  # its rows' most (at least n_image): the width of its tables; out_extra holds 0 past a row's
            n_k = end - start
            table = np.empty((_N_COLS, _padded(n_k)), dtype=np.float32)
            tfeat = np.empty((n_k, dim), dtype=np.float32)
            filled = 0  # table columns filled so far: on demand, a fill block at a time
            misses = np.empty(CULL_BLOCK, dtype=np.float32)
            hits = np.empty(CULL_BLOCK, dtype=np.int64)
            trans = np.empty(LANES, dtype=np.float32)
            weight = np.empty(LANES, dtype=np.float32)
            acc = np.empty((dim, LANES), dtype=np.float32)
            # per-lane state as float32 like the rest, so that the lane loop is one vector type (stop: exact to 2^24)
            stop = np.empty(LANES, dtype=np.float32)
            live = np.empty(LANES, dtype=np.float32)
            xs = np.empty(LANES, dtype=np.float32)
            for lane in range(LANES):
                xs[lane] = f32(lane) + f32(0.5)
            # the feature loop's lane count, as a value the compiler cannot see is 16: with a constant count it unrolled
            # the lanes and vectorised over channels instead (gathers and scatters; 2x slower)
            feature_lanes = max(n_lanes, LANES)
            for py in range(y_lo, y_hi):
                pyc = f32(py) + f32(0.5)
                row_dim = row_dims[py, tx]  # this row's channels
                for lane in range(LANES):
                    trans[lane] = 1.0
                    stop[lane] = 0.0
                    live[lane] = f32(1.0) if lane < n_lanes else f32(0.0)
                for d in range(row_dim):  # (a slice assignment here made the lane loops 2.5x slower)
                    for lane in range(LANES):
                        acc[d, lane] = 0.0
                for k0 in range(0, n_k, CULL_BLOCK):
                    if k0 == filled:
                        filled = min(filled + FILL_BLOCK, table.shape[1])
                        _fill_tile(means2d, conics, opacities, feats, extra_feats, isect_ids, start, x_lo, k0, filled, table, tfeat)
                    n_hits = _cull_block(table, k0, n_k, pyc, n_lanes, misses, hits)
                    for i in range(n_hits):
                        k = hits[i]
                        _add_to_lanes(table, k, pyc, xs, trans, live, stop, weight)
                        for d in range(row_dim):
                            f = tfeat[k, d]
                            for lane in range(feature_lanes):
                                acc[d, lane] += weight[lane] * f
                    # whether any pixel of the row is still open, once per block (it only saves work: closed lanes add 0)
                    n_live = f32(0.0)
                    for lane in range(LANES):
                        n_live += live[lane]
                    if n_live == f32(0.0):
                        break
                for lane in range(n_lanes):
                    px = x_lo + lane
                    for d in range(n_image):
                        out_img[py, px, d] = acc[d, lane]
                    for d in range(n_image, row_dim):
                        out_extra[py, px, d - n_image] = acc[d, lane]
                    out_trans[py, px] = trans[lane]
                    out_end[py, px] = np.int32(stop[lane])


@njit(parallel=True, cache=True, nogil=True)
def _reaching_tiles(
    means2d, conics, opacities, tile_offsets, isect_ids, slot_of_isect, tiles, pixels, width, height, tile_size, tiles_x,
    reached, workers,
):  # pragma: no cover - compiled
    """``reached[slot]`` = 1 for each (tile, Gaussian) intersection that adds to one of ``pixels`` [H, W] (uint8) in
    the listed ``tiles``: ``_forward_tiles``' cull and lane pass (``_add_to_lanes``), with the lanes of the other
    pixels closed from the start (a pixel's sums never depend on another's) and no channels composited."""
    for worker in prange(workers):  # tiles dealt round-robin (see kernel_math.round_robin_workers)
        for i in range(worker, tiles.shape[0], workers):
            tile = tiles[i]
            start, end = tile_offsets[tile], tile_offsets[tile + 1]
            n_k = end - start
            if n_k == 0:
                continue
            x_lo, y_lo, x_hi, y_hi, n_lanes = _tile_box(tile, tiles_x, tile_size, width, height)
            table = np.empty((_N_COLS, _padded(n_k)), dtype=np.float32)
            no_channels = np.empty((n_k, 0), dtype=np.float32)  # the table fill's feature arrays, with none to copy
            filled = 0
            misses = np.empty(CULL_BLOCK, dtype=np.float32)
            hits = np.empty(CULL_BLOCK, dtype=np.int64)
            trans = np.empty(LANES, dtype=np.float32)
            live = np.empty(LANES, dtype=np.float32)
            weight = np.empty(LANES, dtype=np.float32)
            stop = np.empty(LANES, dtype=np.float32)  # the lane pass's prefix ends, which nothing here reads
            xs = np.empty(LANES, dtype=np.float32)
            for lane in range(LANES):
                xs[lane] = f32(lane) + f32(0.5)
            for py in range(y_lo, y_hi):
                pyc = f32(py) + f32(0.5)
                n_live = f32(0.0)
                for lane in range(LANES):
                    trans[lane] = 1.0
                    stop[lane] = 0.0
                    live[lane] = f32(1.0) if lane < n_lanes and pixels[py, x_lo + lane] != 0 else f32(0.0)
                    n_live += live[lane]
                if n_live == f32(0.0):
                    continue
                for k0 in range(0, n_k, CULL_BLOCK):
                    if k0 == filled:
                        filled = min(filled + FILL_BLOCK, table.shape[1])
                        _fill_tile(means2d, conics, opacities, no_channels, no_channels, isect_ids, start, x_lo, k0, filled, table, no_channels)
                    n_hits = _cull_block(table, k0, n_k, pyc, n_lanes, misses, hits)
                    for j in range(n_hits):
                        k = hits[j]
                        _add_to_lanes(table, k, pyc, xs, trans, live, stop, weight)
                        total = f32(0.0)  # (summed apart from the lane pass, which a reduction would keep scalar)
                        for lane in range(LANES):
                            total += weight[lane]
                        if total > f32(0.0):  # a weight that adds is at least 1/255 x 1e-4
                            reached[slot_of_isect[start + k]] = 1
                    n_live = f32(0.0)
                    for lane in range(LANES):
                        n_live += live[lane]
                    if n_live == f32(0.0):
                        break


@njit(parallel=True, cache=True, nogil=True)
def _any_per_gaussian(reached, gauss_offsets, out):  # pragma: no cover - compiled
    """out[g] = whether any of Gaussian g's intersection slots is set."""
    for g in prange(gauss_offsets.shape[0] - 1):
        found = False
        for i in range(gauss_offsets[g], gauss_offsets[g + 1]):
            found = found or reached[i] != 0
        out[g] = found


@njit(parallel=True, cache=True, nogil=True, fastmath=_REDUCE_FASTMATH)
def _backward_tiles(
    means2d, conics, opacities, feats, extra_feats, tile_offsets, isect_ids, tile_dims, row_dims, width, height, tile_size,
    tiles_x, out_trans, out_end, grad_img, grad_extra, grad_alpha, slot_of_isect, isect_grads, extra_rows, isect_extra, workers,
):  # pragma: no cover - compiled
    """Per (tile, Gaussian) gradients, back to front.

    Per pixel, with G = dL/d(image) and T_k the transmittance in front of Gaussian k, alpha_k's gradient is
    G . (T_k f_k - B_k / (1 - alpha_k)) + dL/d(alpha_out) T_final / (1 - alpha_k), where B_k is the colour
    composited behind k. Only the scalar G . B_k is carried per pixel (not B_k per channel): it grows by
    weight_k (G . f_k). The conic and mean gradients are lane sums of q = gauss dL/d(alpha) and its first two
    moments in x, so a Gaussian's six sums are three reductions.
    """
    n_slots = isect_grads.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    n_image = grad_img.shape[2]  # channels from n_image on: their gradient is grad_extra's
    for worker in prange(workers):  # tiles dealt round-robin (see kernel_math.round_robin_workers)
        for tile in range(worker, n_tiles, workers):
            start, end = tile_offsets[tile], tile_offsets[tile + 1]
            if end == start:
                continue
            x_lo, y_lo, x_hi, y_hi, n_lanes = _tile_box(tile, tiles_x, tile_size, width, height)
            tx = tile % tiles_x
            dim = tile_dims[tile]  # the forward's channels: past a row's, constant 0 with no gradient
            feature_lanes = max(n_lanes, LANES)  # 16, as a value the compiler cannot unroll (see _forward_tiles)
            n_k = end - start
            table = np.empty((_N_COLS, _padded(n_k)), dtype=np.float32)
            tfeat = np.empty((n_k, dim), dtype=np.float32)
            # only the Gaussians in front of some pixel's end: the forward's saturated pixels never reach the rest
            k_tile_end = 0
            for py in range(y_lo, y_hi):
                for px in range(x_lo, x_hi):
                    k_tile_end = max(k_tile_end, out_end[py, px])
            _fill_tile(means2d, conics, opacities, feats, extra_feats, isect_ids, start, x_lo, 0, _padded(k_tile_end), table, tfeat)
            misses = np.empty(CULL_BLOCK, dtype=np.float32)
            hits = np.empty(CULL_BLOCK, dtype=np.int64)
            # gradient sums per (tile, Gaussian): each row adds its lane sums once (per-lane accumulators cost
            # 16x the read-modify-write traffic, measured ~25% of the backward)
            kgrads = np.zeros((k_tile_end, _N_PARAMS + dim), dtype=np.float32)
            trans = np.empty(LANES, dtype=np.float32)
            trans_final = np.empty(LANES, dtype=np.float32)
            g_alpha_out = np.empty(LANES, dtype=np.float32)
            stop = np.zeros(LANES, dtype=np.float32)  # float32 like the lanes' other state (exact to 2^24)
            g_out = np.empty((dim, LANES), dtype=np.float32)
            g_behind = np.empty(LANES, dtype=np.float32)  # G . (colour composited behind the current Gaussian)
            g_feat = np.empty(LANES, dtype=np.float32)  # G . f_k
            mask = np.empty(LANES, dtype=np.float32)
            gauss = np.empty(LANES, dtype=np.float32)
            inv = np.empty(LANES, dtype=np.float32)
            weight = np.empty(LANES, dtype=np.float32)
            g_a = np.empty(LANES, dtype=np.float32)
            xs = np.empty(LANES, dtype=np.float32)
            for lane in range(LANES):
                xs[lane] = f32(lane) + f32(0.5)
            for py in range(y_lo, y_hi):
                pyc = f32(py) + f32(0.5)
                row_dim = row_dims[py, tx]
                k_end = 0
                for lane in range(n_lanes):
                    px = x_lo + lane
                    stop[lane] = f32(out_end[py, px])
                    trans_final[lane] = out_trans[py, px]
                    g_alpha_out[lane] = grad_alpha[py, px]
                    for d in range(n_image):
                        g_out[d, lane] = grad_img[py, px, d]
                    for d in range(n_image, row_dim):
                        g_out[d, lane] = grad_extra[py, px, d - n_image]
                    k_end = max(k_end, out_end[py, px])
                for lane in range(n_lanes, LANES):
                    stop[lane] = 0.0
                    trans_final[lane] = 1.0
                    g_alpha_out[lane] = 0.0
                    for d in range(dim):
                        g_out[d, lane] = 0.0
                for lane in range(LANES):
                    trans[lane] = trans_final[lane]
                    g_behind[lane] = 0.0
                for k0 in range((k_end - 1) // CULL_BLOCK * CULL_BLOCK, -1, -CULL_BLOCK):
                    n_hits = _cull_block(table, k0, k_end, pyc, n_lanes, misses, hits)
                    for i in range(n_hits - 1, -1, -1):
                        k = hits[i]
                        k_f = f32(k)
                        mx, dy = table[_MX, k], table[_MY, k] - pyc
                        a, b, c, o, threshold = table[_CA, k], table[_CB, k], table[_CC, k], table[_OP, k], table[_TH, k]
                        c_term = f32(-0.5) * c * dy * dy
                        for lane in range(LANES):  # same alpha, bit for bit, as the forward pass; stores unconditional
                            dx = mx - xs[lane]
                            power = f32(-0.5) * a * dx * dx - b * dx * dy + c_term
                            gs = exp_nonpositive_unclamped(min(max(power, f32(_POWER_FLOOR)), f32(0.0)))
                            gauss[lane] = gs
                            alpha = min(f32(ALPHA_MAX), o * gs)
                            hit = (k_f < stop[lane]) & (power >= threshold) & (power <= f32(0.0)) & (alpha >= f32(ALPHA_MIN))
                            m = f32(hit)
                            mask[lane] = m
                            inv_l = f32(1.0) / (f32(1.0) - alpha)
                            inv[lane] = inv_l
                            t = _blend(m, trans[lane] * inv_l, trans[lane])  # transmittance in front of k
                            trans[lane] = t
                            weight[lane] = alpha * t * m
                            # d(out)/d(alpha_k) from 1 - T_final; the colour terms are added below
                            g_a[lane] = g_alpha_out[lane] * trans_final[lane] * inv_l
                        for lane in range(LANES):
                            g_feat[lane] = 0.0
                        for d in range(row_dim):
                            f = tfeat[k, d]
                            s_feat = f32(0.0)
                            for lane in range(feature_lanes):
                                g_feat[lane] += g_out[d, lane] * f
                                s_feat += g_out[d, lane] * weight[lane]
                            kgrads[k, _N_PARAMS + d] += s_feat
                        # lane sums, vectorised under `reassoc`: q = gauss dL/d(alpha) (alpha's clamp passes none)
                        s_q = s_qx = s_qxx = f32(0.0)
                        for lane in range(LANES):
                            g_alpha = g_a[lane] + trans[lane] * g_feat[lane] - g_behind[lane] * inv[lane]
                            g_behind[lane] += g_feat[lane] * weight[lane]
                            dx = mx - xs[lane]
                            passes = mask[lane] if o * gauss[lane] <= f32(ALPHA_MAX) else f32(0.0)
                            q = gauss[lane] * g_alpha * passes
                            s_q += q
                            s_qx += q * dx
                            s_qxx += q * dx * dx
                        # power = -a dx^2 / 2 - b dx dy - c dy^2 / 2 with dx = mean x - pixel x; d(alpha)/d(power) = o gauss
                        kgrads[k, 0] -= o * (a * s_qx + b * dy * s_q)
                        kgrads[k, 1] -= o * (c * dy * s_q + b * s_qx)
                        kgrads[k, 2] -= f32(0.5) * o * s_qxx
                        kgrads[k, 3] -= o * dy * s_qx
                        kgrads[k, 4] -= f32(0.5) * o * dy * dy * s_q
                        kgrads[k, 5] += s_q
            for k in range(k_tile_end):  # the rest stay 0: no pixel reached them
                slot = slot_of_isect[start + k]
                for j in range(n_slots):
                    isect_grads[slot, j] = kgrads[k, j]
                for j in range(n_slots, _N_PARAMS + dim):  # the extra channels': rows of their own tiles only
                    isect_extra[extra_rows[tile] + k, j - n_slots] = kgrads[k, j]


@njit(cache=True, nogil=True)
def _add_extra_per_gaussian(isect_extra, extra_rows, tile_offsets, isect_ids, out):  # pragma: no cover - compiled
    """Each Gaussian's gradient of the extra channels: the rows the backward wrote for the tiles that composite them
    (``extra_rows[tile]`` the first, -1 for the others), added in tile order (serially: they are few)."""
    for tile in range(extra_rows.shape[0]):
        first = extra_rows[tile]
        if first < 0:
            continue
        start = tile_offsets[tile]
        for k in range(tile_offsets[tile + 1] - start):
            g = isect_ids[start + k]
            for j in range(isect_extra.shape[1]):
                out[g, j] += isect_extra[first + k, j]


@njit(parallel=True, cache=True, nogil=True)
def _reduce_per_gaussian(isect_grads, gauss_offsets, out):  # pragma: no cover - compiled
    """Each Gaussian's gradient: the sum of its intersections' rows, which the backward wrote contiguously."""
    n = gauss_offsets.shape[0] - 1
    width = isect_grads.shape[1]
    for g in prange(n):
        for j in range(width):
            out[g, j] = 0.0
        for i in range(gauss_offsets[g], gauss_offsets[g + 1]):
            for j in range(width):
                out[g, j] += isect_grads[i, j]


def _tile_maxima(row_dims: np.ndarray, tile_size: int, tiles_y: int) -> np.ndarray:
    """[tiles_y * tiles_x] (row-major tiles): the most channels a row of each tile composites, from ``row_dims``
    [H, tiles_x]: the width of the tile's tables in the kernels."""
    height, tiles_x = row_dims.shape
    padded = np.zeros((tiles_y * tile_size, tiles_x), dtype=row_dims.dtype)
    padded[:height] = row_dims
    return padded.reshape(tiles_y, tile_size, tiles_x).max(axis=1).reshape(-1)


def _split_columns(features: Tensor, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-Gaussian features [N, D] as two contiguous float32 arrays, the first ``count`` columns and the others:
    tiles that composite the first ones only read a narrow array, which stays in cache where [N, D] rows would not."""
    values = float32_array(features)
    return np.ascontiguousarray(values[:, :count]), np.ascontiguousarray(values[:, count:])


class _CompositeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bins: TileBins, width: int, height: int, row_dims: np.ndarray, image_channels: int):  # type: ignore[override]
        if bins.tile_size > LANES:
            raise ValueError(f"the CPU kernel supports tiles up to {LANES} pixels wide, got {bins.tile_size}")
        ctx.set_materialize_grads(False)  # an output the loss does not read sends None, not a tensor of zeros
        dim = features.shape[1]
        img = np.empty((height, width, image_channels), dtype=np.float32)
        # the extra channels are written where a tile row composites them, zero elsewhere: a pooled zeroed buffer
        # (fresh zeroed pages fault in where the kernel writes: ~1.2 ms a step for 8 flow channels at 400x400)
        everywhere = bool((row_dims >= dim).all())
        shape = (height, width, dim - image_channels)
        # the image rows some tile row of which composites the extra channels: the only ones the kernel writes
        extra = np.empty(shape, dtype=np.float32) if everywhere else ZEROED_BUFFERS.zeros(*shape, rows=(row_dims > image_channels).any(axis=1))
        trans = np.empty((height, width), dtype=np.float32)
        end = np.empty((height, width), dtype=np.int32)
        feats, extra_feats = _split_columns(features, image_channels)
        tile_dims = _tile_maxima(row_dims, bins.tile_size, bins.tiles_y)
        args = (float32_array(means2d), float32_array(conics), float32_array(opacities), feats, extra_feats, bins.tile_offsets,
                bins.isect_ids, tile_dims, row_dims)
        _forward_tiles(*args, width, height, bins.tile_size, bins.tiles_x, img, extra, trans, end, round_robin_workers())
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.bins, ctx.trans, ctx.end, ctx.size = bins, trans, end, (width, height, image_channels)
        ctx.row_dims, ctx.tile_dims = row_dims, tile_dims
        dtype = features.dtype
        return torch.from_numpy(img).to(dtype), torch.from_numpy(1.0 - trans).to(dtype), torch.from_numpy(extra).to(dtype)

    @staticmethod
    def backward(ctx, grad_img: Tensor | None, grad_alpha: Tensor | None, grad_extra: Tensor | None):  # type: ignore[override]
        means2d, conics, opacities, features = ctx.saved_tensors
        bins: TileBins = ctx.bins
        width, height, image_channels = ctx.size
        n, dim = features.shape
        row_dims, tile_dims = ctx.row_dims, ctx.tile_dims
        if grad_extra is None:  # the extra channels add nothing to the loss: their tiles' backward skips them
            row_dims, tile_dims = np.minimum(row_dims, image_channels), np.minimum(tile_dims, image_channels)
            grad_extra = torch.zeros(0, 0, 0)
        img_grad = np.zeros((height, width, image_channels), np.float32) if grad_img is None else float32_array(grad_img)
        alpha_grad = np.zeros((height, width), np.float32) if grad_alpha is None else float32_array(grad_alpha)
        # per intersection, rows no pixel reached are 0; the extra channels' apart, for the tiles that composite them
        isect_grads = np.zeros((bins.num_intersections, _N_PARAMS + image_channels), dtype=np.float32)
        extra_tiles = tile_dims > image_channels
        lengths = np.diff(bins.tile_offsets) * extra_tiles
        extra_rows = np.where(extra_tiles, np.cumsum(lengths) - lengths, -1)
        isect_extra = np.zeros((int(lengths.sum()), dim - image_channels), dtype=np.float32)
        feats, extra_feats = _split_columns(features, image_channels)
        _backward_tiles(
            float32_array(means2d), float32_array(conics), float32_array(opacities), feats, extra_feats, bins.tile_offsets,
            bins.isect_ids, tile_dims, row_dims, width, height, bins.tile_size, bins.tiles_x, ctx.trans, ctx.end, img_grad,
            float32_array(grad_extra), alpha_grad, bins.slot_of_isect, isect_grads, extra_rows, isect_extra, round_robin_workers(),
        )
        per_gauss = np.empty((n, _N_PARAMS + image_channels), dtype=np.float64)
        _reduce_per_gaussian(isect_grads, bins.gauss_offsets, per_gauss)
        per_gauss_extra = np.zeros((n, dim - image_channels), dtype=np.float64)
        _add_extra_per_gaussian(isect_extra, extra_rows, bins.tile_offsets, bins.isect_ids, per_gauss_extra)
        g, g_extra = torch.from_numpy(per_gauss).to(features.dtype), torch.from_numpy(per_gauss_extra).to(features.dtype)
        return g[:, 0:2], g[:, 2:5], g[:, 5], torch.cat([g[:, _N_PARAMS:], g_extra], dim=1), None, None, None, None, None


@njit(parallel=True, cache=True, nogil=True)
def _finish_forward(image, alpha, background, rgb, depth):  # pragma: no cover - compiled
    height, width = alpha.shape
    for y in prange(height):
        for x in range(width):
            transmittance = f32(1.0) - alpha[y, x]
            for c in range(3):
                rgb[y, x, c] = image[y, x, c] + transmittance * background[c]
            depth[y, x] = image[y, x, 3]


@njit(parallel=True, cache=True, nogil=True)
def _finish_backward(grad_rgb, grad_depth, background, grad_image, grad_alpha):  # pragma: no cover - compiled
    """An empty ``grad_depth`` (no element) stands for a gradient autograd did not send: zeros."""
    height, width = grad_alpha.shape
    has_depth = grad_depth.size > 0
    for y in prange(height):
        for x in range(width):
            through_background = f32(0.0)
            for c in range(3):
                g = grad_rgb[y, x, c]
                grad_image[y, x, c] = g
                through_background += g * background[c]
            grad_alpha[y, x] = -through_background
            grad_image[y, x, 3] = grad_depth[y, x] if has_depth else f32(0.0)


class _FinishImageCPU(torch.autograd.Function):
    """The composited colour and depth [H, W, 3 + 1] and alpha -> rgb over the background and depth, each its own
    contiguous array, in one pass (and one pass back). In torch this was a split into views, a broadcast product
    and a sum, and their backward (a cat along the last dimension, a broadcast sum over the colour channels): ~5 ms
    of a training step at 400x400, where this takes ~1."""

    @staticmethod
    def forward(ctx, image: Tensor, alpha: Tensor, background: Tensor):  # type: ignore[override]
        ctx.set_materialize_grads(False)  # an output the loss does not read sends None, not a tensor of zeros
        height, width, _ = image.shape
        rgb = np.empty((height, width, 3), dtype=np.float32)
        depth = np.empty((height, width), dtype=np.float32)
        bg = float32_array(background)
        _finish_forward(float32_array(image), float32_array(alpha), bg, rgb, depth)
        ctx.bg, ctx.shape = bg, (height, width)
        return torch.from_numpy(rgb), torch.from_numpy(depth)

    @staticmethod
    def backward(ctx, grad_rgb: Tensor | None, grad_depth: Tensor | None):  # type: ignore[override]
        height, width = ctx.shape
        rgb = np.zeros((height, width, 3), dtype=np.float32) if grad_rgb is None else float32_array(grad_rgb)
        depth = np.empty((0, 0), dtype=np.float32) if grad_depth is None else float32_array(grad_depth)
        grad_image = np.empty((height, width, 4), dtype=np.float32)
        grad_alpha = np.empty((height, width), dtype=np.float32)
        _finish_backward(rgb, depth, ctx.bg, grad_image, grad_alpha)
        return torch.from_numpy(grad_image), torch.from_numpy(grad_alpha), None


def finish_image_cpu(image: Tensor, alpha: Tensor, background: Tensor) -> tuple[Tensor, Tensor]:
    """(rgb [H, W, 3] = colour + (1 - alpha) * background, depth [H, W]) from a composited image [H, W, 3 + 1]
    (colour, depth) and its alpha [H, W]: the arithmetic of ``rasterize``'s torch form, differentiable with respect
    to ``image`` and ``alpha`` (not ``background``), for float32 CPU tensors."""
    if image.dtype != torch.float32 or image.device.type != "cpu" or image.dim() != 3 or image.shape[-1] != 4:
        raise ValueError(f"finish_image_cpu: image must be a float32 CPU [H, W, 4] tensor, got {image.dtype} {list(image.shape)} on {image.device}")
    if background.requires_grad:
        raise ValueError("finish_image_cpu: the background gets no gradient here; composite it in torch to learn it")
    return _FinishImageCPU.apply(image, alpha, background)


def composite_cpu(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
    row_channels: Tensor | None = None,
    image_channels: int | None = None,
    bins: TileBins | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Same contract as ``composite_reference``: image [H, W, A], alpha [H, W] and extra [H, W, D - A],
    differentiable; a tile row composites only its ``row_channels`` [H, tiles_x] leading channels (and pays for
    those only). ``bins``: these Gaussians' tile lists when the caller has them (``bin_gaussians``), else made here."""
    if bins is None:
        bins = bin_gaussians(means2d, radii, depths, width, height, tile_size)
    longest = int(np.diff(bins.tile_offsets).max()) if bins.tile_offsets.shape[0] > 1 else 0
    if longest >= _MAX_TILE_LIST:
        raise ValueError(f"composite_cpu: a tile holds {longest} Gaussians; the kernel counts a pixel's list position "
                         f"in float32, exact below {_MAX_TILE_LIST}")
    dim = features.shape[1]
    image_channels = image_channel_count(image_channels, dim)
    if row_channels is None:
        row_dims = np.full((height, bins.tiles_x), dim, dtype=np.int64)
    else:  # every row composites the image's channels: the kernel writes those everywhere
        if tuple(row_channels.shape) != (height, bins.tiles_x):
            raise ValueError(f"composite_cpu: row_channels must be [H, tiles_x] = [{height}, {bins.tiles_x}], got {list(row_channels.shape)}")
        row_dims = np.clip(row_channels.detach().cpu().numpy().astype(np.int64), image_channels, dim)
    return _CompositeCPU.apply(means2d, conics, opacities, features, bins, width, height, row_dims, image_channels)


@torch.no_grad()
def gaussians_reaching_cpu(
    means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor, pixels: Tensor, tile_size: int = TILE_SIZE,
    bins: TileBins | None = None,
) -> Tensor:
    """[N] bool: the Gaussians that add to a pixel of ``pixels`` [H, W] (bool) in ``composite_cpu``'s render of
    these screen-space Gaussians (a non-zero weight alpha T there), by its own float32 arithmetic, so the set is
    exact: a Gaussian outside it gets no gradient from those pixels and changes nothing there.

    Used to skip per-Gaussian work for a loss that reads a few pixels (the flow loss). Gaussians hidden behind
    opaque ones, or whose alpha stays under 1/255 there, are left out, which a footprint test cannot see. Gaussians
    whose radius is 0 are culled, as in the render: pass 0 radii to leave out Gaussians known to miss the pixels
    (their boxes hold none), which makes the binning cheaper and changes nothing at those pixels. ``bins``: the
    render's own tile lists of these Gaussians (``bin_gaussians``; a render that made them needs no second binning)."""
    height, width = pixels.shape
    if means2d.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool)
    if tile_size > LANES:
        raise ValueError(f"the CPU kernel supports tiles up to {LANES} pixels wide, got {tile_size}")
    if bins is None:
        bins = bin_gaussians(means2d, radii, depths, width, height, tile_size)
    elif (bins.tile_size, bins.tiles_x, bins.tiles_y, bins.gauss_offsets.shape[0]) != (tile_size, *tile_grid(width, height, tile_size), means2d.shape[0] + 1):
        raise ValueError("gaussians_reaching_cpu: the tile lists were made for other Gaussians, another image size or tile size")
    mask = pixels.detach().to(device="cpu", dtype=torch.bool).contiguous()
    tiles = tiles_touched(mask, tile_size).reshape(-1)
    reached = np.zeros(bins.num_intersections, dtype=np.uint8)
    _reaching_tiles(
        float32_array(means2d), float32_array(conics), float32_array(opacities), bins.tile_offsets, bins.isect_ids,
        bins.slot_of_isect, tiles.nonzero().squeeze(1).numpy(), mask.numpy().view(np.uint8), width, height,
        tile_size, bins.tiles_x, reached, round_robin_workers(),
    )
    out = np.empty(means2d.shape[0], dtype=np.bool_)
    _any_per_gaussian(reached, bins.gauss_offsets, out)
    return torch.from_numpy(out)


def count_pixel_gaussian_pairs(bins: TileBins, width: int, height: int) -> int:
    """Pixel-Gaussian pairs a render visits (each tile's list length x its pixels): the work measure of benches."""
    ts = bins.tile_size
    cols = np.minimum(ts, width - ts * np.arange(bins.tiles_x))
    rows = np.minimum(ts, height - ts * np.arange(bins.tiles_y))
    pixels_per_tile = np.outer(rows, cols).reshape(-1)
    return int((np.diff(bins.tile_offsets) * pixels_per_tile).sum())
