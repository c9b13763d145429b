"""Training SSIM (3DGS zero-padded form) with a numba blur and an analytic backward pass.

Why: at 400x400 the autograd SSIM of ``pidg.evaluation.metrics`` (depthwise ``conv2d`` on 15 maps, then its
backward) was the largest single item of a CPU training step. SSIM only needs separable Gaussian blurs, and its
gradient w.r.t. the prediction is three more blurs of closed-form maps:

  s = A1 A2 / (B1 B2),  A1 = 2 mu_p mu_g + C1,  A2 = 2 cov + C2,  B1 = mu_p^2 + mu_g^2 + C1,  B2 = var_p + var_g + C2
  with mu = blur(x), var_p = blur(p^2) - mu_p^2, cov = blur(p g) - mu_p mu_g. Then
  dS/dp = blur(dS/dmu_p) + 2 p blur(dS/dE_pp) + g blur(dS/dE_pg)      (the zero-padded blur is self-adjoint)
  dS/dmu_p = 2 mu_g (A2 - A1) / (B1 B2) - 2 mu_p s (1/B1 - 1/B2),  dS/dE_pp = -s / B2,  dS/dE_pg = 2 A1 / (B1 B2).

``pidg.evaluation.metrics.ssim(..., padding="zeros")`` is the readable autograd reference the tests compare with.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.evaluation.metrics import SSIM_K, SSIM_WIN_SIGMA, SSIM_WIN_SIZE


def gaussian_window_1d(size: int = SSIM_WIN_SIZE, sigma: float = SSIM_WIN_SIGMA) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - size // 2
    k = np.exp(-(x**2) / (2.0 * sigma**2))
    return (k / k.sum()).astype(np.float32)


@njit(parallel=True, cache=True, nogil=True)
def _blur_zero_padded(maps, kernel, out):  # pragma: no cover - compiled
    """Separable correlation of [M, H, W] maps with ``kernel`` along x then y, zero outside the image.

    Each output row is accumulated in a local buffer and then stored: accumulating into ``out`` directly kept
    the compiler from vectorising (it cannot rule out that ``out`` aliases ``maps``).
    """
    n_maps, height, width = maps.shape
    taps = kernel.shape[0]
    radius = taps // 2
    for m in prange(n_maps):
        tmp = np.empty((height, width), dtype=np.float32)
        row = np.empty(width, dtype=np.float32)
        for y in range(height):
            for x in range(width):
                row[x] = 0.0
            for k in range(taps):
                shift = k - radius
                w = kernel[k]
                for x in range(max(0, -shift), min(width, width - shift)):
                    row[x] += w * maps[m, y, x + shift]
            for x in range(width):
                tmp[y, x] = row[x]
        for y in range(height):
            for x in range(width):
                row[x] = 0.0
            for k in range(max(0, radius - y), min(taps, height + radius - y)):
                w = kernel[k]
                yy = y + k - radius
                for x in range(width):
                    row[x] += w * tmp[yy, x]
            for x in range(width):
                out[m, y, x] = row[x]


def blur(maps: Tensor) -> Tensor:
    """[M, H, W] float32 -> same shape, blurred by the 11-tap sigma-1.5 Gaussian with zero padding."""
    src = maps.detach().to(torch.float32).contiguous().numpy()
    out = np.empty_like(src)
    _blur_zero_padded(src, gaussian_window_1d(), out)
    return torch.from_numpy(out)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor) -> Tensor:  # type: ignore[override]
        c1, c2 = SSIM_K[0] ** 2, SSIM_K[1] ** 2
        p, g = pred.detach().to(torch.float32), gt.detach().to(torch.float32)
        n = p.shape[0]
        mu_p, mu_g, e_pp, e_gg, e_pg = blur(torch.cat([p, g, p * p, g * g, p * g], dim=0)).split(n, dim=0)
        a1 = 2.0 * mu_p * mu_g + c1
        a2 = 2.0 * (e_pg - mu_p * mu_g) + c2
        b1 = mu_p * mu_p + mu_g * mu_g + c1
        b2 = (e_pp - mu_p * mu_p) + (e_gg - mu_g * mu_g) + c2
        s = (a1 * a2) / (b1 * b2)
        ctx.save_for_backward(p, g, mu_p, mu_g, a1, a2, b1, b2, s)
        ctx.dtype = pred.dtype
        return s.mean().to(pred.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        p, g, mu_p, mu_g, a1, a2, b1, b2, s = ctx.saved_tensors
        scale = grad.to(torch.float32) / s.numel()
        inv_b1b2 = 1.0 / (b1 * b2)
        d_mu = (2.0 * mu_g * (a2 - a1) * inv_b1b2 - 2.0 * mu_p * s * (1.0 / b1 - 1.0 / b2)) * scale
        d_pp = (-s / b2) * scale
        d_pg = (2.0 * a1 * inv_b1b2) * scale
        n = p.shape[0]
        bm, bpp, bpg = blur(torch.cat([d_mu, d_pp, d_pg], dim=0)).split(n, dim=0)
        return (bm + 2.0 * p * bpp + g * bpg).to(ctx.dtype), None


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
    # [H, W, C] -> [C, H, W] maps (a view for the common channels-last image)
    chw_pred, chw_gt = pred.permute(2, 0, 1), gt.permute(2, 0, 1)
    return _FusedSSIM.apply(chw_pred, chw_gt)
