"""Projection and SH colour of every Gaussian in one numba kernel, with a hand-written backward (CPU backend).

Why: :func:`pidg.render.projection.project_gaussians` and :func:`pidg.render.sh.sh_to_rgb` are ~100 small torch ops
over [N, 3] tensors; with autograd's bookkeeping and a second pass for the backward they cost several ms per
render at 20k Gaussians, more than their arithmetic (a few hundred flops per Gaussian). Here one parallel loop
over the Gaussians computes exactly what those functions compute (same clamps, culling and exact radii; float32
like gsplat), and one loop computes the gradients. Those two functions stay the readable reference: the tests
compare values and gradients against torch autograd through them.

Per Gaussian (w2c = [W | t], pinhole fx, fy, cx, cy):
    p = W mu + t;  1/z of the depth if near < z < far (else of 1, a finite dummy);  tan = clamp(x/z, y/z)
    J W rows: jw0 = fx/z W0 - fx tan_x/z W2,  jw1 = fy/z W1 - fy tan_y/z W2
    a_r = (R(q)^T jw_r) * s,  cov2d = (a0.a0 + eps, a0.a1, a1.a1 + eps),  conic = adj(cov2d) / det
    means2d = (fx x/z + cx, fy y/z + cy),  depth = z
    rgb = max(sum_k Y_k(dir) c_k + 1/2, 0),  dir = (mu - camera centre) / |mu - camera centre|
The backward applies the chain rule to these lines in reverse (derivatives written out below, each next to the
forward line it belongs to).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import float32_array
from pidg.render.camera import Camera
from pidg.render.projection import ALPHA_MIN, EPS2D, FRUSTUM_MARGIN, Projection
from pidg.render.sh import C0, C1, C2, C3

f32 = np.float32
_CHUNK = 256  # Gaussians per parallel task


def _camera_constants(camera: Camera) -> np.ndarray:
    """[26] float32: w2c rows (12), fx fy cx cy, width height near far, the four tan limits, camera centre (3)...
    packed so that the kernels take one array."""
    w2c = camera.world_to_camera.detach().to(device="cpu", dtype=torch.float64)
    lim_x_pos = (camera.width - camera.cx) / camera.fx + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.width / camera.fx
    lim_x_neg = camera.cx / camera.fx + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.width / camera.fx
    lim_y_pos = (camera.height - camera.cy) / camera.fy + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.height / camera.fy
    lim_y_neg = camera.cy / camera.fy + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.height / camera.fy
    centre = camera.camera_center.detach().to(device="cpu", dtype=torch.float64).reshape(3)
    values = [*w2c[:3, :4].reshape(-1).tolist(), camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
              camera.height, camera.near, camera.far, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg, *centre.tolist()]
    return np.asarray(values, dtype=np.float32)


_FX, _FY, _CX, _CY, _WIDTH, _HEIGHT, _NEAR, _FAR, _LXP, _LXN, _LYP, _LYN, _CENTRE = 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24


@njit(cache=True, inline="always")
def _rotmat(qw, qx, qy, qz, r):  # pragma: no cover - compiled
    """R of the unit quaternion (w, x, y, z) into r [3, 3] (the convention of ``quat_to_rotmat``)."""
    r[0, 0] = f32(1.0) - f32(2.0) * (qy * qy + qz * qz)
    r[0, 1] = f32(2.0) * (qx * qy - qw * qz)
    r[0, 2] = f32(2.0) * (qx * qz + qw * qy)
    r[1, 0] = f32(2.0) * (qx * qy + qw * qz)
    r[1, 1] = f32(1.0) - f32(2.0) * (qx * qx + qz * qz)
    r[1, 2] = f32(2.0) * (qy * qz - qw * qx)
    r[2, 0] = f32(2.0) * (qx * qz - qw * qy)
    r[2, 1] = f32(2.0) * (qy * qz + qw * qx)
    r[2, 2] = f32(1.0) - f32(2.0) * (qx * qx + qy * qy)


@njit(cache=True, inline="always")
def _sh_basis(degree, x, y, z, out):  # pragma: no cover - compiled
    """Real SH basis values Y_k at the unit direction (x, y, z), k < (degree + 1)^2 (``pidg.render.sh.sh_basis``)."""
    out[0] = f32(C0)
    if degree >= 1:
        out[1] = f32(-C1) * y
        out[2] = f32(C1) * z
        out[3] = f32(-C1) * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = f32(C2[0]) * x * y
        out[5] = f32(C2[1]) * y * z
        out[6] = f32(C2[2]) * (f32(2.0) * zz - xx - yy)
        out[7] = f32(C2[3]) * x * z
        out[8] = f32(C2[4]) * (xx - yy)
        if degree >= 3:
            out[9] = f32(C3[0]) * y * (f32(3.0) * xx - yy)
            out[10] = f32(C3[1]) * x * y * z
            out[11] = f32(C3[2]) * y * (f32(4.0) * zz - xx - yy)
            out[12] = f32(C3[3]) * z * (f32(2.0) * zz - f32(3.0) * xx - f32(3.0) * yy)
            out[13] = f32(C3[4]) * x * (f32(4.0) * zz - xx - yy)
            out[14] = f32(C3[5]) * z * (xx - yy)
            out[15] = f32(C3[6]) * x * (xx - f32(3.0) * yy)


@njit(cache=True, inline="always")
def _sh_basis_gradient(degree, x, y, z, g, out):  # pragma: no cover - compiled
    """out (3) = sum_k g[k] dY_k/d(x, y, z): the derivatives of each line of :func:`_sh_basis`."""
    gx = gy = gz = f32(0.0)
    if degree >= 1:
        gy += f32(-C1) * g[1]
        gz += f32(C1) * g[2]
        gx += f32(-C1) * g[3]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        gx += f32(C2[0]) * y * g[4]
        gy += f32(C2[0]) * x * g[4]
        gy += f32(C2[1]) * z * g[5]
        gz += f32(C2[1]) * y * g[5]
        gx += f32(-2.0 * C2[2]) * x * g[6]
        gy += f32(-2.0 * C2[2]) * y * g[6]
        gz += f32(4.0 * C2[2]) * z * g[6]
        gx += f32(C2[3]) * z * g[7]
        gz += f32(C2[3]) * x * g[7]
        gx += f32(2.0 * C2[4]) * x * g[8]
        gy += f32(-2.0 * C2[4]) * y * g[8]
        if degree >= 3:
            gx += f32(6.0 * C3[0]) * x * y * g[9]
            gy += f32(C3[0]) * (f32(3.0) * xx - f32(3.0) * yy) * g[9]
            gx += f32(C3[1]) * y * z * g[10]
            gy += f32(C3[1]) * x * z * g[10]
            gz += f32(C3[1]) * x * y * g[10]
            gx += f32(-2.0 * C3[2]) * x * y * g[11]
            gy += f32(C3[2]) * (f32(4.0) * zz - xx - f32(3.0) * yy) * g[11]
            gz += f32(8.0 * C3[2]) * y * z * g[11]
            gx += f32(-6.0 * C3[3]) * x * z * g[12]
            gy += f32(-6.0 * C3[3]) * y * z * g[12]
            gz += f32(C3[3]) * (f32(6.0) * zz - f32(3.0) * xx - f32(3.0) * yy) * g[12]
            gx += f32(C3[4]) * (f32(4.0) * zz - f32(3.0) * xx - yy) * g[13]
            gy += f32(-2.0 * C3[4]) * x * y * g[13]
            gz += f32(8.0 * C3[4]) * x * z * g[13]
            gx += f32(2.0 * C3[5]) * x * z * g[14]
            gy += f32(-2.0 * C3[5]) * y * z * g[14]
            gz += f32(C3[5]) * (xx - yy) * g[14]
            gx += f32(C3[6]) * (f32(3.0) * xx - f32(3.0) * yy) * g[15]
            gy += f32(-6.0 * C3[6]) * x * y * g[15]
    out[0], out[1], out[2] = gx, gy, gz


@njit(cache=True, inline="always")
def _unit_quat(quats, i):  # pragma: no cover - compiled
    """Row i of ``quats`` normalised (w, x, y, z), and 1/|q| for the normalisation's backward."""
    qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
    qn = f32(1.0) / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw * qn, qx * qn, qy * qn, qz * qn, qn


