"""Training SSIM (3DGS zero-padded form): numba kernels for the value and its analytic gradient.

Why: at 400x400 the autograd SSIM of ``pidg.metrics`` (depthwise ``conv2d`` on 15 maps, then its
backward) was the largest single item of a CPU training step. SSIM only needs separable Gaussian blurs, and its
gradient w.r.t. the prediction is three more blurs of closed-form maps:

  s = A1 A2 / (B1 B2),  A1 = 2 mu_p mu_g + C1,  A2 = 2 cov + C2,  B1 = mu_p^2 + mu_g^2 + C1,  B2 = var_p + var_g + C2
  with mu = blur(x), var_p = blur(p^2) - mu_p^2, cov = blur(p g) - mu_p mu_g. Then
  dS/dp = blur(dS/dmu_p) + 2 p blur(dS/dE_pp) + g blur(dS/dE_pg)      (the zero-padded blur is self-adjoint)
  dS/dmu_p = 2 mu_g (A2 - A1) / (B1 B2) - 2 mu_p s (1/B1 - 1/B2),  dS/dE_pp = -s / B2,  dS/dE_pg = 2 A1 / (B1 B2).

Layout: the kernels read the [H, W, C] images in place as rows of W*C floats (channels interleaved), so no
transposed copy is made: the vertical pass is the same for every element of a row, and the horizontal pass takes
its taps C elements apart. The blur is separable, so its two passes can run in either order; here the vertical
pass runs first, on whole rows:

* forward, one image row at a time: the vertical pass forms p, g, p^2, g^2, p g from the 11 input rows around it
  and keeps the five sums in registers (the tap loop is unrolled, the loop over the row vectorises), writing one
  row per map into a buffer with 5*C zeros on both sides; the horizontal pass over those rows has fixed bounds, so
  it vectorises too, and evaluates s and the three derivative maps in the same loop. The derivative maps' own
  horizontal blur (the first half of the backward's blurs) follows at once, while the row is in cache, so the
  forward stores the three x-blurred derivative maps and no unblurred one.
* backward: only the vertical pass of those three maps is left, again 11 rows in registers, combined with p and
  g in the same loop.

Rows near the top and bottom edge, whose window is cut by the zero padding, take a slower loop that only adds
the taps inside the image (the same sums in the same order). Only a few small per-thread row buffers are
allocated; no full-image temporary except the x-blurred derivative maps the backward needs. Work is split into
bands of ``_BAND`` rows, a contiguous range of bands per thread; each band sums its SSIM values (per column in
float32, then the band in float64) into its own slot, and the slots are summed in a fixed order, so the value
does not depend on the number of threads and every output is the same bit for bit from run to run.

``pidg.metrics.ssim(..., padding="zeros")`` is the readable autograd reference the tests compare with.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.metrics import SSIM_K, SSIM_WIN_SIGMA, SSIM_WIN_SIZE

_BAND = 8  # rows per band: the unit of the deterministic value sum
_K = SSIM_WIN_SIZE  # taps; compile-time constants in the kernels, so the tap loops unroll
_R = SSIM_WIN_SIZE // 2
# Blur loops may contract multiply-adds into FMAs; nothing is reassociated, so each output is one fixed sequence of
# operations (the same on every run of a build) and the loops over a row vectorise without reordering any sum.
_FASTMATH = {"contract", "nsz", "arcp"}


def gaussian_window_1d(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    k = np.exp(-(x**2) / (2.0 * sigma**2))
    return (k / k.sum()).astype(np.float32)


_WINDOW = gaussian_window_1d()
_TAPS = tuple(np.float32(w) for w in _WINDOW)  # a global tuple: numba compiles it in as constants


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _vblur_5maps(p, g, y, vert, off):  # pragma: no cover - compiled
    """vert[:, off + i] = the vertical blur at row y of p, g, p^2, g^2, p g (rows [H, L]); zero outside the image."""
    height, length = p.shape
    if _R <= y < height - _R:  # the whole window inside: unrolled taps, sums in registers
        r0 = y - _R
        for i in range(length):
            s0 = s1 = s2 = s3 = s4 = np.float32(0.0)
            for k in range(_K):
                w = _TAPS[k]
                a = p[r0 + k, i]
                b = g[r0 + k, i]
                s0 += w * a
                s1 += w * b
                s2 += w * (a * a)
                s3 += w * (b * b)
                s4 += w * (a * b)
            vert[0, off + i] = s0
            vert[1, off + i] = s1
            vert[2, off + i] = s2
            vert[3, off + i] = s3
            vert[4, off + i] = s4
    else:  # cut by the edge: add the taps inside the image, in the same order
        for j in range(5):
            for i in range(length):
                vert[j, off + i] = np.float32(0.0)
        for k in range(_K):
            r = y - _R + k
            if 0 <= r < height:
                w = _TAPS[k]
                for i in range(length):
                    a = p[r, i]
                    b = g[r, i]
                    vert[0, off + i] += w * a
                    vert[1, off + i] += w * b
                    vert[2, off + i] += w * (a * a)
                    vert[3, off + i] += w * (b * b)
                    vert[4, off + i] += w * (a * b)


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _vblur_3maps(maps, y, out):  # pragma: no cover - compiled
    """out[j, i] = the vertical blur at row y of maps[j] ([3, H, L]); zero outside the image."""
    height, length = maps.shape[1], maps.shape[2]
    if _R <= y < height - _R:
        r0 = y - _R
        for i in range(length):
            s0 = s1 = s2 = np.float32(0.0)
            for k in range(_K):
                w = _TAPS[k]
                s0 += w * maps[0, r0 + k, i]
                s1 += w * maps[1, r0 + k, i]
                s2 += w * maps[2, r0 + k, i]
            out[0, i] = s0
            out[1, i] = s1
            out[2, i] = s2
    else:
        for j in range(3):
            for i in range(length):
                out[j, i] = np.float32(0.0)
        for k in range(_K):
            r = y - _R + k
            if 0 <= r < height:
                w = _TAPS[k]
                for i in range(length):
                    out[0, i] += w * maps[0, r, i]
                    out[1, i] += w * maps[1, r, i]
                    out[2, i] += w * maps[2, r, i]


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _ssim_row(vert, n_ch, c1, c2, col, derivs, off):  # pragma: no cover - compiled
    """Horizontal pass of one row of the five vertically blurred maps (``vert``, padded by R*C zeros; neighbours
    are C elements apart), then SSIM per element: col[i] += s; derivs[:, off + i] = dS/dmu_p, dS/dE_pp, dS/dE_pg
    (skipped when ``derivs`` has no rows)."""
    length = col.shape[0]
    if derivs.shape[0] == 0:
        for i in range(length):
            m0 = m1 = m2 = m3 = m4 = np.float32(0.0)
            for k in range(_K):
                w = _TAPS[k]
                m0 += w * vert[0, i + k * n_ch]
                m1 += w * vert[1, i + k * n_ch]
                m2 += w * vert[2, i + k * n_ch]
                m3 += w * vert[3, i + k * n_ch]
                m4 += w * vert[4, i + k * n_ch]
            mpg = m0 * m1
            a1 = np.float32(2.0) * mpg + c1
            a2 = np.float32(2.0) * (m4 - mpg) + c2
            b1 = m0 * m0 + m1 * m1 + c1
            b2 = (m2 - m0 * m0) + (m3 - m1 * m1) + c2
            col[i] += (a1 * a2) / (b1 * b2)
        return
    for i in range(length):
        m0 = m1 = m2 = m3 = m4 = np.float32(0.0)
        for k in range(_K):
            w = _TAPS[k]
            m0 += w * vert[0, i + k * n_ch]
            m1 += w * vert[1, i + k * n_ch]
            m2 += w * vert[2, i + k * n_ch]
            m3 += w * vert[3, i + k * n_ch]
            m4 += w * vert[4, i + k * n_ch]
        mpg = m0 * m1
        a1 = np.float32(2.0) * mpg + c1
        a2 = np.float32(2.0) * (m4 - mpg) + c2
        b1 = m0 * m0 + m1 * m1 + c1
        b2 = (m2 - m0 * m0) + (m3 - m1 * m1) + c2
        inv_b1b2 = np.float32(1.0) / (b1 * b2)
        inv_b1 = b2 * inv_b1b2
        inv_b2 = b1 * inv_b1b2
        s = a1 * a2 * inv_b1b2
        col[i] += s
        derivs[0, off + i] = np.float32(2.0) * m1 * (a2 - a1) * inv_b1b2 - np.float32(2.0) * m0 * s * (inv_b1 - inv_b2)
        derivs[1, off + i] = -s * inv_b2
        derivs[2, off + i] = np.float32(2.0) * a1 * inv_b1b2


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _hblur_3maps(padded, n_ch, y, out):  # pragma: no cover - compiled
    """out[j, y, i] = the horizontal blur of the padded rows ``padded[j]`` (neighbours C elements apart)."""
    length = out.shape[2]
    for i in range(length):
        s0 = s1 = s2 = np.float32(0.0)
        for k in range(_K):
            w = _TAPS[k]
            s0 += w * padded[0, i + k * n_ch]
            s1 += w * padded[1, i + k * n_ch]
            s2 += w * padded[2, i + k * n_ch]
        out[0, y, i] = s0
        out[1, y, i] = s1
        out[2, y, i] = s2


@njit(cache=True, inline="always")
def _band_range(chunk, n_chunks, n_bands):  # pragma: no cover - compiled
    return chunk * n_bands // n_chunks, (chunk + 1) * n_bands // n_chunks


@njit(parallel=True, cache=True, nogil=True, fastmath=_FASTMATH)
def _ssim_forward(p, g, n_ch, c1, c2, n_threads, band_sums, dx):  # pragma: no cover - compiled
    """p, g [H, W*C] -> band_sums [n_bands] (float64 sums of the SSIM map over each band of rows) and, unless dx
    has no maps, dx [3, H, W*C]: the derivative maps w.r.t. mu_p, E[p^2], E[p g], already blurred horizontally."""
    height, length = p.shape
    pad = _R * n_ch
    n_bands = band_sums.shape[0]
    n_chunks = min(n_threads, n_bands)
    n_derivs = 3 if dx.shape[0] > 0 else 0
    for chunk in prange(n_chunks):
        vert = np.zeros((5, length + 2 * pad), dtype=np.float32)
        derivs = np.zeros((n_derivs, length + 2 * pad), dtype=np.float32)
        col = np.empty(length, dtype=np.float32)
        b0, b1 = _band_range(chunk, n_chunks, n_bands)
        for band in range(b0, b1):
            col[:] = 0.0
            for y in range(band * _BAND, min(height, (band + 1) * _BAND)):
                _vblur_5maps(p, g, y, vert, pad)
                _ssim_row(vert, n_ch, c1, c2, col, derivs, pad)
                if n_derivs > 0:
                    _hblur_3maps(derivs, n_ch, y, dx)
            total = 0.0
            for i in range(length):
                total += col[i]
            band_sums[band] = total


@njit(parallel=True, cache=True, nogil=True, fastmath=_FASTMATH)
def _ssim_backward(p, g, dx, scale, n_threads, grad):  # pragma: no cover - compiled
    """grad [H, W*C] = scale * (blur(d_mu) + 2 p blur(d_pp) + g blur(d_pg)): the vertical pass over the forward's
    x-blurred maps dx [3, H, W*C], combined with p and g in the same loop."""
    height, length = p.shape
    n_bands = (height + _BAND - 1) // _BAND
    n_chunks = min(n_threads, n_bands)
    for chunk in prange(n_chunks):
        blurred = np.empty((3, length), dtype=np.float32)
        b0, b1 = _band_range(chunk, n_chunks, n_bands)
        for y in range(b0 * _BAND, min(height, b1 * _BAND)):
            _vblur_3maps(dx, y, blurred)
            for i in range(length):
                grad[y, i] = scale * (blurred[0, i] + np.float32(2.0) * p[y, i] * blurred[1, i] + g[y, i] * blurred[2, i])


@njit(parallel=True, cache=True, nogil=True, fastmath=_FASTMATH)
def _blur_maps(maps, n_threads, out):  # pragma: no cover - compiled
    """out = the zero-padded separable blur of maps [M, H, W]: vertical pass into a padded row, then horizontal."""
    n_maps, height, width = maps.shape
    n_rows = n_maps * height
    n_chunks = min(n_threads, n_rows)
    for chunk in prange(n_chunks):
        row = np.zeros(width + 2 * _R, dtype=np.float32)
        for job in range(chunk * n_rows // n_chunks, (chunk + 1) * n_rows // n_chunks):
            m, y = job // height, job % height
            for i in range(width):
                row[_R + i] = np.float32(0.0)
            for k in range(_K):
                r = y - _R + k
                if 0 <= r < height:
                    w = _TAPS[k]
                    for i in range(width):
                        row[_R + i] += w * maps[m, r, i]
            for i in range(width):
                s = np.float32(0.0)
                for k in range(_K):
                    s += _TAPS[k] * row[i + k]
                out[m, y, i] = s


def _rows(t: Tensor) -> np.ndarray:
    """[H, W, C] tensor -> [H, W*C] float32 rows (a view when it already is contiguous float32)."""
    height, width, n_ch = t.shape
    return t.detach().to(torch.float32).contiguous().numpy().reshape(height, width * n_ch)


def blur(maps: Tensor) -> Tensor:
    """[M, H, W] float32 -> same shape, blurred by the 11-tap sigma-1.5 Gaussian with zero padding."""
    src = maps.detach().to(torch.float32).contiguous().numpy()
    out = np.empty_like(src)
    _blur_maps(src, numba.get_num_threads(), out)
    return torch.from_numpy(out)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:  # type: ignore[override]
        p, g = _rows(pred), _rows(gt)
        n_ch = pred.shape[2]
        band_sums = np.empty((p.shape[0] + _BAND - 1) // _BAND, dtype=np.float64)
        need_grad = ctx.needs_input_grad[0]
        dx = np.empty((3 if need_grad else 0, *p.shape), dtype=np.float32)
        c1, c2 = np.float32(SSIM_K[0] ** 2), np.float32(SSIM_K[1] ** 2)
        _ssim_forward(p, g, n_ch, c1, c2, numba.get_num_threads(), band_sums, dx)
        if need_grad:
            ctx.save_for_backward(pred, gt)  # (re-read in backward: a view costs nothing, and autograd checks versions)
            ctx.dx = dx
        return torch.tensor(band_sums.sum() / p.size, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        pred, gt = ctx.saved_tensors
        p, g = _rows(pred), _rows(gt)
        out = np.empty_like(p)
        _ssim_backward(p, g, ctx.dx, np.float32(float(grad) / p.size), numba.get_num_threads(), out)
        return torch.from_numpy(out).view(pred.shape).to(pred.dtype), None


def fused_ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean zero-padded SSIM of ``pred`` vs ``gt`` (one [H, W, C] image each, same shape), float32.

    Differentiable in ``pred`` only (the ground truth is data). CPU tensors; the value equals
    ``metrics.ssim(pred, gt, padding="zeros")`` up to float32 rounding.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"fused_ssim: pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.dim() != 3:
        raise ValueError(f"fused_ssim: expected one image [H, W, C], got shape {tuple(pred.shape)}")
    if pred.device.type != "cpu":
        raise ValueError("fused_ssim: CPU tensors only (use metrics.ssim on other devices)")
    return _FusedSSIM.apply(pred, gt)
