"""Pictures of optical flow: the Middlebury colour coding and quiver plots (numpy + PIL only).

Colour coding (Baker et al., "A Database and Evaluation Methodology for Optical Flow", IJCV 2011): hue is the
flow direction on a 55-colour wheel red -> yellow -> green -> cyan -> blue -> magenta, saturation the magnitude
relative to a maximum, so zero flow is white; vectors longer than the maximum are drawn darkened. With image y
pointing down, flow to the right is red, down yellow/orange, left cyan-blue, up blue-violet. Pass a fixed
``max_magnitude`` to keep colours comparable over the frames of a video.
"""
from __future__ import annotations

import numpy as np
import torch
from PIL import Image, ImageDraw
from torch import Tensor

# (number of colours, colour at the segment start); each segment blends to the next segment's start.
_WHEEL_SEGMENTS = (
    (15, (255, 0, 0)),  # red -> yellow
    (6, (255, 255, 0)),  # yellow -> green
    (4, (0, 255, 0)),  # green -> cyan
    (11, (0, 255, 255)),  # cyan -> blue
    (13, (0, 0, 255)),  # blue -> magenta
    (6, (255, 0, 255)),  # magenta -> red
)
_OUT_OF_RANGE_SHADE = 0.75  # colours of vectors beyond max_magnitude are darkened by this factor
_ARROW_HEAD = (0.3, 25.0)  # arrowhead length as a fraction of the arrow (capped at 4 px), half-angle in degrees


def _as_numpy(array: Tensor | np.ndarray) -> np.ndarray:
    return array.detach().cpu().numpy() if isinstance(array, Tensor) else np.asarray(array)


def make_colorwheel() -> np.ndarray:
    """The Middlebury colour wheel [55, 3] as float in [0, 255]."""
    rows = []
    for k, (count, start) in enumerate(_WHEEL_SEGMENTS):
        end = np.array(_WHEEL_SEGMENTS[(k + 1) % len(_WHEEL_SEGMENTS)][1], np.float64)
        start_a = np.array(start, np.float64)
        steps = np.floor(255.0 * np.arange(count) / count) / 255.0  # the standard's integer ramp
        rows.append(start_a + np.outer(steps, end - start_a))
    return np.concatenate(rows)


def flow_to_rgb(
    flow: Tensor | np.ndarray, max_magnitude: float | None = None, valid: Tensor | np.ndarray | None = None
) -> np.ndarray:
    """Flow [H, W, 2] (pixels, x right, y down) -> uint8 RGB [H, W, 3].

    ``max_magnitude``: the magnitude drawn fully saturated (default: the largest valid one in this field).
    Invalid (``valid`` False) or non-finite pixels are black.
    """
    f = _as_numpy(flow).astype(np.float64)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ValueError(f"flow must be [H, W, 2], got {list(f.shape)}")
    ok = np.isfinite(f).all(-1)
    if valid is not None:
        ok &= _as_numpy(valid).astype(bool)
    f = np.where(ok[..., None], f, 0.0)
    u, v = f[..., 0], f[..., 1]
    rad = np.hypot(u, v)
    if max_magnitude is None:
        max_magnitude = float(rad[ok].max()) if ok.any() else 1.0
    rad = rad / max(max_magnitude, 1e-12)

    wheel = make_colorwheel() / 255.0
    n = len(wheel)
    angle = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (angle + 1.0) / 2.0 * (n - 1)
    k0 = np.floor(fk).astype(np.int64) % n
    k1 = (k0 + 1) % n
    frac = (fk - np.floor(fk))[..., None]
    col = (1.0 - frac) * wheel[k0] + frac * wheel[k1]
    in_range = (rad <= 1.0)[..., None]
    col = np.where(in_range, 1.0 - rad[..., None] * (1.0 - col), col * _OUT_OF_RANGE_SHADE)
    col = np.where(ok[..., None], col, 0.0)
    return np.clip(np.floor(255.0 * col + 0.5), 0, 255).astype(np.uint8)


def _background(image: Tensor | np.ndarray | None, height: int, width: int) -> np.ndarray:
    if image is None:
        return np.full((height, width, 3), 255, np.uint8)
    img = _as_numpy(image)
    if img.dtype != np.uint8:
        img = np.clip(np.floor(img.astype(np.float64) * 255.0 + 0.5), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.shape[:2] != (height, width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} but the flow is {width}x{height}")
    return np.ascontiguousarray(img[..., :3])


def flow_quiver(
    flow: Tensor | np.ndarray,
    image: Tensor | np.ndarray | None = None,
    step: int = 16,
    scale: float = 1.0,
    color: tuple[int, int, int] | None = None,
    valid: Tensor | np.ndarray | None = None,
    min_magnitude: float = 0.1,
    max_magnitude: float | None = None,
) -> np.ndarray:
    """Arrows of a sparse set of flow vectors (one every ``step`` pixels, drawn ``scale`` x their length) over
    ``image`` ([H, W, 3] float in [0, 1] or uint8; white without one), as uint8 RGB [H, W, 3].

    Arrows take their vector's colour-wheel colour unless ``color`` is given; vectors shorter than
    ``min_magnitude`` pixels or invalid are skipped.
    """
    f = _as_numpy(flow).astype(np.float64)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ValueError(f"flow must be [H, W, 2], got {list(f.shape)}")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    h, w = f.shape[:2]
    ok = np.isfinite(f).all(-1) & (np.hypot(f[..., 0], f[..., 1]) >= min_magnitude)
    if valid is not None:
        ok &= _as_numpy(valid).astype(bool)
    colors = flow_to_rgb(f, max_magnitude=max_magnitude, valid=ok)
    canvas = Image.fromarray(_background(image, h, w))
    draw = ImageDraw.Draw(canvas)
    fraction, half_angle = _ARROW_HEAD[0], np.radians(_ARROW_HEAD[1])
    for i in range(step // 2, h, step):
        for j in range(step // 2, w, step):
            if not ok[i, j]:
                continue
            x0, y0 = j + 0.5, i + 0.5
            dx, dy = scale * f[i, j, 0], scale * f[i, j, 1]
            x1, y1 = x0 + dx, y0 + dy
            rgb = tuple(int(c) for c in colors[i, j]) if color is None else color
            draw.line([(x0, y0), (x1, y1)], fill=rgb, width=1)
            length = np.hypot(dx, dy)
            head = min(4.0, fraction * length)
            back = np.arctan2(-dy, -dx)
            for side in (-half_angle, half_angle):
                draw.line([(x1, y1), (x1 + head * np.cos(back + side), y1 + head * np.sin(back + side))], fill=rgb)
    return np.asarray(canvas)


def flow_rgb_tensor(flow: Tensor, max_magnitude: float | None = None, valid: Tensor | None = None) -> Tensor:
    """:func:`flow_to_rgb` as a float [H, W, 3] tensor in [0, 1], for ``save_png`` / TensorBoard images."""
    return torch.from_numpy(flow_to_rgb(flow, max_magnitude, valid)).float() / 255.0
