"""Deformation models: the shared interface (Grid4D, the MLP baseline, identity) and Grid4D's specifics."""
import dataclasses
import json
import math

import pytest
import torch

from pidg.config_tools import from_jsonable, to_jsonable
from pidg.models.deformation import (
    GROUP_GRID,
    GROUP_MLP,
    Bounds,
    DeformationConfig,
    DeformationModel,
    DeformedGaussians,
    Grid4D,
    Grid4DConfig,
    HashGridConfig,
    IdentityDeformationConfig,
    MLPDeformationConfig,
    IdentityDeformation,
    MLPDeformation,
    as_bounds,
    build_deformation,
    quat_multiply,
    quat_rotate,
)
from pidg.models.deformation.base import _masked_rows
from pidg.render.projection import quat_to_rotmat

BOUNDS = Bounds(centre=(0.5, -1.0, 2.0), half_extent=(2.0, 2.0, 2.0))
SMALL_GRID4D = Grid4DConfig(
    spatial_grid=HashGridConfig(n_levels=4, n_features=2, log2_table_size=12, base_resolution=4, finest_resolution=64),
    temporal_grid=HashGridConfig(n_levels=4, n_features=2, log2_table_size=12, base_resolution=(4, 4, 4), finest_resolution=(16, 16, 8)),
    width=32,
    decoder_depth=1,
)
SMALL_MLP = MLPDeformationConfig(depth=4, width=32, skips=(1,))
CONFIGS = {"grid4d": SMALL_GRID4D, "mlp": SMALL_MLP, "identity": IdentityDeformationConfig()}


