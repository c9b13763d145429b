"""Pixel metrics for novel-view synthesis: PSNR, SSIM and MS-SSIM (LPIPS: :mod:`pidg.metrics.lpips`).

Conventions (those of the 3DGS / D-NeRF evaluation code, so numbers are comparable with published tables):

* images are float tensors in [0, 1], RGB, either one image ``[H,W,3]`` or a batch ``[B,3,H,W]``;
  metric functions return a 0-d tensor for a single image and a ``[B]`` tensor of per-image values for a batch
  (dataset scores are the mean of per-image values, never a metric of the pooled pixels);
* PSNR: ``-10 log10(MSE)`` with data range 1, MSE over all pixels and channels (or the masked pixels);
* SSIM: Gaussian window 11, sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, averaged over pixels and channels.
  Default ``padding="valid"``: computed by ``pytorch-msssim`` over the window positions that fit inside the image
  (Wang et al. 2004, skimage, mip-NeRF). ``padding="zeros"`` reproduces the ``ssim`` of the 3DGS code base (also
  used by its deformable/4D descendants), which zero-pads by 5 px: on white-background D-NeRF frames that reads
  higher (lego 800x800, two test views: 0.7292 valid vs 0.7360 zeros), so compare like with like;
* MS-SSIM: same window, the 5 standard scale weights of Wang et al. 2003; it needs the short side > 160 px;
* LPIPS v0.1 with AlexNet and VGG16 heads, inputs mapped to [-1, 1] internally (see :mod:`pidg.metrics.lpips`).
"""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

SSIM_WIN_SIZE = 11
SSIM_WIN_SIGMA = 1.5
SSIM_K = (0.01, 0.03)
#: MS-SSIM downsamples 4 times (5 scales); the 11-px window must still fit at the coarsest scale.
MS_SSIM_MIN_SIDE = (SSIM_WIN_SIZE - 1) * 2**4 + 1

SSIMPadding = Literal["valid", "zeros"]


class ImageTooSmallError(ValueError):
    """The image is too small for the requested metric (e.g. MS-SSIM on < 161 px)."""


