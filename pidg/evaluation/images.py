"""Turning tensors into pictures: PNG writing, depth and scalar colour maps."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

TITLE_STRIP_PX = 16  # height of the strip :func:`with_titles` adds (even, so a video's frame size stays even)


def to_uint8(image: Tensor) -> np.ndarray:
    """[H, W, 3] or [H, W] float in [0, 1] -> uint8 array."""
    return (image.detach().float().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def save_png(image: Tensor, path: Path | str) -> Path:
    """Write an [H, W, 3] or [H, W] image in [0, 1] as PNG, creating the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(to_uint8(image)).save(path)
    return path


def with_titles(image: Tensor, titles: Sequence[str]) -> Tensor:
    """``image`` [H, W, 3] in [0, 1], made of ``len(titles)`` panels of equal width side by side, with a black strip of
    :data:`TITLE_STRIP_PX` rows above it naming each panel (white, PIL's built-in font: no font file to ship; a title
    longer than its panel is cut at the panel's edge). A saved picture then says what it shows without the docs."""
    width = int(image.shape[1])
    if not titles or width % len(titles):
        raise ValueError(f"with_titles: an image {width} px wide cannot hold {len(titles)} equal panels")
    panel = width // len(titles)
    strip = Image.new("RGB", (width, TITLE_STRIP_PX))
    font = ImageFont.load_default()
    for k, title in enumerate(titles):
        label = Image.new("RGB", (panel, TITLE_STRIP_PX))
        ImageDraw.Draw(label).text((3, 2), title, fill=(255, 255, 255), font=font)
        strip.paste(label, (k * panel, 0))
    top = torch.from_numpy(np.asarray(strip).copy()).to(device=image.device, dtype=torch.float32).div_(255.0)
    return torch.cat([top, image.detach().float().clamp(0, 1)], dim=0)


def colorize_scalar(values: Tensor, valid: Tensor | None = None, lo: float | None = None, hi: float | None = None) -> Tensor:
    """Map a scalar image [H, W] to RGB with a perceptually ordered ramp (dark blue -> yellow); invalid = black."""
    v = values.detach().float()
    mask = torch.ones_like(v, dtype=torch.bool) if valid is None else valid
    if mask.any():
        lo = float(v[mask].min()) if lo is None else lo
        hi = float(v[mask].max()) if hi is None else hi
    else:
        lo, hi = 0.0, 1.0
    t = ((v - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    # a compact viridis-like ramp: three anchor colours blended piecewise
    anchors = torch.tensor([[0.267, 0.005, 0.329], [0.128, 0.567, 0.551], [0.993, 0.906, 0.144]], device=v.device)
    pos = t * (len(anchors) - 1)
    i0 = pos.floor().long().clamp(max=len(anchors) - 2)
    frac = (pos - i0).unsqueeze(-1)
    rgb = anchors[i0] * (1 - frac) + anchors[i0 + 1] * frac
    return rgb * mask.unsqueeze(-1)
