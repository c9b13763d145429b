import pytest
import torch

from pidg.models.deformation.base import Bounds
from pidg.models.gaussians import GaussianModel
from pidg.models.jet import FieldJet, jet_from_function
from pidg.models.material_field import GROUP_EMBEDDING, MaterialField, MaterialFieldConfig, stress_magnitude
from pidg.models.planes import plane_lookup
from pidg.physics import PhysicsConfig

JET_FIELDS = ("v", "sigma", "dv_dx", "dv_dt", "dsigma_dx")


def _assert_jets_close(a: FieldJet, b: FieldJet, atol: float, rtol: float = 0.0) -> None:
    for name in JET_FIELDS:
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=atol, rtol=rtol, msg=lambda m, n=name: f"{n}: {m}")


def _jet_by_reverse_mode(field: MaterialField, x: torch.Tensor, t: torch.Tensor, index: torch.Tensor) -> FieldJet:
    """Rows are independent, so the gradient of a column's sum is every row's derivative (reverse-mode AD)."""
    x = x.detach().requires_grad_(True)
    t = t.detach().requires_grad_(True)
    v, sigma = field(x, t, index)
    dv = [torch.autograd.grad(v[:, j].sum(), (x, t), retain_graph=True) for j in range(3)]
    ds = [torch.autograd.grad(sigma[:, c].sum(), x, retain_graph=True)[0] for c in range(6)]
    return FieldJet(
        v=v.detach(), sigma=sigma.detach(),
        dv_dx=torch.stack([g[0] for g in dv], dim=1), dv_dt=torch.stack([g[1] for g in dv], dim=1),
        dsigma_dx=torch.stack(ds, dim=1),
    )  # fmt: skip


def _jet_by_central_differences(field: MaterialField, x: torch.Tensor, t: torch.Tensor, index: torch.Tensor, h: float = 1e-6) -> FieldJet:
    v, sigma = field(x, t, index)
    dv, ds = [], []
    for i in range(4):
        step_x, step_t = torch.zeros_like(x), torch.zeros_like(t)
        if i < 3:
            step_x[:, i] = h
        else:
            step_t += h
        (vp, sp), (vm, sm) = field(x + step_x, t + step_t, index), field(x - step_x, t - step_t, index)
        dv.append((vp - vm) / (2 * h))
        ds.append((sp - sm) / (2 * h))
    return FieldJet(v, sigma, torch.stack(dv[:3], dim=-1), dv[3], torch.stack(ds[:3], dim=-1))


# ---- the hand-written jet -------------------------------------------------------------------------------------
@pytest.mark.parametrize("activation", ["tanh", "silu", "softplus"])
def test_jet_matches_forward_mode_and_reverse_mode_autodiff(tiny_field, random_inputs, activation):
    field = tiny_field(activation=activation)
    x, t, index = random_inputs(40, spread=1.4)  # ~half of the points lie outside the box
    jet = field.jet(x, t, index)
    with torch.no_grad():
        v, sigma = field(x, t, index)
    torch.testing.assert_close(jet.v, v, atol=1e-14, rtol=1e-13)  # F.silu rounds unlike z * sigmoid(z)
    torch.testing.assert_close(jet.sigma, sigma, atol=1e-14, rtol=1e-13)
    _assert_jets_close(jet, jet_from_function(lambda xx, tt: field(xx, tt, index), x, t), atol=1e-12, rtol=1e-10)
    _assert_jets_close(jet, _jet_by_reverse_mode(field, x, t, index), atol=1e-12, rtol=1e-10)


def test_jet_with_a_scalar_time(tiny_field, random_inputs):
    field = tiny_field()
    x, _, index = random_inputs(9)
    jet = field.jet(x, 0.3, index)
    _assert_jets_close(jet, field.jet(x, torch.full((9,), 0.3, dtype=torch.float64), index), atol=0)
    assert jet.dv_dt.abs().max() > 0


def test_jet_matches_central_differences_inside_near_and_beyond_the_border(tiny_field):
    field = tiny_field()
    centre, half = torch.tensor(field.normalize.centre.tolist()), torch.tensor(field.normalize.half_extent.tolist())
    unit = torch.tensor(
        [[0.1, -0.37, 0.52], [0.993, -0.61, 0.2], [-0.999, 0.998, -0.41], [1.31, 0.27, -0.8], [-1.7, 1.45, 2.2]],
        dtype=torch.float64,
    )  # inside, near the faces, and beyond them (the last two rows)
    x = centre + unit * half
    t = torch.tensor([0.21, 0.01, 0.993, 1.08, -0.15], dtype=torch.float64)  # times beyond [0, 1] too
    index = torch.tensor([0, 3, 5, 7, 10])
    jet = field.jet(x, t, index)
    _assert_jets_close(jet, _jet_by_central_differences(field, x, t, index), atol=1e-7, rtol=1e-6)
    outside = jet.dv_dx[3:]
    assert (outside.abs().amax(dim=(1, 2)) > 1e-3).all(), "derivatives must not vanish outside the box"
    assert (jet.dv_dt[3:].abs().amax(dim=1) > 1e-3).all()


