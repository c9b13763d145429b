"""Which Gaussians can reach a set of pixels: their screen footprints tested against a pixel mask.

Why: a loss evaluated on a few pixels (the flow loss only sees the pixels its target supervises) gets nothing from
Gaussians whose footprint misses all of them, so their per-Gaussian extra channels need not be computed at all; the
compositor draws a Gaussian only inside the box ``means2d +- radii`` (radii bound the alpha >= 1/255 ellipse, see
:func:`pidg.render.projection.project_gaussians`), so a box that holds no masked pixel centre proves the Gaussian
adds nothing there. The test is conservative by one pixel on every side.
"""
from __future__ import annotations

import torch
from torch import Tensor


def pixel_count_table(mask: Tensor) -> Tensor:
    """Summed-area table [H + 1, W + 1] (int64) of a bool mask [H, W]: S[y, x] = mask[:y, :x].sum()."""
    if mask.dim() != 2:
        raise ValueError(f"pixel_count_table: mask must be [H, W], got {list(mask.shape)}")
    table = torch.zeros(mask.shape[0] + 1, mask.shape[1] + 1, dtype=torch.int64, device=mask.device)
    table[1:, 1:] = mask.to(torch.int64).cumsum(0).cumsum(1)
    return table


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
    count = table[y1p, x1p] - table[y0, x1p] - table[y1p, x0] + table[y0, x0]
    return drawn & (count > 0)