def canonical(n: int = 300, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    centre, half = torch.tensor(BOUNDS.centre), torch.tensor(BOUNDS.half_extent)
    means = centre + (torch.rand(n, 3, generator=gen) * 2 - 1) * half * 0.9
    quats = torch.randn(n, 4, generator=gen)
    log_scales = torch.randn(n, 3, generator=gen) - 3
    return means, quats, log_scales


def randomize_heads(model: torch.nn.Module, scale: float = 0.05, seed: int = 1) -> None:
    """Move the zero-initialised output layers so that the deformation is no longer the identity."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith("head_"):
                p.copy_(torch.randn(p.shape, generator=gen) * scale)


@pytest.mark.parametrize("kind", list(CONFIGS))
def test_identity_at_initialisation(kind):
    model = build_deformation(CONFIGS[kind], BOUNDS)
    assert isinstance(model, DeformationModel)
    means, quats, log_scales = canonical()
    for t in (0.0, 0.37, torch.rand(len(means))):
        out = model(means, quats, log_scales, t)
        assert torch.equal(out.means, means) and torch.equal(out.quats, quats) and torch.equal(out.log_scales, log_scales)


@pytest.mark.parametrize("kind", list(CONFIGS))
def test_shapes_and_interface(kind):
    model = build_deformation(CONFIGS[kind], BOUNDS)
    randomize_heads(model)
    means, quats, log_scales = canonical(50)
    out = model(means, quats, log_scales, torch.full((50,), 0.5), regularize=True)
    assert out.means.shape == (50, 3) and out.quats.shape == (50, 4) and out.log_scales.shape == (50, 3)
    assert out.means.dtype == torch.float32
    reg = out.regularization
    assert (reg is not None) == (kind == "grid4d")  # only Grid4D has a regulariser
    assert reg is None or (reg.dim() == 0 and torch.isfinite(reg))
    groups = model.parameter_groups()
    assert set(groups) <= {GROUP_GRID, GROUP_MLP}
    listed = [id(p) for ps in groups.values() for p in ps]
    assert sorted(listed) == sorted(id(p) for p in model.parameters())  # every parameter exactly once
    with pytest.raises(ValueError):
        model(means, quats, log_scales, torch.zeros(7))
    assert model(means, quats, log_scales, torch.zeros(50, 1)).means.shape == (50, 3)
    empty = model(means[:0], quats[:0], log_scales[:0], 0.5)
    assert empty.means.shape == (0, 3) and empty.quats.shape == (0, 4)


@pytest.mark.parametrize("kind", ["grid4d", "mlp"])
def test_static_rows_are_untouched(kind):
    model = build_deformation(CONFIGS[kind], BOUNDS)
    randomize_heads(model)
    means, quats, log_scales = canonical()
    means.requires_grad_(True)
    static = torch.zeros(len(means), dtype=torch.bool)
    static[::3] = True
    out = model(means, quats, log_scales, 0.6, static_mask=static)
    assert torch.equal(out.means[static], means[static]) and torch.equal(out.quats[static], quats[static])
    assert torch.equal(out.log_scales[static], log_scales[static])
    full = model(means, quats, log_scales, 0.6)
    assert (out.means[~static] - full.means[~static]).abs().max() < 1e-6  # dynamic rows as without a mask
    assert (full.means[~static] - means[~static]).abs().max() > 1e-3  # ... and those do move
    out.means.sum().backward()
    assert torch.equal(means.grad[static], torch.ones(int(static.sum()), 3))  # identity for static rows
    all_static = model(means, quats, log_scales, 0.6, static_mask=torch.ones(len(means), dtype=torch.bool))
    assert all_static.means is means


@pytest.mark.parametrize("kind", ["grid4d", "mlp"])
def test_gradients_reach_every_parameter(kind):
    model = build_deformation(CONFIGS[kind], BOUNDS)
    means, quats, log_scales = canonical()
    target = torch.randn(len(means), 3)

    def step_loss(regularize: bool = True):
        out = model(means, quats, log_scales, 0.3, regularize=regularize)
        loss = (out.means * target).sum() + out.quats.square().sum() + out.log_scales.sum()
        return loss + out.regularization if out.regularization is not None else loss

    # zero-initialised heads: the first backward of a rendering-type loss reaches only them ...
    step_loss(regularize=False).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert (p.grad.abs().max() > 0) == name.startswith("head_"), name
    # ... and after one optimiser step every parameter group receives gradients
    optimizers = [torch.optim.Adam(ps, lr=1e-2) for ps in model.parameter_groups().values()]
    for opt in optimizers:
        opt.step()
        opt.zero_grad()
    step_loss().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, name


def test_grid4d_parameter_groups_split_grids_from_networks():
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    groups = model.parameter_groups()
    assert {id(p) for p in groups[GROUP_GRID]} == {id(g.table) for g in (model.grid_xyz, model.grid_xyt, model.grid_yzt, model.grid_xzt)}
    assert len(groups[GROUP_MLP]) == 2 + 2 + 2 + 6  # f_s, f_t, one decoder layer, three heads


def test_grid4d_time_and_space_mapping():
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    corners = torch.tensor([[-1.5, -3.0, 0.0], [2.5, 1.0, 4.0]])  # the box's min and max corners
    u, ut = model.grid_coordinates(corners, torch.tensor([0.0, 1.0]))
    assert torch.allclose(u, torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    assert torch.allclose(ut, torch.tensor([0.05, 0.95]))  # t' in [-0.9 b, 0.9 b] -> [0.05, 0.95]


def test_grid4d_warp_convention():
    """A hand-set warp: mu' = c + R (mu - c) + half_extent * T, q' = q_x * q, log s' = log s + ds."""
    model = Grid4D(dataclasses.replace(SMALL_GRID4D, decoder_depth=0), BOUNDS)
    angle = 0.3
    q_x = torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])  # rotation about z
    shift = torch.tensor([0.1, -0.2, 0.05])
    with torch.no_grad():
        model.head_warp.bias.copy_(torch.cat([q_x - torch.tensor([1.0, 0, 0, 0]), shift]))
        model.head_scale.bias.fill_(0.25)
    means, quats, log_scales = canonical(20)
    out = model(means, quats, log_scales, 0.5)
    centre, half = torch.tensor(BOUNDS.centre), torch.tensor(BOUNDS.half_extent)
    expected = centre + (means - centre) @ quat_to_rotmat(q_x[None])[0].T + half * shift
    assert torch.allclose(out.means, expected, atol=1e-5)
    assert torch.allclose(out.quats, quat_multiply(q_x.expand(20, 4), quats), atol=1e-6)
    assert torch.allclose(out.log_scales, log_scales + 0.25)
    frozen = Grid4D(dataclasses.replace(SMALL_GRID4D, decoder_depth=0, rotate_with_warp=False), BOUNDS)
    frozen.load_state_dict(model.state_dict())
    assert torch.allclose(frozen(means, quats, log_scales, 0.5).quats, quats)