@njit(cache=True, inline="always")
def _view_point(cam, mx, my, mz):  # pragma: no cover - compiled
    """Camera-space point of a world centre and the perspective Jacobian's factors, shared by forward and backward:
    (x, y, z, in_depth, 1/z, x/z, y/z, tan_x, tan_y, fx/z, fx tan_x/z, fy/z, fy tan_y/z); the tangents clamped to the
    frustum's extent as 3DGS clamps them (1/z is taken with z = 1 outside [near, far], where the Gaussian is culled)."""
    fx, fy = cam[_FX], cam[_FY]
    x = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[3]
    y = cam[4] * mx + cam[5] * my + cam[6] * mz + cam[7]
    z = cam[8] * mx + cam[9] * my + cam[10] * mz + cam[11]
    in_depth = (z > cam[_NEAR]) and (z < cam[_FAR])
    inv_z = f32(1.0) / (z if in_depth else f32(1.0))
    tx_raw, ty_raw = x * inv_z, y * inv_z
    tan_x = min(max(tx_raw, -cam[_LXN]), cam[_LXP])
    tan_y = min(max(ty_raw, -cam[_LYN]), cam[_LYP])
    return x, y, z, in_depth, inv_z, tx_raw, ty_raw, tan_x, tan_y, fx * inv_z, fx * tan_x * inv_z, fy * inv_z, fy * tan_y * inv_z


