"""Grid4D's warp of one Gaussian: the decoder's head outputs applied to a canonical Gaussian, with a numba kernel and
a torch reference.

Per row, from the heads' outputs ``[w (4), T (3), dr (4), ds (3)]`` (14 columns, in that order):

    q_x  = normalize((1, 0, 0, 0) + w)          the rigid warp's rotation
    mu'  = mu + (R(q_x) (mu - c) - (mu - c)) + half_extent * T      (a rotation about the box centre c)
    q'   = q_x * normalize((1, 0, 0, 0) + dr) * q   (q_x left out unless ``rotate_with_warp``)
    log s' = log s + ds

(``grid4d``'s module docstring says why). ``normalize`` is ``F.normalize(x, eps=1e-8)``, ``*`` the Hamilton product.

Two implementations behind :func:`apply_warp`:
  * :func:`apply_warp_reference`: the formulas above in torch (autograd; any device and dtype). CUDA uses it.
  * ``_WarpCPU``: one numba pass over the rows forward and one backward, float32, with the derivatives written out
    (below). In torch the same warp is ~60 small elementwise ops forward and twice as many backward: 14 ms of a
    ~150 ms CPU training step at 24k Gaussians, against well under 1 ms for the kernel (``pidg bench step``).

The backward, for the upstream gradients g_mu', g_q', g_ls':
  * g_ls = g_ds = g_ls';  g_T = half_extent * g_mu';
  * g_mu = R(q_x)^T g_mu' (the identity and -I of ``mu + R o - o`` cancel);
  * Hamilton products p = a * b: g_a = g_p * conj(b), g_b = conj(a) * g_p (left and right multiplication matrices
    are orthogonal up to |a|, |b|, with transposes the conjugates' matrices);
  * rotation f(q) = o + 2 w (u x o) + 2 u x (u x o) of o by q = (w, u): g_w = 2 g . (u x o),
    g_u = 2 w (o x g) + 2 (u x o) x g + 2 o x (g x u);
  * normalize: g_x = (g_q - q (q . g_q)) / max(|x|, eps) (just g_q / eps below eps, where normalize is x / eps).
Tests compare both passes with autograd through the reference in float64.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import float32_array
from pidg.models.deformation.base import quat_multiply, quat_rotate, unit_quat_from_delta
from pidg.models.deformation.hash_grid import HashGridBackend, resolve_backend

WARP_COLUMNS = (4, 3, 4, 3)  # the heads' columns: warp quaternion increment w, translation T, dr, ds
_EPS = 1e-8  # F.normalize's eps in unit_quat_from_delta
f32 = np.float32


def split_heads(heads: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(w [N, 4], T [N, 3], dr [N, 4], ds [N, 3]) from the heads' outputs [N, 14]."""
    return heads.split(WARP_COLUMNS, dim=-1)  # type: ignore[return-value]