def test_grid4d_bounds_on_translation_and_scale_change():
    """max_translation / max_log_scale_change: T = b tanh(T_raw / b), ds = b tanh(ds_raw / b) -- a raw head far
    beyond the bound gives the bound, a small one passes almost unchanged; rotation heads are untouched."""
    bounded = dataclasses.replace(SMALL_GRID4D, decoder_depth=0, max_translation=0.5, max_log_scale_change=2.0)
    model, free = Grid4D(bounded, BOUNDS), Grid4D(dataclasses.replace(bounded, max_translation=0.0, max_log_scale_change=0.0), BOUNDS)
    means, quats, log_scales = canonical(20)
    centre, half = torch.tensor(BOUNDS.centre), torch.tensor(BOUNDS.half_extent)
    for shift, ds in ((torch.tensor([40.0, -40.0, 0.01]), 30.0), (torch.tensor([0.02, -0.01, 0.0]), 0.05)):
        for m in (model, free):
            with torch.no_grad():
                m.head_warp.bias.copy_(torch.cat([torch.zeros(4), shift]))
                m.head_scale.bias.fill_(ds)
        out, raw = model(means, quats, log_scales, 0.5), free(means, quats, log_scales, 0.5)
        expected_t = 0.5 * torch.tanh(shift / 0.5)
        assert torch.allclose(out.means - means, half * expected_t, atol=1e-5)
        assert torch.allclose(out.log_scales - log_scales, torch.full_like(log_scales, 2.0 * math.tanh(ds / 2.0)), atol=1e-5)
        assert torch.allclose(out.quats, raw.quats)
        if ds < 1.0:  # small motions: as without the bound, to the tanh's cubic term
            assert torch.allclose(out.means, raw.means, atol=2e-3) and torch.allclose(out.log_scales, raw.log_scales, atol=1e-4)
    assert (out.means - means).abs().max() < 0.5 * half.max() + 1e-6


def test_quaternion_helpers_agree_with_the_renderer():
    gen = torch.Generator().manual_seed(0)
    a, b = torch.nn.functional.normalize(torch.randn(10, 4, generator=gen), dim=-1), torch.randn(10, 4, generator=gen)
    v = torch.randn(10, 3, generator=gen)
    ra, rab = quat_to_rotmat(a), quat_to_rotmat(quat_multiply(a, b))
    assert torch.allclose(rab, ra @ quat_to_rotmat(b), atol=1e-5)  # a * b rotates by b first, then a
    assert torch.allclose(quat_rotate(a, v), (ra @ v[..., None])[..., 0], atol=1e-5)


def test_grid4d_regularizer_equals_its_formula_on_separately_encoded_points():
    """The term computed inside the forward pass (sample and perturbed copies encoded with the pass's points)
    equals weight * mean_i sum_f (G(u_i + d_i) - G(u_i))^2 from separate encoder calls, for the same draws."""
    config = dataclasses.replace(SMALL_GRID4D, reg_fraction=0.2, reg_spatial_weight=0.7, reg_temporal_weight=1.3,
                                 reg_spatial_perturb=(0.02, 0.03, 0.01), reg_temporal_perturb=(0.01, 0.02, 0.03, 0.04))
    model = Grid4D(config, BOUNDS)
    with torch.no_grad():
        for grid in (model.grid_xyz, model.grid_xyt, model.grid_yzt, model.grid_xzt):
            grid.table.copy_(torch.randn(grid.table.shape))
    means, quats, log_scales = canonical(200)
    torch.manual_seed(5)
    loss = model(means, quats, log_scales, 0.3, regularize=True).regularization

    torch.manual_seed(5)
    u_xyz, u_t = model.grid_coordinates(means, torch.full((200,), 0.3))
    rows = torch.randperm(200)[:40]
    xyz, t = u_xyz[rows], u_t[rows]
    d_s = (torch.rand(40, 3) * 2 - 1) * torch.tensor(config.reg_spatial_perturb)
    d_t = (torch.rand(40, 4) * 2 - 1) * torch.tensor(config.reg_temporal_perturb)
    with torch.no_grad():
        change_s = model.encode_spatial(xyz + d_s) - model.encode_spatial(xyz)
        change_t = model.encode_temporal(xyz + d_t[:, :3], t + d_t[:, 3]) - model.encode_temporal(xyz, t)
    expected = 0.7 * change_s.square().sum(-1).mean() + 1.3 * change_t.square().sum(-1).mean()
    assert float(expected) > 0
    assert torch.allclose(loss.detach(), expected, rtol=1e-5)