def test_plane_lookup_extrapolates_linearly_beyond_the_border():
    planes = torch.randn(1, 3, 4, 2, dtype=torch.float64)
    pb = torch.full((5, 1), 1.3, dtype=torch.float64)
    pa = torch.tensor([[1.5], [2.0], [2.5], [3.0], [4.0]], dtype=torch.float64)  # the last grid line is 2
    value, d_pa, d_pb = plane_lookup(planes, pa, pb)
    # beyond the last line the lookup continues the border cell: constant slope along a, values on a line
    torch.testing.assert_close(d_pa[2:], d_pa[1:2].expand(3, 1, 2))
    torch.testing.assert_close(value[4] - value[3], d_pa[3])
    assert d_pa.abs().min() > 0 and d_pb.abs().min() > 0
    # on the grid lines the lookup returns the stored values
    on_grid, _, _ = plane_lookup(planes, torch.tensor([[2.0]], dtype=torch.float64), torch.tensor([[3.0]], dtype=torch.float64))
    torch.testing.assert_close(on_grid[0, 0], planes[0, 2, 3])


def test_derivatives_are_in_world_units():
    """Scaling the box by s and moving it scales spatial derivatives by 1 / s and leaves values unchanged."""
    cfg = MaterialFieldConfig(width=16, plane_channels=2, spatial_resolution=6, time_resolution=5, embedding_dim=4, velocity_init_scale=1.0)
    torch.manual_seed(0)
    unit_field = MaterialField(Bounds(), 4, cfg).double()
    moved = MaterialField(Bounds((1.0, 2.0, -3.0), (2.0, 2.0, 2.0)), 4, cfg).double()
    moved.load_state_dict({**unit_field.state_dict(), **{k: v for k, v in moved.state_dict().items() if k.startswith("normalize.")}})
    x = torch.rand(6, 3, dtype=torch.float64) * 2 - 1
    index = torch.arange(6) % 4
    a = unit_field.jet(x, 0.4, index)
    b = moved.jet(torch.tensor([1.0, 2.0, -3.0], dtype=torch.float64) + 2 * x, 0.4, index)
    torch.testing.assert_close(b.v, a.v)
    torch.testing.assert_close(b.dv_dx, a.dv_dx / 2)
    torch.testing.assert_close(b.dv_dt, a.dv_dt)


# ---- initialisation and the "no stress" mode -------------------------------------------------------------------
def test_stress_is_exactly_zero_at_initialisation_and_velocity_small():
    torch.manual_seed(0)
    field = MaterialField(Bounds(), 50, MaterialFieldConfig())
    x, index = torch.rand(64, 3) * 2 - 1, torch.randint(0, 50, (64,))
    jet = field.jet(x, 0.5, index)
    assert torch.count_nonzero(jet.sigma) == 0 and torch.count_nonzero(jet.dsigma_dx) == 0
    assert 0 < jet.v.abs().max() < 0.1


def test_no_stress_mode_gives_zero_stress_whatever_the_weights(tiny_field, random_inputs):
    field = tiny_field(stress=False)  # the stress head is random here, and must be ignored
    assert field.head_stress.weight.abs().sum() > 0
    x, t, index = random_inputs(8)
    jet = field.jet(x, t, index)
    assert torch.count_nonzero(jet.sigma) == 0 and torch.count_nonzero(jet.dsigma_dx) == 0
    assert torch.count_nonzero(field(x, t, index)[1]) == 0


# ---- gradients through the jet -----------------------------------------------------------------------------------
def test_jet_is_differentiable_with_respect_to_parameters_and_positions(tiny_field, random_inputs):
    field = tiny_field()
    x, t, index = random_inputs(6)
    x.requires_grad_(True)
    jet = field.jet(x, t, index)
    total = sum(getattr(jet, name).square().sum() for name in JET_FIELDS)
    total.backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    for name, p in field.named_parameters():
        assert p.grad is not None, name
        grad = p.grad.to_dense() if p.grad.is_sparse else p.grad
        assert grad.abs().sum() > 0, name


