"""The flow channels of :func:`pidg.flow.gaussian_flow.flow_features` as numba kernels with a hand-written backward.

Why: per Gaussian the channels are ~40 scalar operations (two closed-form 2x2 square roots, a 2x2 product, the
affine offsets), which torch runs as ~60 small ops forward and ~100 backward, plus batched 2x2 matrix products; at
the ~7k Gaussians the flow loss reads per step that was ~6 of the ~10 ms its channels cost (projections aside).
One row-parallel pass each way does the same arithmetic.

Per Gaussian, with S_t = (a0, b0, c0) and S_{t+1} = (a1, b1, c1) (upper triangles of the 2D covariances):

    P = S_{t+1}^{1/2} = (S_{t+1} + s1 I) / t1,          s1 = sqrt(det S_{t+1}),  t1 = sqrt(tr S_{t+1} + 2 s1)
    Q = S_t^{-1/2}    = adj(S_t + s0 I) / (t0 s0),       s0 = sqrt(det S_t),      t0 = sqrt(tr S_t + 2 s0)
    M = P Q - I,   b = mu_{t+1} - mu_t - M mu_t,   b_v = mu_v - mu_t - M mu_t

and the backward is the chain rule through exactly these lines (P and Q are symmetric, so dL/dP = dL/dA Q and
dL/dQ = P dL/dA). Arithmetic is float64 inside (:func:`_row`); the torch form runs in the input dtype. Rows where
``keep`` is False are zero and get no gradient, as in the torch form. Tests compare both passes with autograd through it.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

_CHUNK = 512  # rows per parallel task


@njit(cache=True, inline="always")
def _roots(a0, b0, c0, a1, b1, c1):  # pragma: no cover - compiled
    """(P entries p00, p01, p11, Q entries q00, q01, q11, and s0, t0, s1, t1) of the module docstring."""
    s1 = math.sqrt(a1 * c1 - b1 * b1)
    t1 = math.sqrt(a1 + c1 + 2.0 * s1)
    s0 = math.sqrt(a0 * c0 - b0 * b0)
    t0 = math.sqrt(a0 + c0 + 2.0 * s0)
    u0 = t0 * s0
    return (a1 + s1) / t1, b1 / t1, (c1 + s1) / t1, (c0 + s0) / u0, -b0 / u0, (a0 + s0) / u0, s0, t0, s1, t1


@njit(cache=True, inline="always")
def _row(cov, i):  # pragma: no cover - compiled
    """Row i's (a, b, c) in float64 (``np.float64``: numba's ``float()`` of a float32 stays float32)."""
    return np.float64(cov[i, 0]), np.float64(cov[i, 1]), np.float64(cov[i, 2])


@njit(cache=True, inline="always")
def _minus_identity(p00, p01, p11, q00, q01, q11):  # pragma: no cover - compiled
    """M = P Q - I (row-major entries) for the symmetric P and Q of :func:`_roots`."""
    return p00 * q00 + p01 * q01 - 1.0, p00 * q01 + p01 * q11, p01 * q00 + p11 * q01, p01 * q01 + p11 * q11 - 1.0


@njit(parallel=True, cache=True, nogil=True)
def _forward(cov_t, cov_t1, mu_t, mu_t1, mu_v, keep, out):  # pragma: no cover - compiled
    """out [N, 6 or 8]: M (row-major), b, and b_v when ``mu_v`` has rows; zero rows where ``keep`` is False."""
    n = cov_t.shape[0]
    velocity = mu_v.shape[0] > 0
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            if not keep[i]:
                for j in range(out.shape[1]):
                    out[i, j] = 0.0
                continue
            (a0, b0, c0), (a1, b1, c1) = _row(cov_t, i), _row(cov_t1, i)
            p00, p01, p11, q00, q01, q11, _, _, _, _ = _roots(a0, b0, c0, a1, b1, c1)
            m00, m01, m10, m11 = _minus_identity(p00, p01, p11, q00, q01, q11)
            x, y = np.float64(mu_t[i, 0]), np.float64(mu_t[i, 1])
            mmu_x, mmu_y = m00 * x + m01 * y, m10 * x + m11 * y
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = m00, m01, m10, m11
            out[i, 4] = mu_t1[i, 0] - x - mmu_x
            out[i, 5] = mu_t1[i, 1] - y - mmu_y
            if velocity:
                out[i, 6] = mu_v[i, 0] - x - mmu_x
                out[i, 7] = mu_v[i, 1] - y - mmu_y


@njit(parallel=True, cache=True, nogil=True)
def _backward(cov_t, cov_t1, mu_t, keep, grad, g_cov_t, g_cov_t1, g_mu_t, g_mu_t1, g_mu_v):  # pragma: no cover - compiled
    """Gradients of the inputs from ``grad`` [N, 6 or 8] (the outputs' gradient); every output array is written."""
    n = cov_t.shape[0]
    velocity = grad.shape[1] == 8
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        for i in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            if not keep[i]:
                for j in range(3):
                    g_cov_t[i, j] = 0.0
                    g_cov_t1[i, j] = 0.0
                for j in range(2):
                    g_mu_t[i, j] = 0.0
                    g_mu_t1[i, j] = 0.0
                    if velocity:
                        g_mu_v[i, j] = 0.0
                continue
            (a0, b0, c0), (a1, b1, c1) = _row(cov_t, i), _row(cov_t1, i)
            p00, p01, p11, q00, q01, q11, s0, t0, s1, t1 = _roots(a0, b0, c0, a1, b1, c1)
            m00, m01, m10, m11 = _minus_identity(p00, p01, p11, q00, q01, q11)
            x, y = np.float64(mu_t[i, 0]), np.float64(mu_t[i, 1])
            # offsets: b = mu1 - mu - M mu (and b_v = mu_v - mu - M mu)
            gb_x, gb_y = np.float64(grad[i, 4]), np.float64(grad[i, 5])
            gv_x, gv_y = (np.float64(grad[i, 6]), np.float64(grad[i, 7])) if velocity else (0.0, 0.0)
            g_mmu_x, g_mmu_y = -(gb_x + gv_x), -(gb_y + gv_y)  # gradient of M mu
            g_mu_t1[i, 0], g_mu_t1[i, 1] = gb_x, gb_y
            if velocity:
                g_mu_v[i, 0], g_mu_v[i, 1] = gv_x, gv_y
            g_mu_t[i, 0] = g_mmu_x + m00 * g_mmu_x + m10 * g_mmu_y
            g_mu_t[i, 1] = g_mmu_y + m01 * g_mmu_x + m11 * g_mmu_y
            # M = P Q - I: dL/dA = dL/dM, with M mu's share
            ga00 = np.float64(grad[i, 0]) + g_mmu_x * x
            ga01 = np.float64(grad[i, 1]) + g_mmu_x * y
            ga10 = np.float64(grad[i, 2]) + g_mmu_y * x
            ga11 = np.float64(grad[i, 3]) + g_mmu_y * y
            # dL/dP = dL/dA Q, dL/dQ = P dL/dA; the symmetric entries' two gradients add
            gp00 = ga00 * q00 + ga01 * q01
            gp01 = (ga00 * q01 + ga01 * q11) + (ga10 * q00 + ga11 * q01)
            gp11 = ga10 * q01 + ga11 * q11
            gq00 = p00 * ga00 + p01 * ga10
            gq01 = (p00 * ga01 + p01 * ga11) + (p01 * ga00 + p11 * ga10)
            gq11 = p01 * ga01 + p11 * ga11
            # P = [[a1 + s1, b1], [b1, c1 + s1]] / t1
            g_t1 = -(gp00 * p00 + gp01 * p01 + gp11 * p11) / t1
            g_s1 = (gp00 + gp11) / t1 + g_t1 / t1  # t1 = sqrt(a1 + c1 + 2 s1)
            g_a1 = gp00 / t1 + g_t1 / (2.0 * t1) + g_s1 * c1 / (2.0 * s1)
            g_c1 = gp11 / t1 + g_t1 / (2.0 * t1) + g_s1 * a1 / (2.0 * s1)
            g_b1 = gp01 / t1 - g_s1 * b1 / s1
            # Q = [[c0 + s0, -b0], [-b0, a0 + s0]] / u0, u0 = t0 s0
            u0 = t0 * s0
            g_u0 = -(gq00 * q00 + gq01 * q01 + gq11 * q11) / u0
            g_t0 = g_u0 * s0
            g_s0 = (gq00 + gq11) / u0 + g_u0 * t0 + g_t0 / t0
            g_a0 = gq11 / u0 + g_t0 / (2.0 * t0) + g_s0 * c0 / (2.0 * s0)
            g_c0 = gq00 / u0 + g_t0 / (2.0 * t0) + g_s0 * a0 / (2.0 * s0)
            g_b0 = -gq01 / u0 - g_s0 * b0 / s0
            g_cov_t[i, 0], g_cov_t[i, 1], g_cov_t[i, 2] = g_a0, g_b0, g_c0
            g_cov_t1[i, 0], g_cov_t1[i, 1], g_cov_t1[i, 2] = g_a1, g_b1, g_c1


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _FlowChannelsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cov_t: Tensor, cov_t1: Tensor, mu_t: Tensor, mu_t1: Tensor, mu_v: Tensor | None, keep: Tensor):  # type: ignore[override]
        n = cov_t.shape[0]
        out = np.empty((n, 6 if mu_v is None else 8), dtype=np.float64)
        empty = np.empty((0, 2), dtype=np.float64)
        _forward(_np(cov_t), _np(cov_t1), _np(mu_t), _np(mu_t1), empty if mu_v is None else _np(mu_v), _np(keep), out)
        ctx.save_for_backward(cov_t, cov_t1, mu_t, keep)
        ctx.velocity = mu_v is not None
        return torch.from_numpy(out).to(cov_t.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        cov_t, cov_t1, mu_t, keep = ctx.saved_tensors
        n = cov_t.shape[0]
        g_cov_t, g_cov_t1 = np.empty((n, 3)), np.empty((n, 3))
        g_mu_t, g_mu_t1 = np.empty((n, 2)), np.empty((n, 2))
        g_mu_v = np.empty((n, 2) if ctx.velocity else (0, 2))
        _backward(_np(cov_t), _np(cov_t1), _np(mu_t), _np(keep), _np(grad), g_cov_t, g_cov_t1, g_mu_t, g_mu_t1, g_mu_v)
        dtype = cov_t.dtype
        grads = [torch.from_numpy(g).to(dtype) for g in (g_cov_t, g_cov_t1, g_mu_t, g_mu_t1)]
        return *grads, torch.from_numpy(g_mu_v).to(dtype) if ctx.velocity else None, None


def flow_channels_cpu(cov_t: Tensor, cov_t1: Tensor, mu_t: Tensor, mu_t1: Tensor, mu_v: Tensor | None, keep: Tensor) -> Tensor:
    """[N, 6] (or [N, 8] with ``mu_v``) flow channels of rows ``keep`` [N] bool (zero elsewhere), differentiable in
    the covariances (a, b, c) [N, 3] and the centres [N, 2]; CPU tensors. Covariances of kept rows must be SPD."""
    return _FlowChannelsCPU.apply(cov_t, cov_t1, mu_t, mu_t1, mu_v, keep.to(torch.bool))