def test_grid4d_regularizer():
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    means, quats, log_scales = canonical()
    with torch.no_grad():
        for grid in (model.grid_xyz, model.grid_xyt, model.grid_yzt, model.grid_xzt):
            grid.table.fill_(0.7)  # a constant field: perturbing the coordinates changes nothing
    out = model(means, quats, log_scales, 0.4, regularize=True)
    assert float(out.regularization.detach()) < 1e-12  # zero up to float32 rounding of the weights
    with torch.no_grad():
        for grid in (model.grid_xyz, model.grid_xyt, model.grid_yzt, model.grid_xzt):
            grid.table.copy_(torch.randn(grid.table.shape))
    loss = model(means, quats, log_scales, 0.4, regularize=True).regularization
    assert float(loss.detach()) > 0
    loss.backward()
    assert model.grid_xyz.table.grad.abs().max() > 0 and model.grid_xzt.table.grad.abs().max() > 0
    # a pass that does not ask for it neither samples nor returns one (e.g. t+1 for the flow loss, rendering)
    rng = torch.get_rng_state()
    assert model(means, quats, log_scales, 0.4).regularization is None
    assert torch.equal(torch.get_rng_state(), rng)
    static = torch.zeros(len(means), dtype=torch.bool)
    static[::2] = True  # with a static mask, the term covers the deformed rows
    assert model(means, quats, log_scales, 0.4, static_mask=static, regularize=True).regularization is not None


def test_grid4d_attention_cache_at_render_time():
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    randomize_heads(model)
    with torch.no_grad():
        model.grid_xyz.table.copy_(torch.randn(model.grid_xyz.table.shape))
    means, quats, log_scales = canonical()
    calls = []
    original = model.encode_spatial
    model.encode_spatial = lambda u: (calls.append(1), original(u))[1]  # type: ignore[method-assign]
    reference = [model(means, quats, log_scales, t).means for t in (0.2, 0.8)]
    with torch.no_grad():
        cached = [model(means, quats, log_scales, t).means for t in (0.2, 0.8)]
        assert len(calls) == 3  # two with autograd, then one for both frames
        assert all(torch.equal(a, b) for a, b in zip(reference, cached))
        model.grid_xyz.table.mul_(2.0)  # a parameter update invalidates the cache
        model(means, quats, log_scales, 0.2)
        assert len(calls) == 4
        model(means + 0.01, quats, log_scales, 0.2)  # so do new positions
        assert len(calls) == 5


@pytest.mark.parametrize("static", [False, True])
def test_grid4d_pass_at_another_time_reuses_the_attention_with_the_same_values_and_gradients(static):
    """A pass at t1 over the same Gaussians takes the pass at t's attention (``invariant``): the same deformed
    Gaussians and the same gradient for every parameter and position as a pass that encodes G_xyz again, and
    G_xyz runs once instead of twice. Static rows (decoupled) are skipped by both passes."""
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    randomize_heads(model)
    with torch.no_grad():
        model.grid_xyz.table.copy_(torch.randn(model.grid_xyz.table.shape) * 0.1)
    means, quats, log_scales = canonical()
    static_mask = (torch.arange(means.shape[0]) % 3 == 0) if static else None
    calls = []
    original = model.encode_spatial
    model.encode_spatial = lambda u: (calls.append(u.shape[0]), original(u))[1]  # type: ignore[method-assign]

    def run(reuse: bool):
        model.zero_grad()
        x = means.clone().requires_grad_(True)
        calls.clear()
        first = model(x, quats, log_scales, 0.3, static_mask=static_mask)
        second = model(x, quats, log_scales, 0.7, static_mask=static_mask, invariant=first.invariant if reuse else None)
        loss = (first.means.square().sum() + second.means.sin().sum() + second.quats.sum() + second.log_scales.square().sum())
        loss.backward()
        grads = [x.grad] + [p.grad.clone() for p in model.parameters()]
        return second, grads, list(calls)

    fresh, fresh_grads, fresh_calls = run(reuse=False)
    reused, reused_grads, reused_calls = run(reuse=True)
    assert len(fresh_calls) == 2 and len(reused_calls) == 1
    for a, b in ((fresh.means, reused.means), (fresh.quats, reused.quats), (fresh.log_scales, reused.log_scales)):
        assert torch.equal(a, b)
    for a, b in zip(fresh_grads, reused_grads):  # float32 sums in another order: equal to rounding
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5 * float(a.abs().max()))
    if static:  # only the deformed rows' features are kept, and read back by row
        deformed = torch.nonzero(~static_mask).squeeze(1)
        assert fresh.invariant.shape == (deformed.numel(), SMALL_GRID4D.width)
        assert torch.equal(fresh.invariant_rows, deformed)
        everyone = fresh.invariant_of(torch.arange(means.shape[0]))
        assert everyone[static_mask].abs().max() == 0 and torch.equal(everyone[~static_mask], fresh.invariant)
        with pytest.raises(ValueError, match=r"one row per Gaussian \(300\) or per deformed Gaussian \(200\)"):
            model(means, quats, log_scales, 0.7, static_mask=static_mask, invariant=fresh.invariant[:10])
    else:
        assert fresh.invariant.shape == (means.shape[0], SMALL_GRID4D.width) and fresh.invariant_rows is None
    with pytest.raises(ValueError, match=r"one row per Gaussian \(300\)"):
        model(means, quats, log_scales, 0.7, invariant=fresh.invariant[:10])


