"""Training losses. Photometric: (1 - lambda_c) L1 + lambda_c D-SSIM (3DGS), with the 3DGS zero-padded SSIM."""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.evaluation.metrics import ssim
from pidg.training.fused_ssim import fused_ssim


def l1_loss(pred: Tensor, gt: Tensor) -> Tensor:
    return (pred - gt).abs().mean()


def photometric_loss(pred: Tensor, gt: Tensor, lambda_dssim: float = 0.2) -> tuple[Tensor, dict[str, float]]:
    """(1 - lambda) * L1 + lambda * (1 - SSIM) on [H, W, 3] images; also returns the parts for logging."""
    l1 = l1_loss(pred, gt)
    if lambda_dssim > 0:
        # the numba SSIM with its analytic backward on CPU (~2x faster than autograd), the reference elsewhere
        value = fused_ssim(pred, gt) if pred.device.type == "cpu" else ssim(pred, gt, padding="zeros")
        d_ssim = 1.0 - value
        total = (1.0 - lambda_dssim) * l1 + lambda_dssim * d_ssim
    else:
        d_ssim = torch.zeros((), dtype=pred.dtype)
        total = l1
    return total, {"l1": float(l1.detach()), "dssim": float(d_ssim.detach())}