@njit(parallel=True, cache=True, nogil=True)
def _project_forward(means, quats, scales, opacities, coeffs, degree, cam, eps2d,
                     means2d, conics, depths, cov2d, rgb, radii):  # pragma: no cover - compiled
    n = means.shape[0]
    fx, fy, cx, cy = cam[_FX], cam[_FY], cam[_CX], cam[_CY]
    width, height = cam[_WIDTH], cam[_HEIGHT]
    n_basis = (degree + 1) * (degree + 1)
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        r = np.empty((3, 3), dtype=np.float32)
        basis = np.empty(16, dtype=np.float32)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
            x, y, z, in_depth, inv_z, tx_raw, ty_raw, tan_x, tan_y, a0s, b0s, a1s, b1s = _view_point(cam, mx, my, mz)
            w, ux, uy, uz, qn = _unit_quat(quats, i)
            _rotmat(w, ux, uy, uz, r)
            aa = ab = cc = f32(0.0)
            for k in range(3):  # a_r[k] = (sum_j R[j, k] jw_r[j]) * s[k]
                v0 = f32(0.0)
                v1 = f32(0.0)
                for j in range(3):
                    jw0 = a0s * cam[j] - b0s * cam[8 + j]
                    jw1 = a1s * cam[4 + j] - b1s * cam[8 + j]
                    v0 += r[j, k] * jw0
                    v1 += r[j, k] * jw1
                e0, e1 = v0 * scales[i, k], v1 * scales[i, k]
                aa += e0 * e0
                ab += e0 * e1
                cc += e1 * e1
            a, b, c = aa + eps2d, ab, cc + eps2d
            det = a * c - b * b
            det_ok = det > f32(0.0)
            inv_det = f32(1.0) / (det if det_ok else f32(1.0))
            conics[i, 0], conics[i, 1], conics[i, 2] = c * inv_det, -b * inv_det, a * inv_det
            cov2d[i, 0], cov2d[i, 1], cov2d[i, 2] = a, b, c
            u, v = fx * x * inv_z + cx, fy * y * inv_z + cy
            means2d[i, 0], means2d[i, 1] = u, v
            depths[i] = z
            # radii (no gradient): the exact alpha >= 1/255 extent, as project_gaussians
            o = opacities[i]
            keep = in_depth and det_ok and o > f32(ALPHA_MIN) and math.isfinite(u) and math.isfinite(v)
            r2 = max(f32(2.0) * math.log(max(o, f32(ALPHA_MIN)) / f32(ALPHA_MIN)), f32(0.0)) * f32(1.0 + 1e-4)
            hx, hy = math.sqrt(r2 * max(a, f32(0.0))), math.sqrt(r2 * max(c, f32(0.0)))
            keep = keep and (u + hx > 0) and (u - hx < width) and (v + hy > 0) and (v - hy < height) and hx > 0 and hy > 0
            radii[i, 0] = np.int32(math.ceil(min(hx, f32(2**30)))) if keep else np.int32(0)  # (inf: a huge Gaussian)
            radii[i, 1] = np.int32(math.ceil(min(hy, f32(2**30)))) if keep else np.int32(0)
            if degree >= 0:
                dx, dy, dz = mx - cam[_CENTRE], my - cam[_CENTRE + 1], mz - cam[_CENTRE + 2]
                inv_len = f32(1.0) / max(math.sqrt(dx * dx + dy * dy + dz * dz), f32(1e-12))
                _sh_basis(degree, dx * inv_len, dy * inv_len, dz * inv_len, basis)
                for ch in range(3):
                    s = f32(0.0)
                    for k in range(n_basis):
                        s += basis[k] * coeffs[i, k, ch]
                    rgb[i, ch] = max(s + f32(0.5), f32(0.0))


