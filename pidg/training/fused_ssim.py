"""Training SSIM (3DGS zero-padded form): numba kernels for the value and its analytic gradient.

Why: at 400x400 the autograd SSIM of ``pidg.metrics`` (depthwise ``conv2d`` on 15 maps, then its
backward) was the largest single item of a CPU training step. SSIM only needs separable Gaussian blurs, and its
gradient w.r.t. the prediction is three more blurs of closed-form maps:

  s = A1 A2 / (B1 B2),  A1 = 2 mu_p mu_g + C1,  A2 = 2 cov + C2,  B1 = mu_p^2 + mu_g^2 + C1,  B2 = var_p + var_g + C2
  with mu = blur(x), var_p = blur(p^2) - mu_p^2, cov = blur(p g) - mu_p mu_g. Then
  dS/dp = blur(dS/dmu_p) + 2 p blur(dS/dE_pp) + g blur(dS/dE_pg)      (the zero-padded blur is self-adjoint)
  dS/dmu_p = 2 mu_g (A2 - A1) / (B1 B2) - 2 mu_p s (1/B1 - 1/B2),  dS/dE_pp = -s / B2,  dS/dE_pg = 2 A1 / (B1 B2).

Each pass is one kernel that forms its maps on the fly, one band of 16 output rows of one channel per task: the
forward builds p, g, p^2, g^2, p g on the band's rows plus the window's margin, blurs them vertically then
horizontally a row at a time and evaluates s and the three derivative maps there; the backward does the same
with the derivative maps and combines them with p and g. No full-image temporary is made (building the maps
with torch ops around a blur kernel cost as much again as the blurs). The horizontal pass reads rows padded with
zeros, so its loops have fixed bounds and vectorise: with bounds clipped at the image edge they ran 8x slower,
which made the previous version of this module scalar (3.8x slower at 400x400, measured).

``pidg.metrics.ssim(..., padding="zeros")`` is the readable autograd reference the tests compare with.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.metrics import SSIM_K, SSIM_WIN_SIGMA, SSIM_WIN_SIZE

_BAND = 16  # output rows per parallel task
# Blur loops may contract multiply-adds into FMAs and reassociate nothing else: the result is the same on every run
# of a build (no reduction depends on the thread schedule), and the lane loops vectorise.
_BLUR_FASTMATH = {"contract", "nsz", "arcp"}


def gaussian_window_1d(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    k = np.exp(-(x**2) / (2.0 * sigma**2))
    return (k / k.sum()).astype(np.float32)


@njit(cache=True, inline="always", fastmath=_BLUR_FASTMATH)
def _blur_band_y(band, n_maps, row, kernel, out):  # pragma: no cover - compiled
    """out[j, radius + x] = sum_k kernel[k] band[j, row + k, x]: the vertical pass of one output row from a band
    whose rows are already zero-padded, written into a row with ``radius`` zeros on both sides (the horizontal pass
    then needs no bounds: loops with fixed bounds vectorise, clipped ones ran 8x slower, measured)."""
    width = band.shape[2]
    radius = kernel.shape[0] // 2
    for j in range(n_maps):
        for x in range(width + 2 * radius):
            out[j, x] = np.float32(0.0)
        for k in range(kernel.shape[0]):
            w = kernel[k]
            for x in range(width):
                out[j, radius + x] += w * band[j, row + k, x]


@njit(cache=True, inline="always", fastmath=_BLUR_FASTMATH)
def _blur_rows_x(padded, n_maps, kernel, out):  # pragma: no cover - compiled
    """out[j, x] = sum_k kernel[k] padded[j, x + k]: the horizontal pass over rows padded by ``radius`` zeros."""
    width = out.shape[1]
    for j in range(n_maps):
        for x in range(width):
            out[j, x] = np.float32(0.0)
        for k in range(kernel.shape[0]):
            w = kernel[k]
            for x in range(width):
                out[j, x] += w * padded[j, x + k]


@njit(parallel=True, cache=True, nogil=True)
def _blur_maps(maps, kernel, out):  # pragma: no cover - compiled
    """out = the zero-padded separable blur of maps [M, H, W], one band of rows per task."""
    n_maps, height, width = maps.shape
    radius = kernel.shape[0] // 2
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_maps * n_bands):
        m, y0 = job // n_bands, (job % n_bands) * _BAND
        y1 = min(height, y0 + _BAND)
        band = np.zeros((1, y1 - y0 + 2 * radius, width), dtype=np.float32)
        for r in range(y1 - y0 + 2 * radius):
            yy = y0 + r - radius
            if 0 <= yy < height:
                for x in range(width):
                    band[0, r, x] = maps[m, yy, x]
        vert = np.empty((1, width + 2 * radius), dtype=np.float32)
        horiz = np.empty((1, width), dtype=np.float32)
        for y in range(y0, y1):
            _blur_band_y(band, 1, y - y0, kernel, vert)
            _blur_rows_x(vert, 1, kernel, horiz)
            for x in range(width):
                out[m, y, x] = horiz[0, x]


@njit(parallel=True, cache=True, nogil=True, fastmath=_BLUR_FASTMATH)
def _ssim_forward(p, g, kernel, c1, c2, row_sums, derivs):  # pragma: no cover - compiled
    """p, g [C, H, W] -> row_sums [C, H] of the SSIM map, and derivs [3, C, H, W]: its derivative maps w.r.t.
    mu_p, E[p^2] and E[p g]. Each task takes one channel's band of output rows: it forms the five maps (p, g, p^2,
    g^2, p g) on the band's rows plus the window's margin (zero outside the image), blurs them vertically then
    horizontally one output row at a time, and evaluates SSIM there: no full-image temporary."""
    n_ch, height, width = p.shape
    radius = kernel.shape[0] // 2
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_ch * n_bands):
        c, y0 = job // n_bands, (job % n_bands) * _BAND
        y1 = min(height, y0 + _BAND)
        band = np.zeros((5, y1 - y0 + 2 * radius, width), dtype=np.float32)
        for r in range(y1 - y0 + 2 * radius):
            yy = y0 + r - radius
            if 0 <= yy < height:
                for x in range(width):
                    a, b = p[c, yy, x], g[c, yy, x]
                    band[0, r, x] = a
                    band[1, r, x] = b
                    band[2, r, x] = a * a
                    band[3, r, x] = b * b
                    band[4, r, x] = a * b
        vert = np.empty((5, width + 2 * radius), dtype=np.float32)
        mu = np.empty((5, width), dtype=np.float32)
        for y in range(y0, y1):
            _blur_band_y(band, 5, y - y0, kernel, vert)
            _blur_rows_x(vert, 5, kernel, mu)
            total = 0.0
            for x in range(width):
                mp, mg = mu[0, x], mu[1, x]
                a1 = np.float32(2.0) * mp * mg + c1
                a2 = np.float32(2.0) * (mu[4, x] - mp * mg) + c2
                b1 = mp * mp + mg * mg + c1
                b2 = (mu[2, x] - mp * mp) + (mu[3, x] - mg * mg) + c2
                inv_b1 = np.float32(1.0) / b1
                inv_b2 = np.float32(1.0) / b2
                inv_b1b2 = inv_b1 * inv_b2
                s = a1 * a2 * inv_b1b2
                total += s
                derivs[0, c, y, x] = np.float32(2.0) * mg * (a2 - a1) * inv_b1b2 - np.float32(2.0) * mp * s * (inv_b1 - inv_b2)
                derivs[1, c, y, x] = -s * inv_b2
                derivs[2, c, y, x] = np.float32(2.0) * a1 * inv_b1b2
            row_sums[c, y] = total


@njit(parallel=True, cache=True, nogil=True, fastmath=_BLUR_FASTMATH)
def _ssim_gradient(p, g, derivs, kernel, scale, grad):  # pragma: no cover - compiled
    """grad [C, H, W] = scale * (blur(d_mu) + 2 p blur(d_pp) + g blur(d_pg)) from the derivative maps, band by band
    like the forward (the zero-padded blur with a symmetric window is self-adjoint)."""
    n_ch, height, width = p.shape
    radius = kernel.shape[0] // 2
    n_bands = (height + _BAND - 1) // _BAND
    for job in prange(n_ch * n_bands):
        c, y0 = job // n_bands, (job % n_bands) * _BAND
        y1 = min(height, y0 + _BAND)
        band = np.zeros((3, y1 - y0 + 2 * radius, width), dtype=np.float32)
        for r in range(y1 - y0 + 2 * radius):
            yy = y0 + r - radius
            if 0 <= yy < height:
                for j in range(3):
                    for x in range(width):
                        band[j, r, x] = derivs[j, c, yy, x]
        vert = np.empty((3, width + 2 * radius), dtype=np.float32)
        blurred = np.empty((3, width), dtype=np.float32)
        for y in range(y0, y1):
            _blur_band_y(band, 3, y - y0, kernel, vert)
            _blur_rows_x(vert, 3, kernel, blurred)
            for x in range(width):
                grad[c, y, x] = scale * (blurred[0, x] + np.float32(2.0) * p[c, y, x] * blurred[1, x] + g[c, y, x] * blurred[2, x])


_WINDOW = gaussian_window_1d()


def _chw(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()


def blur(maps: Tensor) -> Tensor:
    """[M, H, W] float32 -> same shape, blurred by the 11-tap sigma-1.5 Gaussian with zero padding."""
    src = _chw(maps)
    out = np.empty_like(src)
    _blur_maps(src, _WINDOW, out)
    return torch.from_numpy(out)


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
        out = np.empty_like(p)
        _ssim_gradient(p, g, derivs, _WINDOW, np.float32(float(grad) / p.size), out)
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
