"""The velocity a flow carries particles with over an interval: the paper's first-order step and the midpoint rule,
against closed forms (a rigid rotation, a field linear in time)."""
from __future__ import annotations

import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import pytest
import torch
from torch import Tensor, nn

from pidg.flow import interval_velocity
from pidg.models.deformation.identity import IdentityDeformation
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModel
from pidg.models.time_axis import TimeAxis

S = 4.0  # physics time units per unit of dataset time
OMEGA = 0.7  # rad per physics time unit, about z


class Rotation(nn.Module):
    """v = OMEGA z x x (a rigid rotation about the z axis, physics units), stress 0."""

    def forward(self, means: Tensor, t, index: Tensor) -> tuple[Tensor, Tensor]:
        v = torch.stack([-OMEGA * means[:, 1], OMEGA * means[:, 0], torch.zeros_like(means[:, 0])], dim=-1)
        return v, means.new_zeros(len(means), 6)


class Accelerating(nn.Module):
    """v = (2 t, 0, 0) at dataset time t, the same everywhere (physics units)."""

    def forward(self, means: Tensor, t, index: Tensor) -> tuple[Tensor, Tensor]:
        t = torch.as_tensor(t, dtype=means.dtype).expand(len(means))
        return torch.stack([2.0 * t, torch.zeros_like(t), torch.zeros_like(t)], dim=-1), means.new_zeros(len(means), 6)


def model_with(field: nn.Module) -> DynamicGaussians:
    g = torch.Generator().manual_seed(0)
    n = 16
    means = torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats = torch.zeros(n, 4, dtype=torch.float64)
    quats[:, 0] = 1
    gaussians = GaussianModel(means, quats, torch.zeros(n, 3, dtype=torch.float64), torch.zeros(n, dtype=torch.float64),
                              torch.zeros(n, 1, 3, dtype=torch.float64), torch.zeros(n, 0, 3, dtype=torch.float64), sh_degree=0)
    return DynamicGaussians(gaussians, IdentityDeformation(), field, TimeAxis(S, 1.0 / S), torch.zeros(3))


def rotated(x: Tensor, angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], dim=-1)


def endpoint_error(model: DynamicGaussians, dt: float, rule: str) -> float:
    x = model.canonical().means.detach()
    v = interval_velocity(model, 0.3, dt, x, integration=rule)
    return float((x + v * model.time_axis.to_physics(dt) - rotated(x, OMEGA * S * dt)).norm(dim=-1).max())


def test_euler_is_the_fields_velocity_at_t_and_midpoint_the_one_half_a_step_on():
    model = model_with(Rotation())
    x = model.canonical().means.detach()
    v = model.velocities(0.3, x)
    torch.testing.assert_close(interval_velocity(model, 0.3, 0.1, x), v)
    torch.testing.assert_close(interval_velocity(model, 0.3, 0.1, x, integration="midpoint"),
                               model.velocities(0.35, x + 0.5 * S * 0.1 * v))
    rows = torch.tensor([5, 2])
    torch.testing.assert_close(interval_velocity(model, 0.3, 0.1, x[rows], rows, "midpoint"),
                               interval_velocity(model, 0.3, 0.1, x, integration="midpoint")[rows])
    with pytest.raises(ValueError, match="'euler' or 'midpoint'"):
        interval_velocity(model, 0.3, 0.1, x, integration="rk4")  # type: ignore[arg-type]


def test_on_a_rotation_midpoint_is_second_order_and_euler_first():
    """Halving the interval divides the endpoint's error on a circle by ~4 for Euler (local error O(dt^2)) and by
    ~8 for the midpoint rule (O(dt^3)); the exact endpoint is the rotation by OMEGA x the interval."""
    model = model_with(Rotation())
    for sign in (1.0, -1.0):  # backwards in time too: a reversed flow pair (--flow.directions both) has dt < 0
        for rule, ratio in (("euler", 4.0), ("midpoint", 8.0)):
            coarse, fine = endpoint_error(model, sign * 0.04, rule), endpoint_error(model, sign * 0.02, rule)
            assert coarse / fine == pytest.approx(ratio, rel=0.05), (rule, sign)
        assert endpoint_error(model, sign * 0.04, "midpoint") < 0.1 * endpoint_error(model, sign * 0.04, "euler")


def test_midpoint_is_exact_for_a_velocity_linear_in_time():
    """x(t + dt) - x(t) = integral of 2 s ds over [t, t + dt] (physics units x S) = the velocity at t + dt/2 x dt."""
    model = model_with(Accelerating())
    x = model.canonical().means.detach()
    t, dt = 0.3, 0.2
    exact = S * ((t + dt) ** 2 - t**2)
    moved = interval_velocity(model, t, dt, x, integration="midpoint")[:, 0] * model.time_axis.to_physics(dt)
    torch.testing.assert_close(moved, torch.full_like(moved, exact))
    euler = interval_velocity(model, t, dt, x)[:, 0] * model.time_axis.to_physics(dt)
    assert float((euler - exact).abs().min()) > 0.1  # first order misses the acceleration's share
    back = interval_velocity(model, t + dt, -dt, x, integration="midpoint")[:, 0] * model.time_axis.to_physics(-dt)
    torch.testing.assert_close(back, torch.full_like(back, -exact))  # the same interval run backwards
