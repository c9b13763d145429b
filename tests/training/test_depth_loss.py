"""The depth loss (``--optim.lambda_depth``): its relative error on known renders and its gradient against finite
differences (the trainer's side: tests/training/test_trainer.py)."""
import math

import pytest
import torch
from torch import Tensor

from pidg.render import Camera, rasterize
from pidg.render.output import RenderOutput
from pidg.training.losses import relative_depth_error


def _render(depth: Tensor, alpha: Tensor) -> RenderOutput:
    """A render with these expected depths (given a hit) and alphas; nothing else is read."""
    none = torch.zeros(0, 2)
    return RenderOutput(torch.zeros(*alpha.shape, 3), alpha, depth * alpha, None, none, torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0))


def test_relative_depth_error_known_answers():
    depth = torch.tensor([[2.0, 3.0], [4.0, 5.0]])  # expected depth given a hit
    alpha = torch.tensor([[1.0, 0.8], [0.2, 1.0]])
    gt = torch.tensor([[2.5, 3.0], [4.0, 0.0]])  # 0: no measurement
    # (2, 2.5): 0.2; (3, 3): 0; (alpha 0.2 < 0.5): counts 1; the last pixel has no measurement
    assert float(relative_depth_error(_render(depth, alpha), gt)) == pytest.approx((0.2 + 0.0 + 1.0) / 3)
    nan_gt = torch.full((2, 2), float("nan"))
    assert float(relative_depth_error(_render(depth, alpha), nan_gt)) == 0.0


def test_depth_loss_gradient_matches_finite_differences_and_pulls_towards_the_measurement():
    camera = Camera(torch.eye(4), 40.0, 40.0, 16.0, 16.0, 32, 32)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.05, 0.02, 2.4]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    log_scales = torch.full((2, 3), math.log(0.3), dtype=torch.float64)
    opacities = torch.tensor([0.9, 0.9], dtype=torch.float64)
    colors = torch.full((2, 3), 0.5, dtype=torch.float64)
    gt = torch.full((32, 32), 3.0, dtype=torch.float64)

    def loss(m):
        out = rasterize(m, quats, opacities, colors, camera, log_scales=log_scales, background=torch.zeros(3, dtype=torch.float64), backend="torch")
        return relative_depth_error(out, gt)

    m = means.clone().requires_grad_(True)
    loss(m).backward()
    assert m.grad[0, 2] < 0 and m.grad[1, 2] < 0  # both surfaces are in front of the measurement: move them back
    eps = 1e-5
    for i in range(2):
        step = torch.zeros_like(means)
        step[i, 2] = eps
        fd = (loss(means + step) - loss(means - step)) / (2 * eps)
        assert float(m.grad[i, 2]) == pytest.approx(float(fd), rel=1e-4)


def test_depth_loss_gradient_of_the_cpu_kernel_matches_the_torch_reference():
    camera = Camera(torch.eye(4), 40.0, 40.0, 16.0, 16.0, 32, 32)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.05, 0.02, 2.4], [-0.1, 0.05, 3.5]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3)
    log_scales = torch.full((3, 3), math.log(0.3))
    opacities = torch.tensor([0.6, 0.9, 0.8])
    colors = torch.full((3, 3), 0.5)
    gt = torch.full((32, 32), 3.0)
    grads = []
    for backend in ("torch", "cpu"):
        m = means.clone().requires_grad_(True)
        out = rasterize(m, quats, opacities, colors, camera, log_scales=log_scales, background=torch.zeros(3), backend=backend)
        relative_depth_error(out, gt).backward()
        grads.append(m.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=2e-3, atol=1e-6)


def test_opaque_depth_is_the_expected_depth_where_opaque_and_zero_elsewhere():
    """depth / alpha where alpha >= min_alpha; exactly 0, with zero gradients, elsewhere, also where alpha is 0."""
    alpha = torch.tensor([1.0, 0.5, 0.49, 0.0], requires_grad=True)
    composited = torch.tensor([2.0, 1.5, 1.96, 0.0], requires_grad=True)  # a compositor's depth channel: depth x alpha
    none = torch.zeros(0, 2)
    out = RenderOutput(torch.zeros(4, 3), alpha, composited, None, none, torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0))
    d = out.opaque_depth(0.5)
    assert d.tolist() == [2.0, 3.0, 0.0, 0.0]
    d.sum().backward()
    assert composited.grad.tolist() == [1.0, 2.0, 0.0, 0.0]  # 1 / alpha where opaque
    assert alpha.grad.tolist() == [-2.0, -6.0, 0.0, 0.0]  # -depth x alpha / alpha^2 where opaque
    with pytest.raises(ValueError, match="min_alpha must be > 0"):
        out.opaque_depth(0.0)


def test_a_kept_opaque_depth_takes_the_one_pass_kernel_with_the_same_values():
    """Without a gradient (the flow term keeps a depth map every step), float32 CPU maps take
    ``quotient_where_at_least``: the torch form's values, alpha exactly at the threshold and alpha 0 included."""
    gen = torch.Generator().manual_seed(3)
    alpha = torch.rand(37, 41, generator=gen)
    alpha[0, :4] = torch.tensor([0.5, 0.0, 1.0, 0.4999999])
    composited = torch.rand(37, 41, generator=gen) * 4 * alpha
    none = torch.zeros(0, 2)
    out = RenderOutput(torch.zeros(37, 41, 3), alpha, composited, None, none, torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0))
    reference = composited / alpha.clamp_min(0.5) * (alpha >= 0.5)
    with torch.no_grad():
        kept = out.opaque_depth(0.5)
    assert kept.shape == (37, 41) and not kept.requires_grad
    torch.testing.assert_close(kept, reference, rtol=0, atol=0)
    assert kept[0, :4].tolist() == [composited[0, 0].item() / 0.5, 0.0, composited[0, 2].item(), 0.0]