def test_float32_jet_on_the_kernels_matches_the_torch_backend(tiny_field, random_inputs):
    """The CPU kernels (plane lookups, tanh tangents) against the torch references: the jet and the gradients of a
    loss on all of it with respect to the positions and every parameter."""
    results = []
    for backend in ("torch", "auto"):
        field = tiny_field(backend=backend).float()
        x, t, index = random_inputs(64)
        x = x.float().requires_grad_(True)
        jet = field.jet(x, t.float(), index)
        gen = torch.Generator().manual_seed(3)
        loss = sum((getattr(jet, name) * torch.randn(getattr(jet, name).shape, generator=gen)).sum() for name in JET_FIELDS)
        loss.backward()
        grads = {name: (p.grad.to_dense() if p.grad.is_sparse else p.grad) for name, p in field.named_parameters()}
        results.append((jet, x.grad, grads))
    (jet_ref, x_ref, grads_ref), (jet_k, x_k, grads_k) = results
    _assert_jets_close(jet_k, jet_ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(x_k, x_ref, atol=1e-5, rtol=1e-4)
    for name, g in grads_ref.items():
        torch.testing.assert_close(grads_k[name], g, atol=1e-5, rtol=1e-4, msg=lambda m, n=name: f"{n}: {m}")


# ---- densification, optimisers ------------------------------------------------------------------------------------
def test_embedding_is_keyed_by_inherited_particle_index():
    """Children carry their parent's particle_index, so the table (num_particles rows) never resizes and a
    child at its parent's position gets its parent's velocity and stress."""
    means = torch.rand(5, 3)
    model = GaussianModel(
        means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(5, 1), log_scales=torch.zeros(5, 3),
        opacity_logits=torch.zeros(5), sh_dc=torch.zeros(5, 1, 3), sh_rest=torch.zeros(5, 15, 3),
    )  # fmt: skip
    torch.manual_seed(0)
    field = MaterialField(Bounds.from_points(means), model.num_particles, MaterialFieldConfig())
    children = torch.tensor([0, 3, 3, 4])  # a densified model's rows: particle_index of the sources
    x = means[children]
    v, _ = field(x, 0.2, model.particle_index[children])
    torch.testing.assert_close(v[1], v[2])
    assert field.index_embedding.shape[0] == model.num_particles == 5


def test_parameter_groups_cover_every_parameter_once_and_the_embedding_gradient_is_sparse():
    field = MaterialField(Bounds(), 20, MaterialFieldConfig(width=16))
    groups = field.parameter_groups()
    ids = [id(p) for params in groups.values() for p in params]
    assert len(ids) == len(set(ids)) == len(list(field.parameters()))
    assert groups[GROUP_EMBEDDING] == [field.index_embedding]
    v, _ = field(torch.rand(3, 3), 0.5, torch.tensor([2, 5, 5]))
    v.sum().backward()
    grad = field.index_embedding.grad
    assert grad.is_sparse and sorted(set(grad.coalesce().indices()[0].tolist())) == [2, 5]  # only the rows evaluated


# ---- bad input --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "x, t, index, error, match",
    [
        (torch.zeros(4, 2), 0.5, torch.zeros(4, dtype=torch.long), ValueError, r"x must be \[M, 3\]"),
        (torch.zeros(4, 3), 0.5, torch.zeros(3, dtype=torch.long), ValueError, r"index must be \[M\]"),
        (torch.zeros(4, 3), 0.5, torch.zeros(4), ValueError, "integer"),
        (torch.zeros(4, 3), torch.zeros(3), torch.zeros(4, dtype=torch.long), ValueError, "shape"),
        (torch.zeros(4, 3), 0.5, torch.tensor([0, 1, 2, 7]), IndexError, r"out of range \[0, 7\)"),
        (torch.zeros(4, 3), 0.5, torch.tensor([0, -1, 2, 3]), IndexError, "out of range"),
        (torch.tensor([[0.0, 0, 0], [float("nan"), 0, 0]]), 0.5, torch.zeros(2, dtype=torch.long), ValueError, "non-finite"),
        (torch.zeros(2, 3), float("inf"), torch.zeros(2, dtype=torch.long), ValueError, "non-finite times"),
    ],
)
def test_bad_input_raises_clear_errors(x, t, index, error, match):
    field = MaterialField(Bounds(), 7, MaterialFieldConfig(width=8))
    for call in (field, field.jet):
        with pytest.raises(error, match=match):
            call(x, t, index)


def test_config_validation():
    with pytest.raises(ValueError, match="kind"):
        PhysicsConfig(kind="pde")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"spatial_resolution must be >= 2, got 1"):
        MaterialFieldConfig(spatial_resolution=1)
    with pytest.raises(ValueError, match="activation"):
        MaterialFieldConfig(activation="relu")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="samples"):
        PhysicsConfig(samples=0)
    with pytest.raises(ValueError, match="num_particles"):
        MaterialField(Bounds(), 0, MaterialFieldConfig())
    assert not PhysicsConfig().active(100) and PhysicsConfig(kind="cmr", start=10).active(10)


def test_stress_magnitude_is_the_frobenius_norm_of_the_symmetric_matrix():
    sigma = torch.randn(7, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    xx, yy, zz, xy, xz, yz = sigma.unbind(-1)
    full = torch.stack([torch.stack([xx, xy, xz], -1), torch.stack([xy, yy, yz], -1), torch.stack([xz, yz, zz], -1)], -2)
    torch.testing.assert_close(stress_magnitude(sigma), torch.linalg.matrix_norm(full), rtol=1e-12, atol=0)
