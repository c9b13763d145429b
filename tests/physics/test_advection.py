"""Advection by the material field: the integrators against closed-form flows, their orders of accuracy, and the
scene model's velocity converted from physics time to dataset time."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import pytest
import torch

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.models.deformation import DeformationConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.models.material_field import MaterialFieldConfig
from pidg.models.time_axis import TimeAxis
from pidg.physics.advection import Advection, integrate

OMEGA = torch.tensor([0.3, -0.5, 1.1], dtype=torch.float64)  # rad per unit time
CENTER = torch.tensor([0.2, 0.1, -0.4], dtype=torch.float64)


def _rotation(angle_axis: torch.Tensor) -> torch.Tensor:
    """Rodrigues: the rotation matrix of a rotation vector (closed form, independent of the integrators)."""
    theta = float(angle_axis.norm())
    k = angle_axis / theta
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def _spin(x: torch.Tensor, t: float) -> torch.Tensor:
    """A rigid rotation about CENTER: v = omega x (x - c)."""
    return torch.cross(OMEGA.expand_as(x), x - CENTER, dim=1)


def _points() -> torch.Tensor:
    return torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


@pytest.mark.parametrize("method", ["midpoint", "rk4"])
def test_a_rigid_rotation_follows_the_closed_form(method):
    x0, t0, t1 = _points(), 0.2, 1.7
    exact = (x0 - CENTER) @ _rotation(OMEGA * (t1 - t0)).T + CENTER
    got = integrate(_spin, x0, t0, t1, substeps=200, method=method)
    assert (got - exact).norm(dim=1).max() < (1e-3 if method == "midpoint" else 1e-9)
    back = integrate(_spin, got, t1, t0, substeps=200, method=method)  # and backwards in time
    assert (back - x0).norm(dim=1).max() < (2e-3 if method == "midpoint" else 1e-9)


@pytest.mark.parametrize(("method", "order"), [("midpoint", 2), ("rk4", 4)])
def test_the_error_falls_with_the_methods_order(method, order):
    """A time-dependent field with a closed form: dx/dt = a(t) x, a(t) = cos t  ->  x(t) = x0 exp(sin t - sin t0)."""
    x0, t0, t1 = _points(), 0.0, 2.0
    exact = x0 * math.exp(math.sin(t1) - math.sin(t0))
    errors = [
        float((integrate(lambda x, t: math.cos(t) * x, x0, t0, t1, n, method) - exact).abs().max()) for n in (10, 20, 40)
    ]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert all(2**order * 0.8 < r < 2**order * 1.25 for r in ratios), (errors, ratios)


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="substeps"):
        integrate(_spin, _points(), 0.0, 1.0, substeps=0)
    with pytest.raises(ValueError, match="method"):
        integrate(_spin, _points(), 0.0, 1.0, substeps=1, method="euler")  # type: ignore[arg-type]


class _SpinField(torch.nn.Module):
    """A stand-in material field: v = omega x (x - c) in world units per physics time unit, no stress."""

    def forward(self, means, t, index):
        v = torch.cross(OMEGA.to(means).expand_as(means), means - CENTER.to(means), dim=1)
        return v, means.new_zeros(len(means), 6)


def test_advection_converts_physics_time_to_dataset_time_and_continues_in_order():
    scene = make_procedural_scene(ProceduralSceneConfig(n_train=5, n_test=2, width=16, height=16, n_gaussians=500, n_init_points=50))
    model = DynamicGaussians.from_scene(
        scene, GaussianModelConfig(), DeformationConfig(kind="identity"), MaterialFieldConfig(width=8, embedding_dim=4)
    )
    model.material_field = _SpinField()
    model.time_axis = TimeAxis(physics_per_dataset=4.0, frame_interval=0.25)
    advection = Advection(model, t_start=0.5, method="rk4", max_step=0.01)
    start = model.at(0.5).means.double()
    for t in (0.6, 0.9, 0.7):  # in order, then back to an earlier time (it starts again)
        state = advection.at(t)
        angle = OMEGA * 4.0 * (t - 0.5)  # 4 physics units per unit of dataset time
        exact = (start - CENTER) @ _rotation(angle).T + CENTER
        assert (state.means.double() - exact).norm(dim=1).max() < 2e-5  # float32 positions
        assert torch.equal(state.quats, model.at(0.5).quats)  # orientation and size kept from t_start
    with pytest.raises(ValueError, match="forward"):
        advection.at(0.4)
    model.material_field = None
    with pytest.raises(ValueError, match="material field"):
        Advection(model, 0.5)
