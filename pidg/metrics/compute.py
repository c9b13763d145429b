"""All metrics of one image (or the mean over a batch) as plain floats, with None where a metric cannot apply."""
from __future__ import annotations

import warnings
from typing import Sequence

import torch

from pidg.metrics.image import ImageTooSmallError, SSIMPadding, ms_ssim, psnr, ssim
from pidg.metrics.lpips import INSTALL_HINT, LPIPSError, NetName, lpips, lpips_weights_available


#: The metric key of each SSIM convention.
SSIM_KEYS: dict[SSIMPadding, str] = {"valid": "ssim", "zeros": "ssim_zeros"}


def compute_metrics(
    pred: torch.Tensor,
    gt: torch.Tensor,
    lpips_nets: Sequence[NetName] = ("alex", "vgg"),
) -> dict[str, float | None]:
    """All metrics for one image (``[H,W,3]``) or the mean over a batch (``[B,3,H,W]``), as Python floats.

    Keys: ``psnr``, ``ssim`` (valid filtering, Wang et al.), ``ssim_zeros`` (zero-padded, the 3DGS family's
    tables), ``ms_ssim``, and ``lpips_<net>`` for each requested net (see :data:`SSIM_KEYS` and
    :mod:`pidg.metrics.image` for the two SSIM conventions). ``pred`` is clamped to
    [0, 1] first (renders can overshoot slightly). A metric that cannot be computed is ``None`` and a
    ``RuntimeWarning`` says why: MS-SSIM on images smaller than 161 px, LPIPS when its weights are not installed
    or the image is too small for the backbone. PSNR and both SSIMs are always computed (MS-SSIM always uses
    valid filtering).
    """
    pred = pred.detach().clamp(0.0, 1.0)
    gt = gt.detach()

    def mean(x: torch.Tensor) -> float:
        return float(x.double().mean())

    out: dict[str, float | None] = {"psnr": mean(psnr(pred, gt))}
    for padding, key in SSIM_KEYS.items():
        out[key] = mean(ssim(pred, gt, padding))
    try:
        out["ms_ssim"] = mean(ms_ssim(pred, gt))
    except ImageTooSmallError as e:
        warnings.warn(f"ms_ssim reported as None: {e}", RuntimeWarning, stacklevel=2)
        out["ms_ssim"] = None
    for net in lpips_nets:
        key = f"lpips_{net}"
        if not lpips_weights_available((net,)):
            warnings.warn(f"{key} reported as None: {INSTALL_HINT}", RuntimeWarning, stacklevel=2)
            out[key] = None
            continue
        try:
            out[key] = mean(lpips(pred, gt, net))
        except LPIPSError as e:
            warnings.warn(f"{key} reported as None: {e}", RuntimeWarning, stacklevel=2)
            out[key] = None
    return out