def to_bchw(img: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """``[H,W,3]`` -> ``([1,3,H,W], True)``; ``[B,3,H,W]`` -> ``(img, False)``. The flag says to squeeze results."""
    if not torch.is_floating_point(img):
        raise TypeError(f"expected a float image tensor in [0, 1], got dtype {img.dtype}")
    if img.dim() == 3 and img.shape[-1] == 3:
        return img.permute(2, 0, 1).unsqueeze(0), True
    if img.dim() == 4 and img.shape[1] == 3:
        return img, False
    raise ValueError(f"expected an image of shape [H,W,3] or [B,3,H,W], got {tuple(img.shape)}")


def _pair(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    p, squeeze = to_bchw(pred)
    g, _ = to_bchw(gt)
    dtype = torch.promote_types(p.dtype, g.dtype)
    return p.to(dtype), g.to(dtype), squeeze


def _out(values: torch.Tensor, squeeze: bool) -> torch.Tensor:
    return values[0] if squeeze else values


def _mask_bchw(mask: torch.Tensor, batch: int, h: int, w: int) -> torch.Tensor:
    """Masks may be [H,W], [H,W,1], [B,H,W] or [B,1,H,W]; returned as float [B,1,H,W]."""
    m = mask.to(torch.float32) if mask.dtype == torch.bool else mask
    if m.dim() == 3 and m.shape[-1] == 1 and m.shape[:2] == (h, w):
        m = m[..., 0]
    if m.dim() == 2:
        m = m[None, None]
    elif m.dim() == 3:
        m = m[:, None]
    if m.dim() != 4 or m.shape[1] != 1 or m.shape[-2:] != (h, w) or m.shape[0] not in (1, batch):
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not match images of size {h}x{w}")
    return m.expand(batch, 1, h, w)


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (data range 1), per image.

    With ``mask`` (bool or weights in [0, 1]), the MSE is averaged over the masked pixels only (all 3 channels);
    an image whose mask is empty gets NaN rather than failing the whole batch. Identical images give +inf.
    """
    p, g, squeeze = _pair(pred, gt)
    se = (p - g) ** 2
    if mask is None:
        mse = se.flatten(1).mean(dim=1)
    else:
        b, _, h, w = se.shape
        m = _mask_bchw(mask.to(se.device), b, h, w).to(se.dtype)
        denom = m.flatten(1).sum(dim=1) * se.shape[1]
        mse = (se * m).flatten(1).sum(dim=1) / denom  # 0/0 -> NaN for empty masks
    return _out(-10.0 * torch.log10(mse), squeeze)


def _msssim_module():  # noqa: ANN202  (module type)
    try:
        import pytorch_msssim
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("SSIM/MS-SSIM need the `pytorch-msssim` package: pip install pytorch-msssim==1.0.0") from e
    return pytorch_msssim


def ssim(pred: torch.Tensor, gt: torch.Tensor, padding: SSIMPadding = "valid") -> torch.Tensor:
    """Structural similarity (window 11, sigma 1.5, data range 1), per image; ``padding`` as in the module doc."""
    p, g, squeeze = _pair(pred, gt)
    if min(p.shape[-2:]) < SSIM_WIN_SIZE:
        raise ImageTooSmallError(f"SSIM needs images of at least {SSIM_WIN_SIZE} px per side, got {tuple(p.shape[-2:])}")
    if padding == "valid":
        val = _msssim_module().ssim(
            p, g, data_range=1.0, size_average=False, win_size=SSIM_WIN_SIZE, win_sigma=SSIM_WIN_SIGMA, K=SSIM_K
        )
    elif padding == "zeros":
        val = _ssim_zero_padded(p, g)
    else:
        raise ValueError(f"padding must be 'valid' or 'zeros', got {padding!r}")
    return _out(val, squeeze)


def _ssim_zero_padded(p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """SSIM exactly as 3DGS ``utils/loss_utils.ssim`` (same-size filtering with zero padding), per image."""
    x = torch.arange(SSIM_WIN_SIZE, dtype=p.dtype, device=p.device) - SSIM_WIN_SIZE // 2
    k1 = torch.exp(-(x**2) / (2 * SSIM_WIN_SIGMA**2))
    k1 = k1 / k1.sum()
    win = (k1[:, None] * k1[None, :]).expand(3, 1, SSIM_WIN_SIZE, SSIM_WIN_SIZE)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, win, padding=SSIM_WIN_SIZE // 2, groups=3)

    c1, c2 = SSIM_K[0] ** 2, SSIM_K[1] ** 2
    mu_p, mu_g = blur(p), blur(g)
    var_p = blur(p * p) - mu_p**2
    var_g = blur(g * g) - mu_g**2
    cov = blur(p * g) - mu_p * mu_g
    s = ((2 * mu_p * mu_g + c1) * (2 * cov + c2)) / ((mu_p**2 + mu_g**2 + c1) * (var_p + var_g + c2))
    return s.flatten(1).mean(dim=1)


def ms_ssim(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Multi-scale SSIM (5 scales, standard weights), per image.

    Raises :class:`ImageTooSmallError` if the short side is below :data:`MS_SSIM_MIN_SIDE` (161 px), because the
    11-px window no longer fits at the coarsest scale; :func:`compute_metrics` reports ``None`` in that case.
    """
    p, g, squeeze = _pair(pred, gt)
    if min(p.shape[-2:]) < MS_SSIM_MIN_SIDE:
        raise ImageTooSmallError(
            f"MS-SSIM with 5 scales needs the short image side >= {MS_SSIM_MIN_SIDE} px, got {tuple(p.shape[-2:])}"
        )
    val = _msssim_module().ms_ssim(
        p, g, data_range=1.0, size_average=False, win_size=SSIM_WIN_SIZE, win_sigma=SSIM_WIN_SIGMA, K=SSIM_K
    )
    return _out(val, squeeze)