def apply_warp_reference(
    means: Tensor, quats: Tensor, log_scales: Tensor, heads: Tensor, centre: Tensor, half_extent: Tensor,
    rotate_with_warp: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """The warp in torch (see the module docstring): (means', quats', log_scales')."""
    w, translation, dr, ds = split_heads(heads)
    q_warp = unit_quat_from_delta(w)
    offset = means - centre
    # mu + (R v - v) + T rather than c + R v + T: exactly mu when R = I and T = 0
    new_means = means + (quat_rotate(q_warp, offset) - offset) + translation * half_extent
    new_quats = quat_multiply(unit_quat_from_delta(dr), quats)
    if rotate_with_warp:
        new_quats = quat_multiply(q_warp, new_quats)
    return new_means, new_quats, log_scales + ds


# ----------------------------------------------------------------------------------------------------------------
# numba kernel


@njit(cache=True, inline="always")
def _unit(x0, x1, x2, x3):  # pragma: no cover - compiled
    """normalize((1, 0, 0, 0) + x) and the divisor max(|.|, eps)."""
    a0 = f32(1.0) + x0
    norm = max(np.sqrt(a0 * a0 + x1 * x1 + x2 * x2 + x3 * x3), f32(_EPS))
    return a0 / norm, x1 / norm, x2 / norm, x3 / norm, norm


@njit(cache=True, inline="always")
def _hamilton(aw, ax, ay, az, bw, bx, by, bz):  # pragma: no cover - compiled
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@njit(cache=True, inline="always")
def _cross(ax, ay, az, bx, by, bz):  # pragma: no cover - compiled
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(cache=True, inline="always")
def _unit_backward(gw, gx, gy, gz, qw, qx, qy, qz, norm):  # pragma: no cover - compiled
    """Gradient through q = x / max(|x|, eps) at q (unit unless |x| < eps, where it is x / eps)."""
    if norm > f32(_EPS):
        dot = gw * qw + gx * qx + gy * qy + gz * qz
        return (gw - qw * dot) / norm, (gx - qx * dot) / norm, (gy - qy * dot) / norm, (gz - qz * dot) / norm
    return gw / norm, gx / norm, gy / norm, gz / norm


@njit(parallel=True, cache=True, nogil=True)
def _warp_forward(means, quats, log_scales, heads, centre, half, rotate, out_means, out_quats, out_log_scales):  # pragma: no cover - compiled
    for i in prange(means.shape[0]):
        ww, wx, wy, wz, _ = _unit(heads[i, 0], heads[i, 1], heads[i, 2], heads[i, 3])
        ox, oy, oz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
        tx, ty, tz = _cross(wx, wy, wz, ox, oy, oz)
        tx, ty, tz = f32(2.0) * tx, f32(2.0) * ty, f32(2.0) * tz
        cx, cy, cz = _cross(wx, wy, wz, tx, ty, tz)
        out_means[i, 0] = means[i, 0] + (ww * tx + cx) + heads[i, 4] * half[0]
        out_means[i, 1] = means[i, 1] + (ww * ty + cy) + heads[i, 5] * half[1]
        out_means[i, 2] = means[i, 2] + (ww * tz + cz) + heads[i, 6] * half[2]
        dw, dx, dy, dz, _ = _unit(heads[i, 7], heads[i, 8], heads[i, 9], heads[i, 10])
        pw, px, py, pz = _hamilton(dw, dx, dy, dz, quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3])
        if rotate:
            pw, px, py, pz = _hamilton(ww, wx, wy, wz, pw, px, py, pz)
        out_quats[i, 0], out_quats[i, 1], out_quats[i, 2], out_quats[i, 3] = pw, px, py, pz
        for d in range(3):
            out_log_scales[i, d] = log_scales[i, d] + heads[i, 11 + d]


@njit(parallel=True, cache=True, nogil=True)
def _warp_backward(means, quats, heads, centre, half, rotate, g_means_out, g_quats_out, g_ls_out, g_means, g_quats, g_heads):  # pragma: no cover - compiled
    for i in prange(means.shape[0]):
        ww, wx, wy, wz, wnorm = _unit(heads[i, 0], heads[i, 1], heads[i, 2], heads[i, 3])
        dw, dx, dy, dz, dnorm = _unit(heads[i, 7], heads[i, 8], heads[i, 9], heads[i, 10])
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        gx, gy, gz = g_means_out[i, 0], g_means_out[i, 1], g_means_out[i, 2]
        # means: R(q_x)^T g = rotation of g by conj(q_x)
        tx, ty, tz = _cross(-wx, -wy, -wz, gx, gy, gz)
        tx, ty, tz = f32(2.0) * tx, f32(2.0) * ty, f32(2.0) * tz
        cx, cy, cz = _cross(-wx, -wy, -wz, tx, ty, tz)
        g_means[i, 0], g_means[i, 1], g_means[i, 2] = gx + ww * tx + cx, gy + ww * ty + cy, gz + ww * tz + cz
        # q_x through the rotation of o = mu - c
        ox, oy, oz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
        uox, uoy, uoz = _cross(wx, wy, wz, ox, oy, oz)
        a_x, a_y, a_z = _cross(ox, oy, oz, gx, gy, gz)
        b_x, b_y, b_z = _cross(uox, uoy, uoz, gx, gy, gz)
        gux, guy, guz = _cross(gx, gy, gz, wx, wy, wz)
        c_x, c_y, c_z = _cross(ox, oy, oz, gux, guy, guz)
        gqw_w = f32(2.0) * (gx * uox + gy * uoy + gz * uoz)
        gqw_x = f32(2.0) * (ww * a_x + b_x + c_x)
        gqw_y = f32(2.0) * (ww * a_y + b_y + c_y)
        gqw_z = f32(2.0) * (ww * a_z + b_z + c_z)
        # quaternion chain q' = q_x * (dq * q)
        hw, hx, hy, hz = g_quats_out[i, 0], g_quats_out[i, 1], g_quats_out[i, 2], g_quats_out[i, 3]
        if rotate:
            pw, px, py, pz = _hamilton(dw, dx, dy, dz, qw, qx, qy, qz)
            ew, ex, ey, ez = _hamilton(hw, hx, hy, hz, pw, -px, -py, -pz)  # g_qx += g * conj(p)
            gqw_w, gqw_x, gqw_y, gqw_z = gqw_w + ew, gqw_x + ex, gqw_y + ey, gqw_z + ez
            hw, hx, hy, hz = _hamilton(ww, -wx, -wy, -wz, hw, hx, hy, hz)  # g_p = conj(q_x) * g
        gdw, gdx, gdy, gdz = _hamilton(hw, hx, hy, hz, qw, -qx, -qy, -qz)  # g_dq = g_p * conj(q)
        g_quats[i, 0], g_quats[i, 1], g_quats[i, 2], g_quats[i, 3] = _hamilton(dw, -dx, -dy, -dz, hw, hx, hy, hz)
        g_heads[i, 0], g_heads[i, 1], g_heads[i, 2], g_heads[i, 3] = _unit_backward(gqw_w, gqw_x, gqw_y, gqw_z, ww, wx, wy, wz, wnorm)
        g_heads[i, 4], g_heads[i, 5], g_heads[i, 6] = gx * half[0], gy * half[1], gz * half[2]
        g_heads[i, 7], g_heads[i, 8], g_heads[i, 9], g_heads[i, 10] = _unit_backward(gdw, gdx, gdy, gdz, dw, dx, dy, dz, dnorm)
        for d in range(3):
            g_heads[i, 11 + d] = g_ls_out[i, d]


