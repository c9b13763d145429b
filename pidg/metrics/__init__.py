"""Image-quality metrics (ground floor: they depend on torch only, so training and evaluation both use them).

``image``: PSNR, SSIM (valid or zero-padded window), MS-SSIM; ``lpips``: offline LPIPS v0.1 (AlexNet, VGG16);
``compute``: every metric of one image as floats. The LPIPS distance itself is ``pidg.metrics.lpips.lpips``.
"""
from pidg.metrics.compute import SSIM_KEYS, compute_metrics
from pidg.metrics.image import (
    MS_SSIM_MIN_SIDE,
    SSIM_K,
    SSIM_WIN_SIGMA,
    SSIM_WIN_SIZE,
    ImageTooSmallError,
    SSIMPadding,
    ms_ssim,
    psnr,
    ssim,
    to_bchw,
)
from pidg.metrics.lpips import INSTALL_HINT, LPIPSError, LPIPSWeightsMissing, NetName, lpips_weights_available

__all__ = [
    "INSTALL_HINT", "MS_SSIM_MIN_SIDE", "SSIM_K", "SSIM_WIN_SIGMA", "SSIM_WIN_SIZE", "ImageTooSmallError", "LPIPSError",
    "LPIPSWeightsMissing", "NetName", "SSIM_KEYS", "SSIMPadding", "compute_metrics", "lpips_weights_available", "ms_ssim",
    "psnr", "ssim", "to_bchw",
]
