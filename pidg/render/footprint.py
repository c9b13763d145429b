"""Which Gaussians can reach a set of pixels: their screen footprints tested against a pixel mask.

Why: a loss evaluated on a few pixels (the flow loss only sees the pixels its target supervises) gets nothing from
Gaussians whose footprint misses all of them, so their per-Gaussian extra channels need not be computed at all; the
compositor draws a Gaussian only inside the box ``means2d +- radii`` (radii bound the alpha >= 1/255 ellipse, see
:func:`pidg.render.projection.project_gaussians`), so a box that holds no masked pixel centre proves the Gaussian
adds nothing there. The test is conservative by one pixel on every side.

Two implementations of one test: :func:`footprints_touching_reference` (torch, any device) and a numba kernel for
CPU tensors (one pass over the mask and one over the Gaussians, where the torch version is ~30 small ops over N:
3.1 ms at 18k Gaussians and a 400x300 mask, against 0.7 ms, measured).
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit
from torch import Tensor


def pixel_count_table(mask: Tensor) -> Tensor:
    """Summed-area table [H + 1, W + 1] (int32: exact below 2^31 pixels) of a bool mask [H, W]:
    S[y, x] = mask[:y, :x].sum()."""
    if mask.dim() != 2:
        raise ValueError(f"pixel_count_table: mask must be [H, W], got {list(mask.shape)}")
    if mask.numel() >= 2**31:
        raise ValueError(f"pixel_count_table: {mask.numel()} pixels overflow its int32 counts")
    counts = F.pad(mask.to(torch.int32), (1, 0, 1, 0))
    return counts.cumsum(0, dtype=torch.int32).cumsum(1, dtype=torch.int32)


@torch.no_grad()
def footprints_touching(means2d: Tensor, radii: Tensor, mask: Tensor) -> Tensor:
    """[N] bool: True for Gaussians whose screen box ``means2d +- radii`` (pixels; radius 0 = culled) holds a pixel
    centre where ``mask`` [H, W] is True, with one pixel of slack on every side. The numba kernel on CPU tensors,
    :func:`footprints_touching_reference` elsewhere."""
    if mask.dim() != 2 or means2d.shape != (means2d.shape[0], 2) or radii.shape != means2d.shape:
        raise ValueError(f"footprints_touching: means2d and radii [N, 2] with a mask [H, W], got {list(means2d.shape)}, "
                         f"{list(radii.shape)}, {list(mask.shape)}")
    if means2d.device.type != "cpu" or radii.device.type != "cpu" or mask.device.type != "cpu":
        return footprints_touching_reference(means2d, radii, mask)
    m = means2d.detach().to(torch.float64).contiguous().numpy()
    r = radii.detach().to(torch.float64).contiguous().numpy()
    return torch.from_numpy(_footprints_kernel(m, r, mask.to(torch.bool).contiguous().numpy()))


@njit(cache=True, nogil=True)
def _footprints_kernel(means2d, radii, mask):  # pragma: no cover - compiled
    """:func:`footprints_touching_reference`'s test, line for line, on numpy arrays (float64 means and radii)."""
    h, w = mask.shape
    table = np.zeros((h + 1, w + 1), dtype=np.int64)
    for y in range(h):
        row = 0
        for x in range(w):
            row += 1 if mask[y, x] else 0
            table[y + 1, x + 1] = table[y, x + 1] + row
    n = means2d.shape[0]
    found = np.zeros(n, dtype=np.bool_)
    for g in range(n):
        mx, my, rx, ry = means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1]
        if not (rx > 0 and ry > 0 and math.isfinite(mx) and math.isfinite(my)):
            continue
        lo_x, hi_x = math.floor(mx - rx - 0.5) - 1.0, math.ceil(mx + rx - 0.5) + 1.0
        lo_y, hi_y = math.floor(my - ry - 0.5) - 1.0, math.ceil(my + ry - 0.5) + 1.0
        if hi_x < 0 or lo_x > w - 1 or hi_y < 0 or lo_y > h - 1:
            continue
        x0, x1 = int(max(lo_x, 0.0)), int(min(hi_x, w - 1.0))
        y0, y1 = int(max(lo_y, 0.0)), int(min(hi_y, h - 1.0))
        found[g] = table[y1 + 1, x1 + 1] - table[y0, x1 + 1] - table[y1 + 1, x0] + table[y0, x0] > 0
    return found


@torch.no_grad()
def footprints_touching_reference(means2d: Tensor, radii: Tensor, mask: Tensor) -> Tensor:
    """The torch reference of :func:`footprints_touching` (any device)."""
    h, w = mask.shape
    table = pixel_count_table(mask)
    m = means2d.detach().to(torch.float64)
    finite = torch.isfinite(m).all(dim=-1)
    m = torch.where(finite[:, None], m, 0.0)  # (not drawn; keeps NaN out of the integer boxes below)
    r = radii.detach().to(torch.float64)
    # pixel j (centre j + 0.5) can be drawn when |j + 0.5 - m| <= r: j in [m - r - 0.5, m + r - 0.5], plus slack
    lo = torch.floor(m - r - 0.5) - 1.0
    hi = torch.ceil(m + r - 0.5) + 1.0
    x0 = lo[:, 0].clamp(0, w - 1).long()
    x1 = hi[:, 0].clamp(-1, w - 1).long()
    y0 = lo[:, 1].clamp(0, h - 1).long()
    y1 = hi[:, 1].clamp(-1, h - 1).long()
    inside = (hi[:, 0] >= 0) & (lo[:, 0] <= w - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= h - 1)
    drawn = (radii > 0).all(dim=-1) & finite & inside
    y1p, x1p = (y1 + 1).clamp_min(0), (x1 + 1).clamp_min(0)
    flat, stride = table.reshape(-1), w + 1  # one flat gather per corner: cheaper than 2-D advanced indexing
    count = flat[y1p * stride + x1p] - flat[y0 * stride + x1p] - flat[y1p * stride + x0] + flat[y0 * stride + x0]
    return drawn & (count > 0)
