"""Turning tensors into pictures: PNG writing, depth and scalar colour maps."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor


def to_uint8(image: Tensor) -> np.ndarray:
    """[H, W, 3] or [H, W] float in [0, 1] -> uint8 array."""
    return (image.detach().float().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def save_png(image: Tensor, path: Path | str) -> Path:
    """Write an [H, W, 3] or [H, W] image in [0, 1] as PNG, creating the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(to_uint8(image)).save(path)
    return path


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
