"""The motion-flow target of :func:`pidg.flow.decomposition.motion_flow_target` as numba kernels (CPU tensors).

Why: the torch form makes dozens of full-image temporaries, a float64 inverse per call and a ``max_pool2d`` for the
dilation; at 400x400 one target cost ~50 ms of a training step, rebuilt every few hundred steps per flow pair. The
arithmetic is a few dozen operations per pixel, so four row-parallel passes do it in a few ms:

  1. frame t+1's grid: back-project each pixel centre with its depth through camera t+1, project with camera t
     (p2), subtract p1 = p4 + backward flow -> motion flow and its validity (valid depth, in front of camera t,
     consistent backward flow);
  2. frame t's grid: bilinear lookup of that motion flow at p + forward(p), exactly as ``sample_bilinear``
     (``grid_sample``, ``align_corners=False``, border padding) and ``sample_mask`` (valid only where every neighbour
     with a non-zero weight is valid, and p + f(p) inside the image) do it, ANDed with the forward consistency;
     without a dataset mask, moving pixels are those whose warped flow exceeds the threshold;
  3. the square dilation of the motion mask, separably (rows, then columns);
  4. validity = warped validity AND dilated mask; the flow is zero elsewhere.

The torch functions in ``decomposition`` stay the readable reference; tests compare the two.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import float32_array
from pidg.render.camera import Camera

f32 = np.float32


@njit(cache=True, inline="always")
def _bilinear_setup(coord, size):  # pragma: no cover - compiled
    """grid_sample's source index for a pixel-centre coordinate (align_corners=False, border padding): the lower
    neighbour, the weight of the upper one, and whether the upper one is used at all."""
    g = coord * f32(2.0 / size) - f32(1.0)
    ix = ((g + f32(1.0)) * f32(size) - f32(1.0)) * f32(0.5)
    ix = min(max(ix, f32(0.0)), f32(size - 1))
    i0 = int(ix)  # ix >= 0: truncation is the floor, without floor's libm call
    w1 = ix - f32(i0)
    i1 = min(i0 + 1, size - 1)
    return i0, i1, w1


@njit(parallel=True, cache=True, nogil=True)
def _motion_on_frame1(depth1, backward, valid_backward, c2w1, w2c0, fx1, fy1, cx1, cy1, near1, fx0, fy0, cx0, cy0, near0,
                      motion, valid1):  # pragma: no cover - compiled
    height, width = depth1.shape
    for i in prange(height):
        py = f32(i) + f32(0.5)
        for j in range(width):
            px = f32(j) + f32(0.5)
            d = depth1[i, j]
            ok = math.isfinite(d) and d > near1
            d = d if ok else f32(1.0)
            xc = (px - cx1) / fx1 * d
            yc = (py - cy1) / fy1 * d
            wx = xc * c2w1[0, 0] + yc * c2w1[0, 1] + d * c2w1[0, 2] + c2w1[0, 3]
            wy = xc * c2w1[1, 0] + yc * c2w1[1, 1] + d * c2w1[1, 2] + c2w1[1, 3]
            wz = xc * c2w1[2, 0] + yc * c2w1[2, 1] + d * c2w1[2, 2] + c2w1[2, 3]
            x0 = wx * w2c0[0, 0] + wy * w2c0[0, 1] + wz * w2c0[0, 2] + w2c0[0, 3]
            y0 = wx * w2c0[1, 0] + wy * w2c0[1, 1] + wz * w2c0[1, 2] + w2c0[1, 3]
            z0 = wx * w2c0[2, 0] + wy * w2c0[2, 1] + wz * w2c0[2, 2] + w2c0[2, 3]
            inv_z = f32(1.0) / max(z0, f32(1e-6))
            u2 = fx0 * x0 * inv_z + cx0
            v2 = fy0 * y0 * inv_z + cy0
            good = ok and z0 > near0 and valid_backward[i, j]
            if good:
                motion[i, j, 0] = u2 - (px + backward[i, j, 0])
                motion[i, j, 1] = v2 - (py + backward[i, j, 1])
            else:
                motion[i, j, 0] = f32(0.0)
                motion[i, j, 1] = f32(0.0)
            valid1[i, j] = good


@njit(parallel=True, cache=True, nogil=True)
def _warp_to_frame0(motion, valid1, forward, valid_forward, derive_mask, threshold, flow, valid0, moving):  # pragma: no cover - compiled
    height, width = valid1.shape
    for i in prange(height):
        py = f32(i) + f32(0.5)
        for j in range(width):
            tx = f32(j) + f32(0.5) + forward[i, j, 0]
            ty = py + forward[i, j, 1]
            inside = math.isfinite(tx) and math.isfinite(ty) and tx >= 0 and tx <= width and ty >= 0 and ty <= height
            fx, fy, ok = f32(0.0), f32(0.0), False
            if inside and valid_forward[i, j]:
                x0, x1, wx = _bilinear_setup(tx, width)
                y0, y1, wy = _bilinear_setup(ty, height)
                a, b = f32(1.0) - wx, f32(1.0) - wy
                w00, w01, w10, w11 = a * b, wx * b, a * wy, wx * wy
                m = (w00 * f32(valid1[y0, x0]) + w01 * f32(valid1[y0, x1])) + (w10 * f32(valid1[y1, x0]) + w11 * f32(valid1[y1, x1]))
                ok = m > f32(1.0 - 1e-6)
                if ok:
                    fx = (w00 * motion[y0, x0, 0] + w01 * motion[y0, x1, 0]) + (w10 * motion[y1, x0, 0] + w11 * motion[y1, x1, 0])
                    fy = (w00 * motion[y0, x0, 1] + w01 * motion[y0, x1, 1]) + (w10 * motion[y1, x0, 1] + w11 * motion[y1, x1, 1])
            flow[i, j, 0] = fx
            flow[i, j, 1] = fy
            valid0[i, j] = ok
            if derive_mask:
                moving[i, j] = ok and math.sqrt(fx * fx + fy * fy) > threshold


@njit(parallel=True, cache=True, nogil=True)
def _dilate_rows(mask, radius, out):  # pragma: no cover - compiled
    height, width = mask.shape
    for i in prange(height):
        last = -(radius + 1) - 1  # column of the last True seen
        for j in range(min(radius, width)):
            if mask[i, j]:
                last = j
        for j in range(width):
            ahead = j + radius
            if ahead < width and mask[i, ahead]:
                last = ahead
            out[i, j] = last >= j - radius


@njit(parallel=True, cache=True, nogil=True)
def _dilate_cols_and_finish(rows, radius, valid0, flow):  # pragma: no cover - compiled
    height, width = rows.shape
    for j in prange(width):
        last = -(radius + 1) - 1
        for i in range(min(radius, height)):
            if rows[i, j]:
                last = i
        for i in range(height):
            ahead = i + radius
            if ahead < height and rows[ahead, j]:
                last = ahead
            keep = valid0[i, j] and last >= i - radius
            valid0[i, j] = keep
            if not keep:
                flow[i, j, 0] = f32(0.0)
                flow[i, j, 1] = f32(0.0)


def _np_bool(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.bool).contiguous().numpy()


def motion_flow_target_cpu(
    depth1: Tensor,
    camera0: Camera,
    camera1: Camera,
    forward: Tensor,
    backward: Tensor,
    valid_forward: Tensor | None,
    valid_backward: Tensor | None,
    motion_mask0: Tensor | None,
    dilation: int,
    motion_threshold: float,
) -> tuple[Tensor, Tensor]:
    """(flow_gt [H, W, 2] float32, valid [H, W] bool) of ``motion_flow_target``; inputs already shape-checked."""
    h, w = depth1.shape
    ones = np.ones((h, w), dtype=np.bool_)
    c2w1 = torch.linalg.inv(camera1.world_to_camera.to(dtype=torch.float64, device="cpu")).to(torch.float32).numpy()
    w2c0 = camera0.world_to_camera.to(dtype=torch.float32, device="cpu").numpy()
    motion = np.empty((h, w, 2), dtype=np.float32)
    valid1 = np.empty((h, w), dtype=np.bool_)
    _motion_on_frame1(
        float32_array(depth1), float32_array(backward), ones if valid_backward is None else _np_bool(valid_backward), c2w1, w2c0,
        f32(camera1.fx), f32(camera1.fy), f32(camera1.cx), f32(camera1.cy), f32(camera1.near),
        f32(camera0.fx), f32(camera0.fy), f32(camera0.cx), f32(camera0.cy), f32(camera0.near), motion, valid1,
    )
    flow = np.empty((h, w, 2), dtype=np.float32)
    valid0 = np.empty((h, w), dtype=np.bool_)
    derive = motion_mask0 is None
    moving = np.empty((h, w), dtype=np.bool_) if derive else _np_bool(motion_mask0)
    _warp_to_frame0(motion, valid1, float32_array(forward), ones if valid_forward is None else _np_bool(valid_forward), derive,
                    f32(motion_threshold), flow, valid0, moving)
    rows = np.empty((h, w), dtype=np.bool_)
    radius = max(int(dilation), 0)
    _dilate_rows(moving, radius, rows)
    _dilate_cols_and_finish(rows, radius, valid0, flow)
    return torch.from_numpy(flow), torch.from_numpy(valid0)
