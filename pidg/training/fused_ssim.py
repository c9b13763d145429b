"""Training SSIM (3DGS zero-padded form): numba kernels for the value and its analytic gradient.

Why: at 400x400 the autograd SSIM of ``pidg.metrics`` (depthwise ``conv2d`` on 15 maps, then its
backward) was the largest single item of a CPU training step. SSIM only needs separable Gaussian blurs, and its
gradient w.r.t. the prediction is three more blurs of closed-form maps:

  s = A1 A2 / (B1 B2),  A1 = 2 mu_p mu_g + C1,  A2 = 2 cov + C2,  B1 = mu_p^2 + mu_g^2 + C1,  B2 = var_p + var_g + C2
  with mu = blur(x), var_p = blur(p^2) - mu_p^2, cov = blur(p g) - mu_p mu_g. Then
  dS/dp = blur(dS/dmu_p) + 2 p blur(dS/dE_pp) + g blur(dS/dE_pg)      (the zero-padded blur is self-adjoint)
  dS/dmu_p = 2 mu_g (A2 - A1) / (B1 B2) - 2 mu_p s (1/B1 - 1/B2),  dS/dE_pp = -s / B2,  dS/dE_pg = 2 A1 / (B1 B2).

Each pass is one kernel that forms its maps on the fly: the forward blurs p, g, p^2, g^2, p g and evaluates s and
the three derivative maps row by row; the backward blurs those and combines them with p and g. (Building the maps
with torch ops around a blur kernel cost as much again as the blurs: ~25 full-image temporaries per step.)
Work is split into bands of rows per channel, so both threads stay busy on 3-channel images.

``pidg.metrics.ssim(..., padding="zeros")`` is the readable autograd reference the tests compare with.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.metrics import SSIM_K, SSIM_WIN_SIGMA, SSIM_WIN_SIZE

_BAND = 16  # rows per parallel task


def gaussian_window_1d(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    k = np.exp(-(x**2) / (2.0 * sigma**2))
    return (k / k.sum()).astype(np.float32)


@njit(cache=True, inline="always")
def _blur_row_x(src, kernel, acc):  # pragma: no cover - compiled
    """acc[x] = sum_k kernel[k] src[x + k - radius], zero outside the row."""
    width = src.shape[0]
    radius = kernel.shape[0] // 2
    for x in range(width):
        acc[x] = 0.0
    for k in range(kernel.shape[0]):
        shift = k - radius
        w = kernel[k]
        for x in range(max(0, -shift), min(width, width - shift)):
            acc[x] += w * src[x + shift]


@njit(cache=True, inline="always")
def _blur_row_y(rows, j, c, y, kernel, acc):  # pragma: no cover - compiled
    """acc[x] = sum_k kernel[k] rows[j, c, y + k - radius, x], zero outside the image."""
    height, width = rows.shape[2], rows.shape[3]
    radius = kernel.shape[0] // 2
    for x in range(width):
        acc[x] = 0.0
    for k in range(max(0, radius - y), min(kernel.shape[0], height + radius - y)):
        w = kernel[k]
        yy = y + k - radius
        for x in range(width):
            acc[x] += w * rows[j, c, yy, x]


@njit(cache=True, inline="always")
def _store(acc, out, j, c, y):  # pragma: no cover - compiled
    for x in range(acc.shape[0]):
        out[j, c, y, x] = acc[x]


@njit(parallel=True, cache=True, nogil=True)
def _blur_pass(src, kernel, dst, along_y):  # pragma: no cover - compiled
    """dst = one pass of the separable blur of [J, C, H, W] maps, along x or (``along_y``) along y."""
    n_maps, n_ch, height, width = src.shape
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_maps * n_ch * n_bands):
        j, c, y0 = job // (n_ch * n_bands), (job // n_bands) % n_ch, (job % n_bands) * _BAND
        acc = np.empty(width, dtype=np.float32)
        for y in range(y0, min(height, y0 + _BAND)):
            if along_y:
                _blur_row_y(src, j, c, y, kernel, acc)
            else:
                _blur_row_x(src[j, c, y], kernel, acc)
            _store(acc, dst, j, c, y)


@njit(parallel=True, cache=True, nogil=True)
def _ssim_forward(p, g, kernel, c1, c2, row_sums, derivs):  # pragma: no cover - compiled
    """p, g [C, H, W] -> row_sums [C, H] of the SSIM map, and derivs [3, C, H, W]: its derivative maps w.r.t.
    mu_p, E[p^2] and E[p g]."""
    n_ch, height, width = p.shape
    rows = np.empty((5, n_ch, height, width), dtype=np.float32)  # x-blurred p, g, p^2, g^2, p g
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_ch * n_bands):
        c, y0 = job // n_bands, (job % n_bands) * _BAND
        src = np.empty((5, width), dtype=np.float32)
        acc = np.empty(width, dtype=np.float32)
        for y in range(y0, min(height, y0 + _BAND)):
            for x in range(width):
                a, b = p[c, y, x], g[c, y, x]
                src[0, x], src[1, x], src[2, x], src[3, x], src[4, x] = a, b, a * a, b * b, a * b
            for j in range(5):
                _blur_row_x(src[j], kernel, acc)
                _store(acc, rows, j, c, y)
    for job in prange(n_ch * n_bands):
        c, y0 = job // n_bands, (job % n_bands) * _BAND
        mu = np.empty((5, width), dtype=np.float32)
        for y in range(y0, min(height, y0 + _BAND)):
            for j in range(5):
                _blur_row_y(rows, j, c, y, kernel, mu[j])
            total = 0.0
            for x in range(width):
                mp, mg = mu[0, x], mu[1, x]
                a1 = np.float32(2.0) * mp * mg + c1
                a2 = np.float32(2.0) * (mu[4, x] - mp * mg) + c2
                b1 = mp * mp + mg * mg + c1
                b2 = (mu[2, x] - mp * mp) + (mu[3, x] - mg * mg) + c2
                inv_b1b2 = np.float32(1.0) / (b1 * b2)
                s = a1 * a2 * inv_b1b2
                total += s
                derivs[0, c, y, x] = np.float32(2.0) * mg * (a2 - a1) * inv_b1b2 - np.float32(2.0) * mp * s * (np.float32(1.0) / b1 - np.float32(1.0) / b2)
                derivs[1, c, y, x] = -s / b2
                derivs[2, c, y, x] = np.float32(2.0) * a1 * inv_b1b2
            row_sums[c, y] = total


@njit(parallel=True, cache=True, nogil=True)
def _ssim_gradient(p, g, blurred_x, kernel, scale, grad):  # pragma: no cover - compiled
    """grad [C, H, W] = scale * (blur(d_mu) + 2 p blur(d_pp) + g blur(d_pg)), from the x-blurred derivative maps."""
    n_ch, height, width = p.shape
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_ch * n_bands):
        c, y0 = job // n_bands, (job % n_bands) * _BAND
        blurred = np.empty((3, width), dtype=np.float32)
        for y in range(y0, min(height, y0 + _BAND)):
            for j in range(3):
                _blur_row_y(blurred_x, j, c, y, kernel, blurred[j])
            for x in range(width):
                grad[c, y, x] = scale * (blurred[0, x] + np.float32(2.0) * p[c, y, x] * blurred[1, x] + g[c, y, x] * blurred[2, x])


_WINDOW = gaussian_window_1d()


def _chw(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()


def blur(maps: Tensor) -> Tensor:
    """[M, H, W] float32 -> same shape, blurred by the 11-tap sigma-1.5 Gaussian with zero padding."""
    src = _chw(maps)[None]
    rows, out = np.empty_like(src), np.empty_like(src)
    _blur_pass(src, _WINDOW, rows, False)
    _blur_pass(rows, _WINDOW, out, True)
    return torch.from_numpy(out[0])


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:  # type: ignore[override]
        p, g = _chw(pred), _chw(gt)
        row_sums = np.empty(p.shape[:2], dtype=np.float64)
        derivs = np.empty((3, *p.shape), dtype=np.float32)
        c1, c2 = np.float32(SSIM_K[0] ** 2), np.float32(SSIM_K[1] ** 2)
        _ssim_forward(p, g, _WINDOW, c1, c2, row_sums, derivs)
        ctx.maps = (p, g, derivs)
        ctx.dtype = pred.dtype
        return torch.tensor(row_sums.sum() / p.size, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        p, g, derivs = ctx.maps
        blurred_x, out = np.empty_like(derivs), np.empty_like(p)
        _blur_pass(derivs, _WINDOW, blurred_x, False)
        _ssim_gradient(p, g, blurred_x, _WINDOW, np.float32(float(grad) / p.size), out)
        return torch.from_numpy(out).to(ctx.dtype), None


def fused_ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean zero-padded SSIM of ``pred`` vs ``gt`` ([H, W, C] or [C, H, W] maps with the same layout), float32.

    Differentiable in ``pred`` only (the ground truth is data). CPU tensors; the value equals
    ``metrics.ssim(pred, gt, padding="zeros")`` up to float32 rounding.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"fused_ssim: pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.dim() != 3:
        raise ValueError(f"fused_ssim: expected one image [H, W, C], got shape {tuple(pred.shape)}")
    if pred.device.type != "cpu":
        raise ValueError("fused_ssim: CPU tensors only (use metrics.ssim on other devices)")
    # [H, W, C] -> [C, H, W] maps (the kernels copy them to contiguous float32)
    chw_pred, chw_gt = pred.permute(2, 0, 1), gt.permute(2, 0, 1)
    return _FusedSSIM.apply(chw_pred, chw_gt)