def test_invariant_of_reads_either_layout_with_the_same_values_and_gradients():
    """``DeformedGaussians.invariant_of(rows)`` of a pass that kept only its deformed rows' features equals the
    same rows of those features spread over every Gaussian with zeros (the layout before), gradients included."""
    n, d = 12, 5
    deformed = torch.tensor([1, 2, 4, 7, 8, 11])
    rows = torch.tensor([11, 0, 4, 4, 3, 8, 1])  # any order, repeats, skipped ones
    values = torch.randn(deformed.numel(), d, requires_grad=True)
    weights = torch.randn(rows.numel(), d)
    means = torch.zeros(n, 3)
    compact = DeformedGaussians(means, torch.zeros(n, 4), torch.zeros(n, 3), invariant=values, invariant_rows=deformed)
    (compact.invariant_of(rows) * weights).sum().backward()
    grad_compact, values.grad = values.grad.clone(), None
    spread = values.new_zeros(n, d).index_copy(0, deformed, values)
    dense = DeformedGaussians(means, torch.zeros(n, 4), torch.zeros(n, 3), invariant=spread)
    assert torch.equal(compact.invariant_of(rows), dense.invariant_of(rows))
    (dense.invariant_of(rows) * weights).sum().backward()
    assert torch.equal(grad_compact, values.grad)
    assert DeformedGaussians(means, torch.zeros(n, 4), torch.zeros(n, 3)).invariant_of(rows) is None
    moving = torch.tensor([8, 1, 11])  # only deformed rows: the same values, unmasked
    assert torch.equal(compact.invariant_of(moving), spread[moving])
    ascending = torch.tensor([1, 4, 8, 11])  # distinct rows in order (the flow loss's): its pooled-gradient gather
    values.grad = None
    (compact.invariant_of(ascending) * weights[:4]).sum().backward()
    expected = torch.zeros(deformed.numel(), d)
    expected[[0, 2, 4, 5]] = weights[:4]
    assert torch.equal(compact.invariant_of(ascending), spread[ascending]) and torch.equal(values.grad, expected)
    mixed = torch.tensor([0, 1, 3, 4, 8, 11])  # increasing, static rows (0, 3) among them: zeros placed around
    w6 = torch.randn(6, d)
    values.grad = None
    (compact.invariant_of(mixed) * w6).sum().backward()
    assert torch.equal(compact.invariant_of(mixed), spread[mixed])
    assert torch.equal(values.grad, torch.zeros(deformed.numel(), d).index_copy(0, torch.tensor([0, 2, 4, 5]), w6[[1, 3, 4, 5]]))
    # the accelerator's sync-free form gives the same rows (what CUDA runs; here on the CPU)
    at = torch.searchsorted(deformed, mixed).clamp_max(deformed.numel() - 1)
    assert torch.equal(_masked_rows(values, at, deformed[at] == mixed), compact.invariant_of(mixed))
    spread_leaf = spread.detach().requires_grad_(True)
    dense_leaf = DeformedGaussians(means, torch.zeros(n, 4), torch.zeros(n, 3), invariant=spread_leaf)
    (dense_leaf.invariant_of(ascending) * weights[:4]).sum().backward()
    assert torch.equal(spread_leaf.grad, torch.zeros(n, d).index_copy(0, ascending, weights[:4]))
    none_deformed = DeformedGaussians(means, torch.zeros(n, 4), torch.zeros(n, 3), invariant=values[:0],
                                      invariant_rows=deformed[:0])
    assert torch.equal(none_deformed.invariant_of(rows), torch.zeros(rows.numel(), d))


