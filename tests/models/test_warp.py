"""Grid4D's warp: the numba kernel against autograd through the torch reference (float64), forward and backward,
with and without the warp's rotation of the orientation, near-degenerate quaternion increments included."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import pytest
import torch

from pidg.models.deformation.warp import WARP_COLUMNS, apply_warp, apply_warp_reference
from pidg.render.projection import quat_to_rotmat


def inputs(n: int = 257, seed: int = 0, head_scale: float = 0.3):
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen) * 2 + torch.tensor([0.5, -1.0, 2.0])
    quats = torch.randn(n, 4, generator=gen)
    log_scales = torch.randn(n, 3, generator=gen) - 3
    heads = torch.randn(n, sum(WARP_COLUMNS), generator=gen) * head_scale
    centre, half = torch.tensor([0.4, -0.8, 1.5]), torch.tensor([2.0, 3.0, 1.5])
    return means, quats, log_scales, heads, centre, half


def run(fn, tensors, rotate, upstream):
    leaves = [t.clone().requires_grad_(i < 4) for i, t in enumerate(tensors)]
    outs = fn(*leaves, rotate)
    sum(((o * u).sum() for o, u in zip(outs, upstream)), torch.zeros(())).backward()
    return [o.detach() for o in outs], [leaf.grad for leaf in leaves[:4]]


@pytest.mark.parametrize("rotate", [True, False])
def test_the_kernel_matches_autograd_through_the_reference(rotate):
    tensors = inputs()
    gen = torch.Generator().manual_seed(5)
    upstream = [torch.randn(tensors[0].shape[0], k, generator=gen) for k in (3, 4, 3)]
    kernel = lambda *a: apply_warp(*a, backend="cpu")  # noqa: E731
    outs, grads = run(kernel, tensors, rotate, upstream)
    ref_outs, ref_grads = run(apply_warp_reference, [t.double() for t in tensors], rotate, [u.double() for u in upstream])
    for name, got, want in zip(("means", "quats", "log_scales"), outs, ref_outs):
        assert got.dtype == torch.float32
        assert torch.allclose(got.double(), want, atol=2e-5, rtol=1e-5), name
    for name, got, want in zip(("means", "quats", "log_scales", "heads"), grads, ref_grads):
        assert torch.allclose(got.double(), want, atol=5e-5, rtol=1e-4), (name, (got.double() - want).abs().max())


def test_a_quaternion_increment_near_minus_one_takes_normalize_s_eps_branch():
    """(1, 0, 0, 0) + w = 0 exactly: normalize divides by eps instead of the norm; both implementations agree."""
    tensors = list(inputs(n=4))
    tensors[3] = tensors[3].clone()
    tensors[3][0, :4] = torch.tensor([-1.0, 0.0, 0.0, 0.0])  # warp quaternion x = 0
    tensors[3][1, 7:11] = torch.tensor([-1.0, 0.0, 0.0, 0.0])  # dr quaternion x = 0
    upstream = [torch.ones(4, k) for k in (3, 4, 3)]
    outs, grads = run(lambda *a: apply_warp(*a, backend="cpu"), tensors, True, upstream)
    ref_outs, ref_grads = run(apply_warp_reference, tensors, True, upstream)
    for got, want in zip(outs + grads, ref_outs + ref_grads):
        assert torch.allclose(got, want, atol=1e-4, rtol=1e-4)


def test_the_warp_is_a_rotation_about_the_box_centre_plus_a_scaled_translation():
    """Closed form: mu' = c + R (mu - c) + half * T, q' = q_x * dq * q, log s' = log s + ds."""
    means, quats, log_scales, heads, centre, half = inputs(n=10)
    heads = heads.clone()
    angle = 0.4
    q_x = torch.tensor([math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0])  # about x
    heads[:, :4] = q_x - torch.tensor([1.0, 0.0, 0.0, 0.0])
    heads[:, 7:11] = 0.0  # dq = identity
    for backend in ("cpu", "torch"):
        new_means, new_quats, new_ls = apply_warp(means, quats, log_scales, heads, centre, half, True, backend)
        expected = centre + (means - centre) @ quat_to_rotmat(q_x[None])[0].T + half * heads[:, 4:7]
        assert torch.allclose(new_means, expected, atol=1e-5)
        assert torch.allclose(quat_to_rotmat(new_quats), quat_to_rotmat(q_x[None]) @ quat_to_rotmat(quats), atol=1e-5)
        assert torch.allclose(new_ls, log_scales + heads[:, 11:])


def test_bad_heads_are_named():
    means, quats, log_scales, heads, centre, half = inputs(n=3)
    with pytest.raises(ValueError, match=r"heads must be \[N, 14\]"):
        apply_warp(means, quats, log_scales, heads[:, :7], centre, half)
