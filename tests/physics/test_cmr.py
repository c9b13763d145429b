import dataclasses

import pytest
import torch
from torch import Tensor

from pidg.models.jet import FieldJet, jet_from_function, stress_matrix
from pidg.models.time_axis import TimeAxis
from pidg.physics import (
    STAT_NAMES,
    cmr_loss,
    convective_acceleration,
    momentum_residual,
    sample_rows,
    stress_divergence,
)

F64 = torch.float64
UNIT = TimeAxis(physics_per_dataset=1.0, frame_interval=1.0)  # physics time = dataset time


def _points(m: int = 16, seed: int = 0) -> tuple[Tensor, Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(m, 3, generator=gen, dtype=F64), torch.rand(m, generator=gen, dtype=F64)


def _no_stress(x: Tensor) -> Tensor:
    return torch.zeros(x.shape[0], 6, dtype=x.dtype)


# ---- the residual on analytic fields -----------------------------------------------------------------------------
def test_uniform_translation_has_zero_residual():
    x, t = _points()
    c = torch.tensor([0.3, -1.2, 2.0], dtype=F64)
    jet = jet_from_function(lambda x, t: (c.expand(x.shape[0], 3) + 0 * x, _no_stress(x)), x, t)
    torch.testing.assert_close(momentum_residual(jet), torch.zeros_like(x), atol=0, rtol=0)


@pytest.mark.parametrize("density", [1.0, 2.5])
def test_rigid_rotation_gives_centripetal_acceleration(density):
    x, t = _points()
    omega = torch.tensor([0.4, -1.1, 0.7], dtype=F64)
    jet = jet_from_function(lambda x, t: (torch.linalg.cross(omega.expand_as(x), x, dim=-1), _no_stress(x)), x, t)
    expected = density * torch.linalg.cross(omega.expand_as(x), torch.linalg.cross(omega.expand_as(x), x, dim=-1), dim=-1)
    torch.testing.assert_close(momentum_residual(jet, density=density), expected)


def test_linear_stress_field_gives_minus_its_constant_divergence():
    """sigma_xx = 2x, sigma_yy = 3y, sigma_zz = -z, sigma_xy = 5x + 7y, sigma_xz = 11z, sigma_yz = 13x + 17y:
    div = (2 + 7 + 11, 5 + 3 + 0, 0 + 17 - 1) = (20, 8, 16)."""
    x, t = _points()

    def field(x: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        px, py, pz = x.unbind(-1)
        sigma = torch.stack([2 * px, 3 * py, -pz, 5 * px + 7 * py, 11 * pz, 13 * px + 17 * py], dim=-1)
        return torch.zeros_like(x), sigma

    jet = jet_from_function(field, x, t)
    expected = -torch.tensor([20.0, 8.0, 16.0], dtype=F64).expand(x.shape[0], 3)
    torch.testing.assert_close(momentum_residual(jet, density=3.0), expected)
    torch.testing.assert_close(momentum_residual(jet, stress=False), torch.zeros_like(x))  # "no stress" ignores it


@pytest.mark.parametrize(
    "velocity, convective, grad_half_speed_squared",
    [
        # shear flow v = (y, 0, 0): (v . grad) v = 0, grad(|v|^2 / 2) = (0, y, 0)
        (lambda x, y, z: (y, 0 * x, 0 * x), lambda x, y, z: (0 * x, 0 * x, 0 * x), lambda x, y, z: (0 * x, y, 0 * x)),
        # v = (y, x^2, 0): (v . grad) v = (x^2, 2xy, 0), grad(|v|^2 / 2) = (2x^3, y, 0)
        (lambda x, y, z: (y, x * x, 0 * x), lambda x, y, z: (x * x, 2 * x * y, 0 * x), lambda x, y, z: (2 * x**3, y, 0 * x)),
    ],
)
def test_convective_term_is_v_dot_grad_v_not_grad_of_half_speed_squared(velocity, convective, grad_half_speed_squared):
    x, t = _points()
    jet = jet_from_function(lambda x, t: (torch.stack(velocity(*x.unbind(-1)), -1), _no_stress(x)), x, t)
    expected = torch.stack(convective(*x.unbind(-1)), -1)
    wrong = torch.stack(grad_half_speed_squared(*x.unbind(-1)), -1)
    torch.testing.assert_close(momentum_residual(jet), expected)
    assert (momentum_residual(jet) - wrong).abs().max() > 0.1


def test_time_dependent_velocity_and_density():
    """v = (sin t, t^2 x, 0): dv/dt = (cos t, 2 t x, 0), (v . grad) v = (0, t^2 sin t, 0)."""
    x, t = _points()
    rho = 1.7
    jet = jet_from_function(lambda x, t: (torch.stack([torch.sin(t), t * t * x[:, 0], 0 * t], -1), _no_stress(x)), x, t)
    expected = rho * torch.stack([torch.cos(t), 2 * t * x[:, 0] + t * t * torch.sin(t), 0 * t], -1)
    torch.testing.assert_close(momentum_residual(jet, density=rho), expected)


def test_residual_layout_on_a_hand_built_jet():
    """dv_dx[m, j, i] = d v_j / d x_i and dsigma_dx[m, c, i] = d sigma_c / d x_i, written out by hand."""
    dv_dx = torch.zeros(1, 3, 3, dtype=F64)
    dv_dx[0, 1, 0] = 2.0  # d v_y / d x
    dsigma_dx = torch.zeros(1, 6, 3, dtype=F64)
    dsigma_dx[0, 3, 0] = 5.0  # d sigma_xy / d x: enters (div sigma)_y only
    dsigma_dx[0, 3, 1] = 7.0  # d sigma_xy / d y: enters (div sigma)_x only
    jet = FieldJet(
        v=torch.tensor([[3.0, 0.0, 0.0]], dtype=F64), sigma=torch.zeros(1, 6, dtype=F64), dv_dx=dv_dx,
        dv_dt=torch.zeros(1, 3, dtype=F64), dsigma_dx=dsigma_dx,
    )  # fmt: skip
    torch.testing.assert_close(convective_acceleration(jet), torch.tensor([[0.0, 6.0, 0.0]], dtype=F64))
    torch.testing.assert_close(stress_divergence(dsigma_dx), torch.tensor([[7.0, 5.0, 0.0]], dtype=F64))
    torch.testing.assert_close(momentum_residual(jet), torch.tensor([[-7.0, 1.0, 0.0]], dtype=F64))
    s = stress_matrix(torch.arange(6, dtype=F64))
    torch.testing.assert_close(s, s.T)
    assert s[0, 1] == 3 and s[0, 2] == 4 and s[1, 2] == 5 and s.diagonal().tolist() == [0, 1, 2]


def test_field_jet_rejects_inconsistent_shapes():
    z = torch.zeros
    with pytest.raises(ValueError, match="FieldJet"):
        FieldJet(z(4, 3), z(4, 6), z(4, 3, 3), z(4, 3), z(4, 3, 6))


# ---- the loss ---------------------------------------------------------------------------------------------------
def _full_loss(field, x: Tensor, t: Tensor, index: Tensor, density: float = 1.0) -> Tensor:
    return momentum_residual(field.jet(x, t, index), density).square().sum(dim=1).mean()


def test_blocks_give_the_full_loss_when_all_particles_fit(tiny_field, tiny_config, random_inputs):
    field = tiny_field()
    x, t, index = random_inputs(30)
    config = tiny_config(samples=100, block_size=7, density=1.3)
    result = cmr_loss(field, x, t, index, config, UNIT, torch.Generator().manual_seed(0))
    torch.testing.assert_close(result.loss, _full_loss(field, x, t, index, 1.3), atol=1e-13, rtol=1e-12)
    assert result.num_samples == 30 and set(result.stats) == set(STAT_NAMES)
    r = momentum_residual(field.jet(x, t, index), 1.3)
    torch.testing.assert_close(result.stats["residual"], r.norm(dim=1).mean())


def test_time_scale_divides_the_time_derivative(tiny_field, tiny_config, random_inputs):
    """tau = S t: dv/d tau = (dv/dt) / S, everything else unchanged."""
    from dataclasses import replace

    field = tiny_field()
    x, t, index = random_inputs(20)
    config = tiny_config(samples=100, block_size=100)
    jet = field.jet(x, t, index)
    expected = momentum_residual(replace(jet, dv_dt=jet.dv_dt / 4.0)).square().sum(dim=1).mean()
    result = cmr_loss(field, x, t, index, config, TimeAxis(physics_per_dataset=4.0, frame_interval=0.25), torch.Generator().manual_seed(0))
    torch.testing.assert_close(result.loss, expected, atol=1e-13, rtol=1e-12)
    assert not torch.allclose(result.loss, _full_loss(field, x, t, index))


def test_subset_is_seeded_and_independent_of_the_block_size(tiny_field, tiny_config, random_inputs):
    field = tiny_field()
    x, t, index = random_inputs(200)
    losses = [
        cmr_loss(field, x, t, index, tiny_config(samples=50, block_size=b), UNIT, torch.Generator().manual_seed(3)).loss
        for b in (50, 7, 1000)
    ]
    rows = sample_rows(200, 50, torch.Generator().manual_seed(3))
    expected = _full_loss(field, x[rows], t[rows], index[rows])
    for loss in losses:
        torch.testing.assert_close(loss, expected, atol=1e-13, rtol=1e-12)
    other = cmr_loss(field, x, t, index, tiny_config(samples=50), UNIT, torch.Generator().manual_seed(4)).loss
    assert other != losses[0]


class _RowCounter:
    """Wraps a field and records how many rows each jet call puts through the network."""

    def __init__(self, field) -> None:
        self.field, self.calls = field, []

    def jet(self, x, t, index):
        self.calls.append(x.shape[0])
        return self.field.jet(x, t, index)


@pytest.mark.parametrize("n", [40, 5000, 50_000])
def test_only_the_sampled_rows_go_through_the_network(tiny_field, tiny_config, n):
    counter = _RowCounter(tiny_field())
    x = torch.rand(n, 3, dtype=F64)
    config = tiny_config(samples=64, block_size=16)
    cmr_loss(counter, x, 0.5, torch.arange(n) % 11, config, UNIT, torch.Generator().manual_seed(0))
    assert sum(counter.calls) == min(n, 64)
    assert max(counter.calls) <= 16


def test_checkpointed_blocks_match_stored_blocks(tiny_field, tiny_config, random_inputs):
    field = tiny_field()
    x, t, index = random_inputs(40)
    results = []
    for ckpt in (False, True):
        leaf = x.clone().requires_grad_(True)
        config = tiny_config(samples=30, block_size=8, checkpoint_blocks=ckpt)
        loss = cmr_loss(field, leaf, t, index, config, UNIT, torch.Generator().manual_seed(1)).loss
        grads = torch.autograd.grad(loss, [leaf, field.trunk[1].weight, field.spatial_planes])
        results.append((loss, grads))
    torch.testing.assert_close(results[0][0], results[1][0])
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b)


def test_detach_positions_stops_gradients_into_the_deformation(tiny_field, tiny_config, random_inputs):
    field = tiny_field()
    x, t, index = random_inputs(12)
    for detach in (False, True):
        leaf = x.clone().requires_grad_(True)
        loss = cmr_loss(field, leaf, t, index, tiny_config(detach_positions=detach), UNIT).loss
        loss.backward()
        assert (leaf.grad is None) == detach
        assert field.trunk[0].weight.grad is not None


def test_no_stress_mode_ignores_the_stress(tiny_field, tiny_config, random_inputs):
    x, t, index = random_inputs(20)
    with_head = tiny_field(stress=False)
    result = cmr_loss(with_head, x, t, index, tiny_config(), UNIT)
    assert result.stats["stress"] == 0 and result.stats["stress_divergence"] == 0
    jet = tiny_field().jet(x, t, index)  # random stress head
    inertia_only = momentum_residual(jet, stress=False)
    torch.testing.assert_close(inertia_only, jet.dv_dt + convective_acceleration(jet))


def test_loss_gradients_match_finite_differences(tiny_field, tiny_config, random_inputs):
    """Autograd through the hand-written tangents (second-order terms included) vs central differences."""
    field = tiny_field()
    x, t, index = random_inputs(9, spread=1.2)
    config = tiny_config(density=1.4)
    x = x.requires_grad_(True)

    def loss() -> Tensor:
        return cmr_loss(field, x, t, index, config, UNIT).loss

    loss().backward()
    h = 1e-6
    gen = torch.Generator().manual_seed(0)
    # a constant stress has no divergence: the stress bias is the one parameter L_CMR cannot see
    assert field.head_stress.bias.grad is None or torch.count_nonzero(field.head_stress.bias.grad) == 0
    targets = [("x", x)] + [(n, p) for n, p in field.named_parameters() if n != "head_stress.bias"]
    for name, tensor in targets:
        grad = tensor.grad.to_dense() if tensor.grad.is_sparse else tensor.grad
        flat_grad = grad.reshape(-1)
        candidates = torch.nonzero(flat_grad).squeeze(1)
        picks = candidates[torch.randperm(candidates.numel(), generator=gen)[:4]]
        assert picks.numel() > 0, name
        for k in picks.tolist():
            with torch.no_grad():
                flat = tensor.view(-1)
                flat[k] += h
                up = loss()
                flat[k] -= 2 * h
                down = loss()
                flat[k] += h
            numeric = (up - down) / (2 * h)
            torch.testing.assert_close(flat_grad[k], numeric, atol=1e-6, rtol=1e-5, msg=lambda m, n=name, i=k: f"{n}[{i}]: {m}")


def test_loss_rejects_bad_input(tiny_field, tiny_config):
    field, config = tiny_field(), tiny_config(samples=4)
    idx = torch.zeros(10, dtype=torch.long)
    with pytest.raises(ValueError, match=r"positions must be \[N, 3\]"):
        cmr_loss(field, torch.zeros(10, 2, dtype=F64), 0.5, idx, config, UNIT)
    with pytest.raises(ValueError, match=r"index must be \[N\]"):
        cmr_loss(field, torch.zeros(10, 3, dtype=F64), 0.5, idx[:9], config, UNIT)
    with pytest.raises(ValueError, match="no particles"):
        cmr_loss(field, torch.zeros(0, 3, dtype=F64), 0.5, idx[:0], config, UNIT)
    bad = torch.zeros(10, 3, dtype=F64)
    bad[7, 1] = float("nan")  # caught even when row 7 is not among the sampled ones
    with pytest.raises(ValueError, match="non-finite positions"):
        cmr_loss(field, bad, 0.5, idx, config, UNIT)
    with pytest.raises(IndexError, match="out of range"):
        cmr_loss(field, torch.zeros(10, 3, dtype=F64), 0.5, idx + 11, dataclasses.replace(config, samples=100), UNIT)