class _WarpCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, heads, centre, half_extent, rotate_with_warp: bool):  # type: ignore[override]
        n = means.shape[0]
        out = [np.empty((n, k), dtype=np.float32) for k in (3, 4, 3)]
        arrays = [float32_array(t) for t in (means, quats, log_scales, heads, centre, half_extent)]
        _warp_forward(*arrays, bool(rotate_with_warp), *out)
        ctx.save_for_backward(means, quats, heads, centre, half_extent)
        ctx.rotate = bool(rotate_with_warp)
        return tuple(torch.from_numpy(a) for a in out)

    @staticmethod
    def backward(ctx, g_means_out, g_quats_out, g_ls_out):  # type: ignore[override]
        means, quats, heads, centre, half_extent = ctx.saved_tensors
        n = means.shape[0]
        grads = [np.empty((n, k), dtype=np.float32) for k in (3, 4, 14)]
        _warp_backward(
            *(float32_array(t) for t in (means, quats, heads, centre, half_extent)), ctx.rotate,
            *(float32_array(g) for g in (g_means_out, g_quats_out, g_ls_out)), *grads,
        )
        g_means, g_quats, g_heads = (torch.from_numpy(a) for a in grads)
        return g_means, g_quats, g_ls_out.to(torch.float32), g_heads, None, None, None


def apply_warp_cpu(
    means: Tensor, quats: Tensor, log_scales: Tensor, heads: Tensor, centre: Tensor, half_extent: Tensor,
    rotate_with_warp: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """The numba kernel: same contract as ``apply_warp_reference`` (float32 arithmetic, first derivatives)."""
    return _WarpCPU.apply(means, quats, log_scales, heads, centre, half_extent, rotate_with_warp)


def apply_warp(
    means: Tensor, quats: Tensor, log_scales: Tensor, heads: Tensor, centre: Tensor, half_extent: Tensor,
    rotate_with_warp: bool = True, backend: HashGridBackend = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """(means', quats', log_scales') [N, 3], [N, 4], [N, 3] of canonical Gaussians warped by the heads' outputs
    [N, 14]; ``centre``, ``half_extent`` [3]: the deformation's normalisation box. The numba kernel for float32 CPU
    tensors (``backend`` as the hash grids': auto, cpu, torch), the torch reference otherwise; one dtype for all."""
    if heads.dim() != 2 or heads.shape[1] != sum(WARP_COLUMNS):
        raise ValueError(f"apply_warp: heads must be [N, {sum(WARP_COLUMNS)}], got {list(heads.shape)}")
    if resolve_backend(backend, heads) == "cpu":
        return apply_warp_cpu(means, quats, log_scales, heads, centre, half_extent, rotate_with_warp)
    return apply_warp_reference(means, quats, log_scales, heads, centre, half_extent, rotate_with_warp)

