import numba
import numpy as np
import pidg  # noqa: F401
import pytest
import torch
import torch.nn.functional as F

from pidg.metrics import ssim
from pidg.training import fused_ssim as fused_module
from pidg.training.fused_ssim import blur, fused_ssim, gaussian_window_1d


def _reference_ssim(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean zero-padded SSIM of [H, W, C] images of any size and channel count, in the dtype given (autograd):
    ``metrics.ssim(padding="zeros")`` written for C channels and images smaller than the window."""
    n_ch = pred.shape[2]
    x = torch.arange(11, dtype=pred.dtype) - 5
    k = torch.exp(-(x**2) / (2 * 1.5**2))
    k = k / k.sum()
    win = (k[:, None] * k[None, :]).expand(n_ch, 1, 11, 11)

    def blur_(t):
        return F.conv2d(t, win, padding=5, groups=n_ch)

    p, g = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    c1, c2 = 0.01**2, 0.03**2
    mu_p, mu_g = blur_(p), blur_(g)
    var_p, var_g = blur_(p * p) - mu_p**2, blur_(g * g) - mu_g**2
    cov = blur_(p * g) - mu_p * mu_g
    s = ((2 * mu_p * mu_g + c1) * (2 * cov + c2)) / ((mu_p**2 + mu_g**2 + c1) * (var_p + var_g + c2))
    return s.mean()


def _pair(shape, seed, noise=0.3):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(*shape, generator=g, dtype=torch.float64)
    pred = (gt + noise * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return pred, gt


def _reference_value_and_gradient(pred, gt):
    ref_in = pred.clone().requires_grad_(True)
    ref = _reference_ssim(ref_in, gt)
    ref.backward()
    return float(ref.detach()), ref_in.grad


def _assert_matches(value, grad, ref_value, ref_grad):
    assert abs(value - ref_value) < 1e-6
    rel = (grad.double() - ref_grad).abs().max() / ref_grad.abs().max()
    assert rel < 1e-4


def test_blur_matches_zero_padded_conv2d():
    maps = torch.rand(4, 23, 37, generator=torch.Generator().manual_seed(0))
    k = torch.from_numpy(gaussian_window_1d())
    win = (k[:, None] * k[None, :]).expand(4, 1, 11, 11)
    expected = F.conv2d(maps.unsqueeze(0), win, padding=5, groups=4)[0]
    assert torch.allclose(blur(maps), expected, atol=1e-6)


def test_reference_helper_is_the_metrics_ssim():
    pred, gt = _pair((29, 41, 3), 7)
    assert torch.allclose(_reference_ssim(pred, gt), ssim(pred, gt, padding="zeros"), rtol=0, atol=1e-12)


def test_fused_ssim_value_and_gradient_match_the_autograd_reference():
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(29, 41, 3, generator=g, dtype=torch.float64)
    pred = (gt + 0.2 * torch.randn(29, 41, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref_in = pred.clone().requires_grad_(True)
    ref = ssim(ref_in, gt, padding="zeros")
    ref.backward()
    fused_in = pred.to(torch.float32).requires_grad_(True)
    value = fused_ssim(fused_in, gt.to(torch.float32))
    (3.0 * value).backward()
    assert abs(float(value.detach()) - float(ref.detach())) < 1e-6
    rel = (fused_in.grad.double() - 3.0 * ref_in.grad).abs().max() / ref_in.grad.abs().max()
    assert rel < 1e-4


def test_fused_ssim_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shapes differ"):
        fused_ssim(torch.rand(20, 20, 3), torch.rand(20, 21, 3))


def test_fused_ssim_rejects_more_channels_than_a_scratch_row_holds():
    with pytest.raises(ValueError, match="channels"):
        fused_ssim(torch.rand(4, 4, 200), torch.rand(4, 4, 200))


@pytest.mark.parametrize(
    "shape",
    [
        (11, 13, 3),  # the smallest image metrics.ssim takes
        (37, 23, 3),
        (16, 16, 3),  # two whole bands of 8 rows
        (17, 40, 3),  # a band of one row
        (64, 33, 3),  # 8 bands: two threads' shares, each with halo rows
        (7, 9, 3),  # smaller than the window: every row and column is cut by the edge
        (7, 9, 1),
        (9, 7, 4),
        (10, 12, 2),
        (3, 5, 1),
        (1, 1, 1),
        (1, 30, 3),
        (30, 1, 3),
    ],
)
def test_fused_ssim_matches_the_reference_on_odd_and_tiny_images(shape):
    """Sizes around the band (8 rows), the window (11) and the thread split, channel counts other than 3."""
    pred, gt = _pair(shape, sum(shape))
    fused_in = pred.to(torch.float32).requires_grad_(True)
    value = fused_ssim(fused_in, gt.to(torch.float32))
    value.backward()
    _assert_matches(float(value.detach()), fused_in.grad, *_reference_value_and_gradient(pred, gt))


@pytest.mark.parametrize("shape", [(13, 1400, 3), (6, 4200, 1)])
def test_fused_ssim_matches_the_reference_on_rows_wider_than_a_scratch_row(shape):
    """W*C above what one segment holds (4096 floats less the halo): rows done in two segments."""
    assert shape[1] * shape[2] > fused_module._segment(shape[1] * shape[2], shape[2])
    pred, gt = _pair(shape, 3)
    fused_in = pred.to(torch.float32).requires_grad_(True)
    value = fused_ssim(fused_in, gt.to(torch.float32))
    value.backward()
    _assert_matches(float(value.detach()), fused_in.grad, *_reference_value_and_gradient(pred, gt))


def _kernel(pred, gt, seg=None, n_threads=1):
    """The forward kernel on float32 copies: (mean SSIM, gradient of the mean)."""
    p = pred.to(torch.float32).contiguous().numpy().reshape(pred.shape[0], -1)
    g = gt.to(torch.float32).contiguous().numpy().reshape(pred.shape[0], -1)
    n_ch = pred.shape[2]
    seg = fused_module._segment(p.shape[1], n_ch) if seg is None else seg
    band_sums = np.empty((p.shape[0] + 7) // 8)
    grad = np.empty_like(p)
    c1, c2 = np.float32(0.01**2), np.float32(0.03**2)
    fused_module._ssim_forward(p, g, n_ch, seg, c1, c2, np.float32(1.0 / p.size), n_threads, band_sums, grad)
    return band_sums.sum() / p.size, torch.from_numpy(grad).view(pred.shape)


@pytest.mark.parametrize("shape", [(23, 40, 3), (9, 31, 1), (20, 6, 2)])
@pytest.mark.parametrize("pixels", [1, 2, 7])
def test_row_segments_match_the_reference(shape, pixels):
    """Rows cut into segments of a few pixels (each with its halo, at the image edge or inside it)."""
    pred, gt = _pair(shape, 11)
    value, grad = _kernel(pred, gt, seg=pixels * shape[2])
    _assert_matches(value, grad, *_reference_value_and_gradient(pred, gt))


def test_thread_shares_do_not_change_a_bit():
    """Each share of bands also works out its neighbours' halo rows: any split gives the same bits."""
    pred, gt = _pair((150, 37, 3), 4)
    value, grad = _kernel(pred, gt, n_threads=1)
    for n_threads in (2, 3, 7):  # (shares; numba runs them on the threads it has)
        value_n, grad_n = _kernel(pred, gt, n_threads=n_threads)
        assert value_n == value and torch.equal(grad_n, grad)
    _assert_matches(value, grad, *_reference_value_and_gradient(pred, gt))


def test_value_is_the_same_without_a_gradient_and_the_thread_count_does_not_matter():
    pred, gt = _pair((70, 50, 3), 9)
    pred, gt = pred.float(), gt.float()
    with torch.no_grad():
        plain = fused_ssim(pred, gt)
    x = pred.clone().requires_grad_(True)
    value = fused_ssim(x, gt)
    value.backward()
    assert torch.equal(plain, value.detach())
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        y = pred.clone().requires_grad_(True)
        one = fused_ssim(y, gt)
        one.backward()
    finally:
        numba.set_num_threads(before)
    assert torch.equal(one.detach(), value.detach()) and torch.equal(y.grad, x.grad)


def test_gradient_only_for_pred():
    pred, gt = _pair((20, 20, 3), 2)
    gt_in = gt.float().requires_grad_(True)
    value = fused_ssim(pred.float(), gt_in)  # pred needs no gradient: the value only
    value.backward()
    assert gt_in.grad is None
    x = pred.requires_grad_(True)  # float64 in, float64 gradient out
    fused_ssim(x, gt).backward()
    assert x.grad.dtype == torch.float64 and x.grad.shape == x.shape


def test_fused_ssim_at_training_size_is_exact_and_deterministic():
    g = torch.Generator().manual_seed(5)
    gt = torch.rand(400, 400, 3, generator=g)
    pred = (gt + 0.1 * torch.randn(400, 400, 3, generator=g)).clamp(0, 1)
    ref_in = pred.double().requires_grad_(True)
    ref = ssim(ref_in, gt.double(), padding="zeros")
    ref.backward()
    grads = []
    for _ in range(2):
        x = pred.clone().requires_grad_(True)
        value = fused_ssim(x, gt)
        value.backward()
        grads.append((value.detach(), x.grad))
        _assert_matches(float(value.detach()), x.grad, float(ref.detach()), ref_in.grad)
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])  # bit for bit


def test_blur_of_odd_sizes_matches_conv2d():
    for h, w in [(3, 5), (17, 40), (33, 2), (1, 1), (12, 11)]:
        maps = torch.rand(2, h, w, generator=torch.Generator().manual_seed(h))
        k = torch.from_numpy(gaussian_window_1d())
        win = (k[:, None] * k[None, :]).expand(2, 1, 11, 11)
        expected = F.conv2d(maps.unsqueeze(0), win, padding=5, groups=2)[0]
        assert torch.allclose(blur(maps), expected, atol=1e-6)