@njit(cache=True, inline="always")
def _no_gradient_reaches(i, g_means2d, g_conics, g_depths, g_cov2d, g_rgb):  # pragma: no cover - compiled
    """True when every output gradient of Gaussian i is zero."""
    zero = g_depths[i] == f32(0.0)
    for k in range(2):
        zero = zero and g_means2d[i, k] == f32(0.0)
    for k in range(3):
        zero = zero and g_conics[i, k] == f32(0.0) and g_cov2d[i, k] == f32(0.0) and g_rgb[i, k] == f32(0.0)
    return zero


@njit(parallel=True, cache=True, nogil=True)
def _project_backward(means, quats, scales, coeffs, degree, cam, eps2d, g_means2d, g_conics, g_depths, g_cov2d, g_rgb,
                      grad_means, grad_quats, grad_scales, grad_coeffs):  # pragma: no cover - compiled
    n = means.shape[0]
    fx, fy = cam[_FX], cam[_FY]
    n_basis = (degree + 1) * (degree + 1)
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        r = np.empty((3, 3), dtype=np.float32)
        g_r = np.empty((3, 3), dtype=np.float32)
        jw = np.empty((2, 3), dtype=np.float32)
        vv = np.empty((2, 3), dtype=np.float32)
        g_jw = np.empty((2, 3), dtype=np.float32)
        basis = np.empty(16, dtype=np.float32)
        g_basis = np.empty(16, dtype=np.float32)
        g_unit = np.empty(3, dtype=np.float32)
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            if _no_gradient_reaches(i, g_means2d, g_conics, g_depths, g_cov2d, g_rgb):
                # (culled or unseen: exactly zero, without evaluating a Jacobian that may overflow float32)
                for k in range(3):
                    grad_means[i, k] = f32(0.0)
                    grad_scales[i, k] = f32(0.0)
                for k in range(4):
                    grad_quats[i, k] = f32(0.0)
                continue
            # ---- recompute the forward's intermediates
            mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
            x, y, z, in_depth, inv_z, tx_raw, ty_raw, tan_x, tan_y, a0s, b0s, a1s, b1s = _view_point(cam, mx, my, mz)
            w, ux, uy, uz, qn = _unit_quat(quats, i)
            _rotmat(w, ux, uy, uz, r)
            for j in range(3):
                jw[0, j] = a0s * cam[j] - b0s * cam[8 + j]
                jw[1, j] = a1s * cam[4 + j] - b1s * cam[8 + j]
            aa = ab = cc = f32(0.0)
            for k in range(3):
                v0 = r[0, k] * jw[0, 0] + r[1, k] * jw[0, 1] + r[2, k] * jw[0, 2]
                v1 = r[0, k] * jw[1, 0] + r[1, k] * jw[1, 1] + r[2, k] * jw[1, 2]
                vv[0, k], vv[1, k] = v0, v1
                e0, e1 = v0 * scales[i, k], v1 * scales[i, k]
                aa += e0 * e0
                ab += e0 * e1
                cc += e1 * e1
            a, b, c = aa + eps2d, ab, cc + eps2d
            det = a * c - b * b
            # ---- conic = adj(cov) / det and cov2d -> d/d(a, b, c)
            ga, gb, gc = g_cov2d[i, 0], g_cov2d[i, 1], g_cov2d[i, 2]
            k0, k1, k2 = g_conics[i, 0], g_conics[i, 1], g_conics[i, 2]
            if det > f32(0.0):
                # dQ = -Q dS Q for Q = S^-1 = [[q0, q1], [q1, q2]]: written with the conic itself, which stays finite
                # (-> 0) where det overflows float32 (a huge Gaussian), instead of c^2 / det^2 = inf * 0 = NaN
                inv_det = f32(1.0) / det
                q0, q1, q2 = c * inv_det, -b * inv_det, a * inv_det
                ga -= k0 * q0 * q0 + k1 * q0 * q1 + k2 * q1 * q1
                gb -= f32(2.0) * k0 * q0 * q1 + k1 * (q0 * q2 + q1 * q1) + f32(2.0) * k2 * q1 * q2
                gc -= k0 * q1 * q1 + k1 * q1 * q2 + k2 * q2 * q2
            else:  # det replaced by 1: conic = (c, -b, a)
                ga += k2
                gb -= k1
                gc += k0
            # ---- a = e0.e0 + eps, b = e0.e1, c = e1.e1 + eps with e_r = v_r * s
            for rr in range(2):
                for j in range(3):
                    g_jw[rr, j] = f32(0.0)
            for j in range(3):
                for k in range(3):
                    g_r[j, k] = f32(0.0)
            for k in range(3):
                s = scales[i, k]
                e0, e1 = vv[0, k] * s, vv[1, k] * s
                g_e0 = f32(2.0) * ga * e0 + gb * e1
                g_e1 = f32(2.0) * gc * e1 + gb * e0
                grad_scales[i, k] = g_e0 * vv[0, k] + g_e1 * vv[1, k]
                g_v0, g_v1 = g_e0 * s, g_e1 * s
                for j in range(3):  # v_r[k] = sum_j R[j, k] jw_r[j]
                    g_r[j, k] += g_v0 * jw[0, j] + g_v1 * jw[1, j]
                    g_jw[0, j] += g_v0 * r[j, k]
                    g_jw[1, j] += g_v1 * r[j, k]
            # ---- R(q / |q|): dR/dq of each entry, then the normalisation
            g_w = f32(2.0) * (-uz * g_r[0, 1] + uy * g_r[0, 2] + uz * g_r[1, 0] - ux * g_r[1, 2] - uy * g_r[2, 0] + ux * g_r[2, 1])
            g_x = f32(2.0) * (uy * g_r[0, 1] + uz * g_r[0, 2] + uy * g_r[1, 0] - f32(2.0) * ux * g_r[1, 1] - w * g_r[1, 2]
                              + uz * g_r[2, 0] + w * g_r[2, 1] - f32(2.0) * ux * g_r[2, 2])
            g_y = f32(2.0) * (-f32(2.0) * uy * g_r[0, 0] + ux * g_r[0, 1] + w * g_r[0, 2] + ux * g_r[1, 0] + uz * g_r[1, 2]
                              - w * g_r[2, 0] + uz * g_r[2, 1] - f32(2.0) * uy * g_r[2, 2])
            g_z = f32(2.0) * (-f32(2.0) * uz * g_r[0, 0] - w * g_r[0, 1] + ux * g_r[0, 2] + w * g_r[1, 0] - f32(2.0) * uz * g_r[1, 1]
                              + uy * g_r[1, 2] + ux * g_r[2, 0] + uy * g_r[2, 1])
            dot = w * g_w + ux * g_x + uy * g_y + uz * g_z
            grad_quats[i, 0] = (g_w - w * dot) * qn
            grad_quats[i, 1] = (g_x - ux * dot) * qn
            grad_quats[i, 2] = (g_y - uy * dot) * qn
            grad_quats[i, 3] = (g_z - uz * dot) * qn
            # ---- jw0 = a0s W0 - b0s W2, jw1 = a1s W1 - b1s W2
            g_a0s = g_jw[0, 0] * cam[0] + g_jw[0, 1] * cam[1] + g_jw[0, 2] * cam[2]
            g_b0s = -(g_jw[0, 0] * cam[8] + g_jw[0, 1] * cam[9] + g_jw[0, 2] * cam[10])
            g_a1s = g_jw[1, 0] * cam[4] + g_jw[1, 1] * cam[5] + g_jw[1, 2] * cam[6]
            g_b1s = -(g_jw[1, 0] * cam[8] + g_jw[1, 1] * cam[9] + g_jw[1, 2] * cam[10])
            g_inv_z = fx * g_a0s + fx * tan_x * g_b0s + fy * g_a1s + fy * tan_y * g_b1s
            g_tan_x, g_tan_y = fx * inv_z * g_b0s, fy * inv_z * g_b1s
            gxc = gyc = gzc = f32(0.0)
            if -cam[_LXN] <= tx_raw <= cam[_LXP]:  # the clamp passes the gradient inside (boundary included)
                gxc += g_tan_x * inv_z
                g_inv_z += g_tan_x * x
            if -cam[_LYN] <= ty_raw <= cam[_LYP]:
                gyc += g_tan_y * inv_z
                g_inv_z += g_tan_y * y
            # ---- means2d = (fx x / z + cx, fy y / z + cy), depth = z, 1/z
            gu, gv = g_means2d[i, 0], g_means2d[i, 1]
            gxc += gu * fx * inv_z
            gyc += gv * fy * inv_z
            g_inv_z += gu * fx * x + gv * fy * y
            gzc += g_depths[i]
            if in_depth:
                gzc -= g_inv_z * inv_z * inv_z
            # ---- p = W mu + t
            gmx = cam[0] * gxc + cam[4] * gyc + cam[8] * gzc
            gmy = cam[1] * gxc + cam[5] * gyc + cam[9] * gzc
            gmz = cam[2] * gxc + cam[6] * gyc + cam[10] * gzc
            # ---- colour
            if degree >= 0:
                dx, dy, dz = mx - cam[_CENTRE], my - cam[_CENTRE + 1], mz - cam[_CENTRE + 2]
                length = math.sqrt(dx * dx + dy * dy + dz * dz)
                inv_len = f32(1.0) / max(length, f32(1e-12))
                ex, ey, ez = dx * inv_len, dy * inv_len, dz * inv_len
                _sh_basis(degree, ex, ey, ez, basis)
                for k in range(n_basis):
                    g_basis[k] = f32(0.0)
                for ch in range(3):
                    s = f32(0.0)
                    for k in range(n_basis):
                        s += basis[k] * coeffs[i, k, ch]
                    g_raw = g_rgb[i, ch] if s + f32(0.5) >= f32(0.0) else f32(0.0)  # clamp_min passes at and above 0
                    for k in range(n_basis):
                        grad_coeffs[i, k, ch] = basis[k] * g_raw
                        g_basis[k] += coeffs[i, k, ch] * g_raw
                _sh_basis_gradient(degree, ex, ey, ez, g_basis, g_unit)
                if length > f32(1e-12):
                    dot_u = ex * g_unit[0] + ey * g_unit[1] + ez * g_unit[2]
                    gmx += (g_unit[0] - ex * dot_u) * inv_len
                    gmy += (g_unit[1] - ey * dot_u) * inv_len
                    gmz += (g_unit[2] - ez * dot_u) * inv_len
                else:
                    gmx += g_unit[0] * inv_len
                    gmy += g_unit[1] * inv_len
                    gmz += g_unit[2] * inv_len
                for k in range(n_basis, coeffs.shape[1]):
                    for ch in range(3):
                        grad_coeffs[i, k, ch] = f32(0.0)
            grad_means[i, 0], grad_means[i, 1], grad_means[i, 2] = gmx, gmy, gmz


