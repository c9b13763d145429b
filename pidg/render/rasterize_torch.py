"""Reference compositor in plain PyTorch (autograd only).

Readable rather than fast: it exists so the CPU kernel has something independent to be tested against, and as
a fallback where numba is unavailable. It walks 16x16 tiles in Python, but within a tile everything is
vectorised: the Gaussians overlapping the tile, sorted by depth, composited front to back with cumulative
products. The conventions are those of 3DGS: skip alpha < 1/255, clamp alpha to 0.99, and stop a pixel before
the Gaussian that would take its transmittance below 1e-4.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.render.projection import ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN, image_channel_count, tile_grid


def composite_reference(
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
) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha-composite per-Gaussian features [N, D]: returns the image [H, W, A] of the leading ``image_channels``
    A (None: all D), alpha [H, W], and the other channels' image ``extra`` [H, W, D - A].

    Gaussians with ``radii == 0`` are ignored. ``radii`` must bound every pixel where alpha >= 1/255 (as
    ``project_gaussians`` guarantees), otherwise contributions would be cut at tile borders. ``row_channels``
    [H, tiles_x]: each tile row (a tile's pixels on one image row) composites that many leading channels (never
    fewer than A); the others are 0 there (see ``rasterize``'s ``feature_pixels``).
    """
    dim = features.shape[1]
    image_channels = image_channel_count(image_channels, dim)
    image, alpha = _composite_all(means2d, conics, opacities, features, depths, radii, width, height, tile_size)
    if row_channels is not None:
        kept = channels_below(row_channels.clamp_min(image_channels), dim, width, height, tile_size)
        image = image * kept.to(image.dtype)
    colour, extra = image.split([image_channels, dim - image_channels], dim=-1)
    return colour, alpha, extra


def _composite_all(
    means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor, radii: Tensor, width: int,
    height: int, tile_size: int,
) -> tuple[Tensor, Tensor]:
    """``composite_reference``'s arithmetic: every channel of ``features`` [N, D] into one image [H, W, D], and
    alpha [H, W]."""
    dim = features.shape[1]
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    visible = (radii > 0).all(dim=-1)
    centre = means2d.detach()
    # tile index range covered by each Gaussian's bounding box [mean - radius, mean + radius]
    lo = torch.floor((centre - radii) / tile_size)
    hi = torch.floor((centre + radii) / tile_size)

    rows_out, alpha_rows = [], []
    for ty in range(tiles_y):
        y0, y1 = ty * tile_size, min((ty + 1) * tile_size, height)
        row_tiles, row_alpha = [], []
        for tx in range(tiles_x):
            x0, x1 = tx * tile_size, min((tx + 1) * tile_size, width)
            hit = visible & (lo[:, 0] <= tx) & (hi[:, 0] >= tx) & (lo[:, 1] <= ty) & (hi[:, 1] >= ty)
            idx = torch.nonzero(hit).squeeze(1)
            if idx.numel() == 0:
                row_tiles.append(features.new_zeros(y1 - y0, x1 - x0, dim))
                row_alpha.append(features.new_zeros(y1 - y0, x1 - x0))
                continue
            idx = idx[torch.argsort(depths.detach()[idx], stable=True)]
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1, dtype=means2d.dtype, device=means2d.device) + 0.5,
                torch.arange(x0, x1, dtype=means2d.dtype, device=means2d.device) + 0.5,
                indexing="ij",
            )
            pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # [P, 2]
            d = means2d[idx].unsqueeze(0) - pix.unsqueeze(1)  # [P, K, 2]
            a, b, c = conics[idx].unbind(-1)
            power = -0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) - b * d[..., 0] * d[..., 1]
            alpha = torch.clamp_max(opacities[idx] * torch.exp(power.clamp_max(0.0)), ALPHA_MAX)
            alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
            # stop rule: transmittance after each Gaussian is non-increasing, so "keep" is a prefix per pixel
            with torch.no_grad():
                keep = torch.cumprod(1.0 - alpha, dim=1) >= TRANSMITTANCE_MIN
            alpha = alpha * keep
            trans_after = torch.cumprod(1.0 - alpha, dim=1)
            trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], dim=1)
            weights = alpha * trans_before  # [P, K]
            tile_img = weights @ features[idx]  # [P, D]
            row_tiles.append(tile_img.reshape(y1 - y0, x1 - x0, dim))
            row_alpha.append((1.0 - trans_after[:, -1]).reshape(y1 - y0, x1 - x0))
        rows_out.append(torch.cat(row_tiles, dim=1))
        alpha_rows.append(torch.cat(row_alpha, dim=1))
    return torch.cat(rows_out, dim=0), torch.cat(alpha_rows, dim=0)


def channels_below(row_channels: Tensor, n_channels: int, width: int, height: int, tile_size: int = TILE_SIZE) -> Tensor:
    """[H, W, n_channels] bool: True for the channels a pixel's tile row composites (``row_channels`` [H,
    tiles_x], see ``composite_reference``)."""
    tiles_x, _ = tile_grid(width, height, tile_size)
    if tuple(row_channels.shape) != (height, tiles_x):
        raise ValueError(f"row_channels must be [H, tiles_x] = [{height}, {tiles_x}], got {list(row_channels.shape)}")
    per_pixel = row_channels.repeat_interleave(tile_size, 1)[:, :width]
    return torch.arange(n_channels, device=per_pixel.device) < per_pixel[..., None]
