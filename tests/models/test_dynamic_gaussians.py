"""The scene model on its own: built from a scene, deformed and rendered at any time, saved and read back without a
Trainer, static rows kept canonical, velocities in the units of its time axis."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses

import pytest
import torch

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.models.deformation import DeformationConfig, Grid4DConfig, HashGridConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.models.material_field import MaterialFieldConfig
from pidg.models.time_axis import TimeAxis

SMALL = DeformationConfig(
    grid4d=Grid4DConfig(spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16)
)


@pytest.fixture(scope="module")
def scene():
    return make_procedural_scene(ProceduralSceneConfig(n_train=5, n_test=2, width=32, height=32, n_gaussians=600, n_init_points=200))


def moved(model: DynamicGaussians, seed: int = 0) -> DynamicGaussians:
    """Give the zero-initialised deformation heads values, so that the model moves its Gaussians over time."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.deformation.named_parameters():
            if name.startswith("head_"):
                p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
    return model


def test_renders_at_any_time_and_round_trips_through_its_state(scene, tmp_path):
    model = moved(DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, MaterialFieldConfig(width=8, embedding_dim=4)))
    frame = scene.test[0]
    with torch.no_grad():
        out = model.render(frame.camera, frame.time)
        assert out.rgb.shape == (32, 32, 3) and torch.isfinite(out.rgb).all()
        assert not torch.equal(model.at(0.1).means, model.at(0.9).means)  # it moves
        torch.save({"format": "pidg-checkpoint-2", "model": model.state_dict()}, tmp_path / "checkpoint.pt")
        loaded = DynamicGaussians.from_run(tmp_path)
        assert torch.equal(loaded.render(frame.camera, frame.time).rgb, out.rgb)
    assert loaded.time_axis == model.time_axis and loaded.num_gaussians == model.num_gaussians
    assert torch.equal(loaded.background, model.background)
    assert loaded.material_field is not None and loaded.material_field.config == model.material_field.config


def test_from_run_names_a_checkpoint_without_a_model(tmp_path):
    torch.save({"format": "pidg-checkpoint-1", "model": {"params": {}}}, tmp_path / "checkpoint.pt")
    with pytest.raises(RuntimeError, match=r"checkpoint\.pt: no pidg scene model.*pidg-checkpoint-1"):
        DynamicGaussians.from_run(tmp_path)


def test_static_gaussians_stay_canonical_and_have_no_velocity(scene):
    model = moved(DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, MaterialFieldConfig(width=8, embedding_dim=4)))
    n = model.num_gaussians
    dynamic = torch.arange(n) % 3 == 0
    model.set_dynamic_mask(dynamic)
    with torch.no_grad():
        at = model.at(0.7)
        canonical = model.canonical()
        assert torch.equal(at.means[~dynamic], canonical.means[~dynamic])
        assert not torch.equal(at.means[dynamic], canonical.means[dynamic])
        v = model.velocities(0.7)
        field_v, _ = model.field_values(at.means, 0.7)
        assert torch.count_nonzero(v[~dynamic]) == 0
        torch.testing.assert_close(v[dynamic], field_v[dynamic])
        # some rows only: mixed, all dynamic (no gather or scatter), all static (no field evaluation)
        for rows in (torch.tensor([4, 0, 7, 3, 8]), dynamic.nonzero().squeeze(1)[:4], (~dynamic).nonzero().squeeze(1)[:4]):
            torch.testing.assert_close(model.velocities(0.7, at.means[rows], rows=rows), v[rows])


def test_a_model_without_a_material_field_says_so(scene):
    model = DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, None)
    with pytest.raises(ValueError, match="no material field"):
        model.velocities(0.5)


def test_time_axis_counts_physics_time_in_training_frames_by_default():
    times = [0.0, 0.25, 0.5, 0.75, 1.0, 0.5]  # a repeated time does not make a zero interval
    axis = TimeAxis.from_times(times)
    assert axis.frame_interval == 0.25 and axis.physics_per_dataset == 4.0
    assert axis.to_physics(0.125) == 0.5 and axis.frame_dt == 1.0
    explicit = TimeAxis.from_times(times, time_scale=2.0)
    assert explicit.physics_per_dataset == 2.0 and explicit.frame_dt == 0.5
    assert TimeAxis.from_times([0.3]).frame_interval == 1.0  # a single time: one unit
    assert TimeAxis.from_state_dict(axis.state_dict()) == axis
    with pytest.raises(ValueError, match="time_scale"):
        TimeAxis.from_times(times, time_scale=-1.0)


def test_velocity_flow_advects_by_the_time_axis(scene):
    """The velocity-flow channels move a Gaussian by v * to_physics(dt) before projecting (checked against a direct
    projection of x + v dt S)."""
    from pidg.flow import flow_channels

    model = DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, MaterialFieldConfig(width=8, embedding_dim=4))
    model.time_axis = dataclasses.replace(model.time_axis, physics_per_dataset=7.0)
    camera, t, dt = scene.train[0].camera, 0.3, 0.1
    with torch.no_grad():
        state = model.at(t)
        channels = flow_channels(model, camera, state, state, t, dt)
        v = model.velocities(t, state.means)
        uv, _ = camera.project_points(state.means)
        uv_v, _ = camera.project_points(state.means + v * dt * 7.0)
    # with identical states the Gaussian flow is 0 (M ~ 0 up to rounding, b ~ 0) and b_v = uv_v - uv; rows of
    # Gaussians the camera culls are all zero
    drawn = channels.abs().sum(-1) > 0
    assert channels[:, :6].abs().max() < 1e-3
    torch.testing.assert_close(channels[drawn, 6:8], (uv_v - uv)[drawn], atol=1e-3, rtol=1e-4)
    assert drawn.sum() > 0.5 * model.num_gaussians and (uv_v - uv)[drawn].norm(dim=-1).max() > 0.01