@pytest.mark.parametrize("kind", ["mlp", "identity"])
def test_models_without_time_independent_features_keep_the_five_argument_deform(kind):
    """The MLP and identity models (and a user's own, written against the five-argument ``deform``) return no
    invariant features and are never handed any: the scene model's ``reuse`` passes through them unchanged."""
    from pidg.models.dynamic_gaussians import DynamicGaussians
    from pidg.models.gaussians import GaussianModel
    from pidg.models.time_axis import TimeAxis

    model = build_deformation(CONFIGS[kind], BOUNDS)
    randomize_heads(model)
    means, quats, log_scales = canonical()
    first = model(means, quats, log_scales, 0.3)
    assert first.invariant is None
    scene_model = DynamicGaussians(GaussianModel.from_points(means, None), model, None, TimeAxis(1.0, 0.1), torch.ones(3))
    state = scene_model.at(0.3)
    assert torch.equal(scene_model.at(0.7, reuse=state).means, scene_model.at(0.7).means)


def test_grid4d_float64_uses_the_reference():
    model = Grid4D(SMALL_GRID4D, BOUNDS).double()
    randomize_heads(model)
    means, quats, log_scales = (x.double() for x in canonical(30))
    out = model(means, quats, log_scales, 0.5)
    assert out.means.dtype == torch.float64
    out32 = Grid4D(SMALL_GRID4D, BOUNDS)
    out32.load_state_dict({k: v.float() for k, v in model.state_dict().items()})
    assert (out32(means.float(), quats.float(), log_scales.float(), 0.5).means - out.means).abs().max() < 1e-4


def test_run_config_selects_the_model_and_round_trips():
    assert isinstance(build_deformation(DeformationConfig()), Grid4D)  # the default is the paper's model
    config = DeformationConfig(kind="mlp", grid4d=SMALL_GRID4D, mlp=SMALL_MLP)
    assert isinstance(build_deformation(config, BOUNDS), MLPDeformation)
    assert isinstance(build_deformation(dataclasses.replace(config, kind="identity")), IdentityDeformation)
    restored = from_jsonable(DeformationConfig, json.loads(json.dumps(to_jsonable(config))))
    assert restored == config
    with pytest.raises(ValueError):
        DeformationConfig(kind="nope")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        from_jsonable(DeformationConfig, {"kind": "mlp", "depth": 3})
    for kind in ("grid4d", "mlp", "identity"):  # the config that builds a model like a given one
        model = build_deformation(dataclasses.replace(config, kind=kind), BOUNDS)
        assert type(build_deformation(DeformationConfig.of(model))) is type(model)
    assert DeformationConfig.of(build_deformation(config, BOUNDS)).mlp == SMALL_MLP


def test_bounds_from_what_the_trainer_has():
    from pidg.data.scene import SceneBounds

    with_points = SceneBounds(torch.zeros(3), 10.0, torch.tensor([-1.0, -1.0, 0.0]), torch.tensor([1.0, 3.0, 1.0]))
    box = as_bounds(with_points, margin=0.0)
    assert box.centre == (0.0, 1.0, 0.5) and box.half_extent == (2.0, 2.0, 2.0)
    cameras_only = as_bounds(SceneBounds(torch.tensor([1.0, 2.0, 3.0]), 4.0))
    assert cameras_only.centre == (1.0, 2.0, 3.0) and cameras_only.half_extent == (4.0, 4.0, 4.0)
    model = build_deformation(SMALL_GRID4D, torch.tensor([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]))
    assert torch.allclose(model.normalize.centre, torch.ones(3)) and torch.allclose(model.normalize.half_extent, torch.full((3,), 1.1))


def test_state_dict_carries_the_bounds():
    model = Grid4D(SMALL_GRID4D, BOUNDS)
    fresh = Grid4D(SMALL_GRID4D)
    fresh.load_state_dict(model.state_dict())
    assert torch.equal(fresh.normalize.centre, torch.tensor(BOUNDS.centre))


def test_bounds_from_points():
    pts = torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 4.0]])
    box = Bounds.from_points(pts, margin=0.0, cube=False)
    assert box.centre == (1.0, 0.5, 2.0) and box.half_extent == (1.0, 0.5, 2.0)
    cube = Bounds.from_points(pts, margin=0.1)
    assert cube.half_extent == pytest.approx((2.2, 2.2, 2.2))
