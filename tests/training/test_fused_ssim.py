import pidg  # noqa: F401
import pytest
import torch
import torch.nn.functional as F

from pidg.metrics import ssim
from pidg.training.fused_ssim import blur, fused_ssim, gaussian_window_1d


def test_blur_matches_zero_padded_conv2d():
    maps = torch.rand(4, 23, 37, generator=torch.Generator().manual_seed(0))
    k = torch.from_numpy(gaussian_window_1d())
    win = (k[:, None] * k[None, :]).expand(4, 1, 11, 11)
    expected = F.conv2d(maps.unsqueeze(0), win, padding=5, groups=4)[0]
    assert torch.allclose(blur(maps), expected, atol=1e-6)


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


@pytest.mark.parametrize("shape", [(11, 13, 3), (37, 23, 3), (16, 16, 3), (17, 40, 3)])
def test_fused_ssim_matches_the_reference_on_odd_and_tiny_images(shape):
    """Bands of 16 rows (one partial, one exact, several), the smallest image the reference takes: the band layout's
    edge cases."""
    g = torch.Generator().manual_seed(sum(shape))
    gt = torch.rand(*shape, generator=g, dtype=torch.float64)
    pred = (gt + 0.3 * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref_in = pred.clone().requires_grad_(True)
    ref = ssim(ref_in, gt, padding="zeros")
    ref.backward()
    fused_in = pred.to(torch.float32).requires_grad_(True)
    value = fused_ssim(fused_in, gt.to(torch.float32))
    value.backward()
    assert abs(float(value.detach()) - float(ref.detach())) < 1e-6
    rel = (fused_in.grad.double() - ref_in.grad).abs().max() / ref_in.grad.abs().max()
    assert rel < 1e-4


def test_fused_ssim_at_training_size_is_exact_and_deterministic():
    g = torch.Generator().manual_seed(5)
    gt = torch.rand(400, 400, 3, generator=g)
    pred = (gt + 0.1 * torch.randn(400, 400, 3, generator=g)).clamp(0, 1)
    ref = ssim(pred.double(), gt.double(), padding="zeros")
    grads = []
    for _ in range(2):
        x = pred.clone().requires_grad_(True)
        value = fused_ssim(x, gt)
        value.backward()
        grads.append((value.detach(), x.grad))
        assert abs(float(value.detach()) - float(ref)) < 1e-6
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])  # bit for bit


def test_blur_of_odd_sizes_matches_conv2d():
    for h, w in [(3, 5), (17, 40), (33, 2)]:
        maps = torch.rand(2, h, w, generator=torch.Generator().manual_seed(h))
        k = torch.from_numpy(gaussian_window_1d())
        win = (k[:, None] * k[None, :]).expand(2, 1, 11, 11)
        expected = F.conv2d(maps.unsqueeze(0), win, padding=5, groups=2)[0]
        assert torch.allclose(blur(maps), expected, atol=1e-6)
