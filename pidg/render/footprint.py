"""Which Gaussians can reach a set of pixels: their screen footprints tested against a pixel mask.

Why: a loss evaluated on a few pixels (the flow loss only sees the pixels its target supervises) gets nothing from
Gaussians whose footprint misses all of them, so their per-Gaussian extra channels need not be computed at all; the
compositor draws a Gaussian only inside the box ``means2d +- radii`` (radii bound the alpha >= 1/255 ellipse, see
:func:`pidg.render.projection.project_gaussians`), so a box that holds no masked pixel centre proves the Gaussian
adds nothing there. The test is conservative by one pixel on every side.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
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
    centre where ``mask`` [H, W] is True, with one pixel of slack on every side."""
    h, w = mask.shape
    table = pixel_count_table(mask)
    m = means2d.detach().to(torch.float64)
    r = radii.detach().to(torch.float64)
    # pixel j (centre j + 0.5) can be drawn when |j + 0.5 - m| <= r: j in [m - r - 0.5, m + r - 0.5], plus slack
    lo = torch.floor(m - r - 0.5) - 1.0
    hi = torch.ceil(m + r - 0.5) + 1.0
    x0 = lo[:, 0].clamp(0, w - 1).long()
    x1 = hi[:, 0].clamp(-1, w - 1).long()
    y0 = lo[:, 1].clamp(0, h - 1).long()
    y1 = hi[:, 1].clamp(-1, h - 1).long()
    inside = (hi[:, 0] >= 0) & (lo[:, 0] <= w - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= h - 1)
    drawn = (radii > 0).all(dim=-1) & torch.isfinite(m).all(dim=-1) & inside
    y1p, x1p = (y1 + 1).clamp_min(0), (x1 + 1).clamp_min(0)
    flat, stride = table.reshape(-1), w + 1  # one flat gather per corner: cheaper than 2-D advanced indexing
    count = flat[y1p * stride + x1p] - flat[y0 * stride + x1p] - flat[y1p * stride + x0] + flat[y0 * stride + x0]
    return drawn & (count > 0)