def _grad(t: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
    return np.zeros(shape, dtype=np.float32) if t is None else float32_array(t)


class _ProjectShadeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, coeffs, camera, degree: int, eps2d: float):  # type: ignore[override]
        n = means.shape[0]
        cam = _camera_constants(camera)
        m, q, s, c = float32_array(means), float32_array(quats), float32_array(scales), float32_array(coeffs)
        means2d = np.empty((n, 2), dtype=np.float32)
        conics = np.empty((n, 3), dtype=np.float32)
        depths = np.empty(n, dtype=np.float32)
        cov2d = np.empty((n, 3), dtype=np.float32)
        rgb = np.empty((n, 3), dtype=np.float32)
        radii = np.empty((n, 2), dtype=np.int32)
        _project_forward(m, q, s, float32_array(opacities), c, degree, cam, np.float32(eps2d), means2d, conics, depths, cov2d, rgb, radii)
        ctx.save_for_backward(means, quats, scales, coeffs)
        ctx.cam, ctx.degree, ctx.eps2d = cam, degree, eps2d
        dtype = means.dtype
        out_radii = torch.from_numpy(radii)
        ctx.mark_non_differentiable(out_radii)
        ctx.set_materialize_grads(False)
        return (torch.from_numpy(means2d).to(dtype), torch.from_numpy(conics).to(dtype), torch.from_numpy(depths).to(dtype),
                torch.from_numpy(cov2d).to(dtype), torch.from_numpy(rgb).to(dtype), out_radii)

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_cov2d, g_rgb, _g_radii):  # type: ignore[override]
        means, quats, scales, coeffs = ctx.saved_tensors
        n = means.shape[0]
        grad_means = np.empty((n, 3), dtype=np.float32)
        grad_quats = np.empty((n, 4), dtype=np.float32)
        grad_scales = np.empty((n, 3), dtype=np.float32)
        grad_coeffs = np.zeros(tuple(coeffs.shape), dtype=np.float32)
        _project_backward(
            float32_array(means), float32_array(quats), float32_array(scales), float32_array(coeffs), ctx.degree, ctx.cam, np.float32(ctx.eps2d),
            _grad(g_means2d, (n, 2)), _grad(g_conics, (n, 3)), _grad(g_depths, (n,)), _grad(g_cov2d, (n, 3)),
            _grad(g_rgb, (n, 3)), grad_means, grad_quats, grad_scales, grad_coeffs,
        )
        dtype = means.dtype
        return (torch.from_numpy(grad_means).to(dtype), torch.from_numpy(grad_quats).to(dtype),
                torch.from_numpy(grad_scales).to(dtype), None, torch.from_numpy(grad_coeffs).to(dtype), None, None, None)


def project_and_shade_cpu(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, camera: Camera,
    sh_degree: int | None, eps2d: float = EPS2D,
) -> tuple[Projection, Tensor]:
    """``project_gaussians(means, quats, scales, opacities, camera)`` and the per-Gaussian RGB [N, 3] (``sh_to_rgb``
    of SH coefficients [N, K, 3] seen from the camera when ``sh_degree`` is given, else ``colors`` [N, 3] as they
    are), computed and differentiated by the numba kernels; CPU tensors."""
    if sh_degree is None:
        coeffs, degree = colors.new_zeros(colors.shape[0], 1, 3), -1
    else:
        coeffs, degree = colors, int(sh_degree)
    means2d, conics, depths, cov2d, rgb, radii = _ProjectShadeCPU.apply(
        means, quats, scales, opacities, coeffs, camera, degree, eps2d
    )
    if sh_degree is None:
        rgb = colors
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, cov2d=cov2d), rgb