def test_flow_channels_of_the_gaussians_reaching_the_supervised_pixels_give_the_full_loss_and_gradients(scene):
    """Only Gaussians the compositor weights on a supervised pixel get flow channels: the rendered flows at those
    pixels, the flow loss and every parameter's gradient equal those of the channels of all Gaussians."""
    from pidg.flow import FlowConfig, decode_flows, flow_channels, lpfm_loss, supervised_flow_channels
    from pidg.flow.decomposition import FlowTarget

    model = moved(DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, MaterialFieldConfig(width=8, embedding_dim=4)))
    frame, t1, dt = scene.train[1], scene.train[2].time, scene.train[2].time - scene.train[1].time
    h, w = frame.height, frame.width
    supervised = torch.zeros(h, w, dtype=torch.bool)
    supervised[4:12, 18:27] = True  # a patch: most Gaussians miss it
    gen = torch.Generator().manual_seed(3)
    target = FlowTarget(torch.randn(h, w, 2, generator=gen) * supervised.unsqueeze(-1), supervised)
    params = list(model.gaussians.params.values()) + list(model.deformation.parameters()) + list(model.material_field.parameters())

    def loss_and_grads(subset: bool, tiles: bool = False):
        for p in params:
            p.grad = None
        state = model.at(frame.time)
        if subset:
            channels = supervised_flow_channels(model, model.prepare_render(state, frame.camera), state, frame.time, t1, dt, supervised)
        else:
            channels = flow_channels(model, frame.camera, state, model.at(t1), frame.time, dt)
        out = model.render_state(state, frame.camera, channels, feature_pixels=supervised if tiles else None)
        flow_g, flow_v, _ = decode_flows(out.features, out.alpha)
        loss = lpfm_loss(flow_g, flow_v, target, out.alpha, FlowConfig(min_alpha=0.0)).loss
        loss.backward()
        grads = [None if p.grad is None else (p.grad.to_dense() if p.grad.is_sparse else p.grad).clone() for p in params]
        return loss.detach(), flow_g.detach()[supervised], grads, channels

    full_loss, full_flow, full_grads, full_channels = loss_and_grads(False)
    sub_loss, sub_flow, sub_grads, sub_channels = loss_and_grads(True)
    # the render composites the flow channels only in the supervised pixels' tiles (what training does): the same
    tile_loss, tile_flow, tile_grads, _ = loss_and_grads(True, tiles=True)
    assert torch.equal(tile_loss, sub_loss) and torch.equal(tile_flow, sub_flow)
    assert all((a is None and b is None) or torch.equal(a, b) for a, b in zip(sub_grads, tile_grads))
    skipped = (sub_channels.abs().sum(-1) == 0) & (full_channels.abs().sum(-1) > 0)
    assert skipped.sum() > 0.2 * model.num_gaussians  # the subset is a real saving here
    assert float(full_loss) > 0
    torch.testing.assert_close(sub_loss, full_loss, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(sub_flow, full_flow, rtol=1e-4, atol=1e-5)
    n_gaussian_params = len(model.gaussians.params)
    for i, (p, a, b) in enumerate(zip(params, full_grads, sub_grads)):
        if a is None:
            assert b is None or b.abs().max() == 0
            continue
        if i < n_gaussian_params:  # per-Gaussian rows the flows skip: bit for bit the full gradient (0 from flows)
            outside = sub_channels.abs().sum(-1) == 0
            assert torch.equal(b[outside], a[outside])
        # float32: the sqrt of tiny 2D covariances rounds differently when summed in another order
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-2 * float(a.abs().max()))


def test_footprints_touching_finds_exactly_the_gaussians_drawn_on_masked_pixels(scene):
    """Against the renderer itself: a Gaussian whose feature channel is non-zero on a masked pixel must be found."""
    from pidg.render.footprint import footprints_touching
    from pidg.render.projection import project_gaussians

    with torch.random.fork_rng():  # the deformation's initial weights: the same draw whatever ran before
        torch.manual_seed(0)
        model = moved(DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, None))
    frame = scene.train[0]
    mask = torch.zeros(frame.height, frame.width, dtype=torch.bool)
    mask[10:14, 5:9] = True
    with torch.no_grad():
        state = model.at(frame.time)
        proj = project_gaussians(state.means, state.quats, state.log_scales.exp(), model.gaussians.opacities, frame.camera)
        found = footprints_touching(proj.means2d, proj.radii, mask)
        # render each Gaussian's own indicator channel (one-hot features) and see which ones reach the mask
        n = model.num_gaussians
        reached = torch.zeros(n, dtype=torch.bool)
        for block in torch.arange(n).split(64):
            onehot = torch.zeros(n, len(block))
            onehot[block, torch.arange(len(block))] = 1.0
            out = model.render_state(state, frame.camera, onehot)
            reached[block] = (out.features[mask] > 0).any(dim=0)
    assert reached.sum() > 0
    assert not (reached & ~found).any()  # never misses one that is drawn there
    # and is tight: a box around each ellipse (plus one pixel) over-reports, here ~1.5x what is drawn (half of the
    # 200 Gaussians, whose radii are ~7.5 px on this 32 px image); 2x leaves room for other initial weights
    assert found.sum() <= 2 * reached.sum() and found.sum() < n
