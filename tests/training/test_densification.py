"""Densification: index inheritance, optimizer state kept in step, split sampling, pruning rules, opacity reset."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import pytest
import torch

from pidg.models.gaussians import GaussianModel
from pidg.render import rasterize
from pidg.render.api import RenderOutput
from pidg.render.projection import quat_to_rotmat
from pidg.render.scenes import orbit_camera
from pidg.training.config import GaussianOptimConfig
from pidg.training.densification import DensificationConfig, DensificationStrategy, clone, prune, split
from pidg.training.optim import make_gaussian_optimizers, means_lr_at


def make_model(n: int = 6, seed: int = 0, scale: float = 0.05, opacity: float = 0.5) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    logit = math.log(opacity / (1 - opacity))
    return GaussianModel(
        means=0.3 * torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.full((n, 3), math.log(scale)) + 0.1 * torch.randn(n, 3, generator=g),
        opacity_logits=torch.full((n,), logit),
        sh_dc=torch.randn(n, 1, 3, generator=g),
        sh_rest=torch.randn(n, 15, 3, generator=g),
    )


def adam_step(model: GaussianModel, optimizers, seed: int = 1) -> None:
    """Give every parameter a random gradient and step, so Adam moments are non-zero."""
    g = torch.Generator().manual_seed(seed)
    for p in model.params.values():
        p.grad = torch.randn(p.shape, generator=g)
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)


def state_of(optimizers, model, name):
    return optimizers[name].state[model.params[name]]


def fake_render(n: int, grad_px: torch.Tensor, radii: torch.Tensor, width: int = 200, height: int = 100) -> RenderOutput:
    """A RenderOutput whose means2d already carries a gradient, as after loss.backward()."""
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = grad_px.clone()
    return RenderOutput(
        rgb=torch.zeros(height, width, 3), alpha=torch.zeros(height, width), depth=torch.zeros(height, width),
        features=None, means2d=means2d, radii=radii.to(torch.int32), depths=torch.ones(n),
    )


def check_optimizer_consistency(model: GaussianModel, optimizers) -> None:
    for name, p in model.params.items():
        if name not in optimizers:
            continue
        (group,) = optimizers[name].param_groups
        assert group["params"][0] is p, name
        state = optimizers[name].state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape, name
    assert all(b.shape[0] == len(model) for b in model.buffers.values())


def strategy_and_state(model: GaussianModel, scene_extent: float = 1.0, config: DensificationConfig | None = None):
    """A (stateless) strategy and the explicit state it works on, for ``model``'s Gaussians."""
    strategy = DensificationStrategy(config, scene_extent)
    return strategy, strategy.initialize_state(len(model))


@pytest.fixture
def setup():
    model = make_model()
    opts = make_gaussian_optimizers(model, scene_extent=1.0)
    adam_step(model, opts)
    strategy, state = strategy_and_state(model)
    return model, opts, strategy, state


def test_clone_copies_rows_with_zero_adam_state(setup):
    model, opts, strategy, state = setup
    before = {k: v.detach().clone() for k, v in model.params.items()}
    moments = {k: state_of(opts, model, k)["exp_avg"].clone() for k in model.params}
    assert clone(model, opts, state, torch.tensor([False, True, False, False, True, False])) == 2
    assert len(model) == 8
    assert model.particle_index.tolist() == [0, 1, 2, 3, 4, 5, 1, 4]
    check_optimizer_consistency(model, opts)
    for k, p in model.params.items():
        assert torch.equal(p.detach(), torch.cat([before[k], before[k][[1, 4]]])), k
        st = state_of(opts, model, k)
        assert torch.equal(st["exp_avg"][:6], moments[k]), k  # survivors keep their moments
        assert (st["exp_avg"][6:] == 0).all() and (st["exp_avg_sq"][6:] == 0).all(), k
    adam_step(model, opts, seed=2)  # a following step runs on the new shapes
    check_optimizer_consistency(model, opts)


def test_prune_removes_rows_and_their_state(setup):
    model, opts, strategy, state = setup
    before = {k: v.detach().clone() for k, v in model.params.items()}
    moments = {k: state_of(opts, model, k)["exp_avg_sq"].clone() for k in model.params}
    mask = torch.tensor([True, False, False, True, False, False])
    assert prune(model, opts, state, mask) == 2
    assert model.particle_index.tolist() == [1, 2, 4, 5]
    check_optimizer_consistency(model, opts)
    for k, p in model.params.items():
        assert torch.equal(p.detach(), before[k][~mask])
        assert torch.equal(state_of(opts, model, k)["exp_avg_sq"], moments[k][~mask])
    adam_step(model, opts, seed=3)
    with pytest.raises(ValueError, match="bool mask"):
        prune(model, opts, state, torch.tensor([0, 1]))


def test_index_inheritance_through_clone_split_prune(setup):
    model, opts, strategy, state = setup
    sh_before = model.params["sh_dc"].detach().clone()
    clone(model, opts, state, torch.tensor([False, True, False, False, True, False]))
    split(model, opts, state, torch.tensor([False, False, True, False, False, False, False, True]))  # row 7 = clone of 4
    prune(model, opts, state, model.particle_index == 0)
    idx = model.particle_index
    assert sorted(idx.tolist()) == [1, 1, 2, 2, 3, 4, 4, 4, 5]
    # every descendant carries its ancestor's colour (children copy all rows they do not resample)
    torch.testing.assert_close(model.params["sh_dc"].detach(), sh_before[idx])
    check_optimizer_consistency(model, opts)
    adam_step(model, opts, seed=4)
    assert model.num_particles == 6


def test_split_samples_children_from_the_parent_gaussian():
    m = 20_000
    rot_a = torch.tensor([0.9, 0.2, -0.3, 0.25])
    rot_b = torch.tensor([0.3, -0.8, 0.1, 0.5])
    scales_a, scales_b = torch.tensor([0.3, 0.1, 0.05]), torch.tensor([0.02, 0.2, 0.08])
    mean_a, mean_b = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([10.0, -2.0, 1.0])
    model = GaussianModel(
        means=torch.cat([mean_a.expand(m, 3), mean_b.expand(m, 3)]),
        quats=torch.cat([rot_a.expand(m, 4), rot_b.expand(m, 4)]),
        log_scales=torch.cat([scales_a.log().expand(m, 3), scales_b.log().expand(m, 3)]),
        opacity_logits=torch.zeros(2 * m), sh_dc=torch.zeros(2 * m, 1, 3), sh_rest=torch.zeros(2 * m, 15, 3),
    )
    opts = make_gaussian_optimizers(model)
    original = {k: v.detach().clone() for k, v in model.params.items()}
    adam_step(model, opts)  # non-zero moments ...
    with torch.no_grad():  # ... but the exact parents back
        for k, v in model.params.items():
            v.copy_(original[k])
    _, state = strategy_and_state(model, 1.0, DensificationConfig(seed=123))
    assert split(model, opts, state, torch.ones(2 * m, dtype=torch.bool)) == 2 * m
    assert len(model) == 4 * m
    check_optimizer_consistency(model, opts)
    for name in model.params:
        st = state_of(opts, model, name)
        assert (st["exp_avg"] == 0).all() and (st["exp_avg_sq"] == 0).all()
    group_a = model.particle_index < m
    assert int(group_a.sum()) == 2 * m  # two children per parent, both inheriting its index
    assert torch.bincount(model.particle_index).eq(2).all()
    for group, mean, quat, scales in ((group_a, mean_a, rot_a, scales_a), (~group_a, mean_b, rot_b, scales_b)):
        torch.testing.assert_close(model.scales[group], (scales / 1.6).expand(2 * m, 3))
        torch.testing.assert_close(model.params["quats"][group].detach(), quat.expand(2 * m, 4))
        x = model.means[group].detach().double()
        rot = quat_to_rotmat(quat[None].double())[0]
        cov = rot @ torch.diag(scales.double() ** 2) @ rot.T
        # sample mean within 4 standard errors, sample covariance within 4% (the statistic's spread is ~1%)
        se = (cov.diagonal() / (2 * m)).sqrt()
        assert ((x.mean(0) - mean.double()).abs() < 4 * se).all()
        torch.testing.assert_close(torch.cov(x.T), cov, rtol=0, atol=0.04 * float(cov.abs().max()))
    # a fixed seed gives the same children
    twin = GaussianModel.from_state_dict({**model.state_dict()})
    _, first = strategy_and_state(twin, 1.0, DensificationConfig(seed=7))
    second_model = GaussianModel.from_state_dict(model.state_dict())
    _, second = strategy_and_state(second_model, 1.0, DensificationConfig(seed=7))
    mask = torch.zeros(4 * m, dtype=torch.bool)
    mask[:10] = True
    split(twin, {}, first, mask)
    split(second_model, {}, second, mask)
    assert torch.equal(twin.means, second_model.means)


def test_gradient_statistics_and_clone_vs_split_decision():
    # extent 1, percent_dense 0.01: max scale 0.005 is small (clone), 0.05 large (split)
    model = make_model(5, scale=0.05)
    with torch.no_grad():
        model.params["log_scales"][:] = math.log(0.05)
        model.params["log_scales"][0] = math.log(0.005)
    opts = make_gaussian_optimizers(model)
    strategy, state = strategy_and_state(model)
    width, height = 200, 100
    # NDC-equivalent gradient = pixel gradient * (W/2, H/2) = pixel gradient * (100, 50)
    grad = torch.tensor([
        [3e-6, 0.0],  # small, 3e-4 >= 2e-4: clone
        [0.0, 6e-6],  # large, 3e-4: split
        [0.0, 3e-6],  # 1.5e-4 < 2e-4: nothing
        [1.0, 1.0],  # huge but never visible: nothing
        [3e-6, 0.0],  # 3e-4 in one view, 0 in the other: average 1.5e-4, nothing
    ])
    radii = torch.tensor([[3, 3], [4, 2], [5, 5], [0, 0], [2, 2]])
    assert strategy.step_post_backward(model, opts, state, 550, fake_render(5, grad, radii, width, height)) is None  # not on schedule
    second = grad.clone()
    second[4] = 0.0
    strategy.step_pre_backward(fake_render(5, second, radii, width, height))
    report = strategy.step_post_backward(model, opts, state, 600, fake_render(5, second, radii, width, height))
    assert report is not None and (report.cloned, report.split, report.pruned) == (1, 1, 0)
    assert report.num_gaussians == 7 == len(model)
    assert model.particle_index.tolist() == [0, 2, 3, 4, 0, 1, 1]
    # statistics restart after a densification round
    assert state.grad_accum.shape == (7,) and (state.count == 0).all() and (state.max_radii == 0).all()


def test_statistics_accumulate_over_views_and_radii():
    model = make_model(3)
    strategy, state = strategy_and_state(model)
    g = torch.tensor([[1e-6, 0.0], [0.0, 2e-6], [1.0, 1.0]])
    outs = [fake_render(3, g, torch.tensor([[3, 7], [2, 2], [0, 0]])), fake_render(3, g, torch.tensor([[9, 1], [0, 0], [0, 0]]))]
    strategy.update_statistics(model, state, outs)
    assert state.count.tolist() == [2, 1, 0]
    torch.testing.assert_close(state.grad_accum, torch.tensor([2e-4, 1e-4, 0.0]))
    assert state.max_radii.tolist() == [9.0, 2.0, 0.0]
    strategy.update_statistics(model, state, outs[0], width=400, height=400)  # explicit size overrides the image's
    torch.testing.assert_close(state.grad_accum, torch.tensor([4e-4, 5e-4, 0.0]))
    with pytest.raises(ValueError, match="Gaussians"):
        strategy.update_statistics(model, state, fake_render(2, g[:2], torch.zeros(2, 2)))


def test_opacity_reset_clamps_and_zeroes_only_opacity_state(setup):
    model, opts, strategy, state = setup
    with torch.no_grad():
        model.params["opacity_logits"][:] = torch.logit(torch.tensor([0.5, 0.006, 0.9, 0.011, 0.009, 0.2]))
    means_state = state_of(opts, model, "means")["exp_avg"].clone()
    param = model.params["opacity_logits"]
    # step 3000 is also a densification round; nothing qualifies for growth or pruning here
    report = strategy.step_post_backward(model, opts, state, 3000, fake_render(6, torch.zeros(6, 2), torch.ones(6, 2)))
    assert report is not None and (report.cloned, report.split, report.pruned) == (0, 0, 0)
    assert model.params["opacity_logits"] is param  # reset in place: nothing else to re-wire
    torch.testing.assert_close(model.opacities, torch.tensor([0.01, 0.006, 0.01, 0.01, 0.009, 0.01]))
    st = state_of(opts, model, "opacity_logits")
    assert (st["exp_avg"] == 0).all() and (st["exp_avg_sq"] == 0).all()
    assert torch.equal(state_of(opts, model, "means")["exp_avg"], means_state)
    adam_step(model, opts)


@pytest.mark.parametrize("world_fraction", [0.1, 0.015])
def test_pruning_rules(world_fraction):
    n = 6
    model = make_model(n, scale=0.01)
    opts = make_gaussian_optimizers(model)
    adam_step(model, opts)
    with torch.no_grad():
        model.params["log_scales"][:] = math.log(0.01)
        model.params["opacity_logits"][0] = math.log(0.004 / 0.996)  # transparent: pruned at any round
        model.params["opacity_logits"][1] = math.log(0.006 / 0.994)  # just above the limit: kept
        model.params["log_scales"][2, 1] = math.log(0.5)  # > 0.1 x extent (2 x 0.1 = 0.2)
        model.params["log_scales"][3, 2] = math.log(0.05)  # > 0.015 x extent (0.03) but < 0.2
    cfg = DensificationConfig(prune_world_scale=world_fraction)
    strategy, state = strategy_and_state(model, 2.0, cfg)
    radii = torch.tensor([[2, 2], [2, 2], [2, 2], [2, 2], [25, 3], [20, 20]])  # row 4 is too big on screen
    render = fake_render(n, torch.zeros(n, 2), radii)
    strategy.update_statistics(model, state, render)
    assert strategy.prune_mask(model, state, 600).tolist() == [True, False, False, False, False, False]  # before the first reset
    expected = [True, False, True, world_fraction < 0.05, True, False]
    assert strategy.prune_mask(model, state, 3100).tolist() == expected
    report = strategy.step_post_backward(model, opts, state, 3100, render)
    assert report is not None and report.pruned == sum(expected)
    kept = [i for i in range(n) if not expected[i]]
    assert model.particle_index.tolist() == kept
    check_optimizer_consistency(model, opts)


def test_schedule_bounds():
    model = make_model(4, opacity=0.001)  # would all be pruned by any densification round
    strategy, state = strategy_and_state(model)
    opts = make_gaussian_optimizers(model)
    render = fake_render(4, torch.zeros(4, 2), torch.ones(4, 2))
    assert strategy.step_post_backward(model, opts, state, 500, render) is None  # start is exclusive
    assert strategy.step_post_backward(model, opts, state, 15_000, render) is None  # stop is exclusive
    assert state.count.tolist() == [1, 1, 1, 1]  # only step 500 gathered statistics
    assert len(model) == 4


def test_extra_rows_follow_buffers_params_statistics_and_single_optimizer():
    model = make_model(4)
    model.add_buffer("dynamic", torch.tensor([True, False, True, False]))
    emb = model.add_param("embedding", torch.arange(8.0).reshape(4, 2))
    # 3DGS layout: one optimizer with a parameter group per tensor
    opt = torch.optim.Adam([{"params": [p], "name": k} for k, p in model.params.items()], lr=1e-3)
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    _, state = strategy_and_state(model)
    state.grad_accum = torch.tensor([10.0, 11.0, 12.0, 13.0])
    clone(model, opt, state, torch.tensor([False, False, True, False]))
    split(model, opt, state, torch.tensor([True, False, False, False, False]))
    prune(model, opt, state, torch.tensor([False, False, False, True, False, False]))
    assert model.particle_index.tolist() == [1, 2, 3, 0, 0]
    assert model.buffers["dynamic"].tolist() == [False, True, False, True, True]
    assert model.params["embedding"] is not emb
    assert model.params["embedding"].detach()[:, 0].tolist() == pytest.approx([2.0, 4.0, 6.0, 0.0, 0.0], abs=2e-3)
    assert state.grad_accum.tolist() == [11.0, 12.0, 13.0, 0.0, 0.0]  # survivors keep their statistics, children start at 0
    params_in_opt = [g["params"][0] for g in opt.param_groups]
    assert all(any(p is q for q in params_in_opt) for p in model.params.values())
    assert all(opt.state[p]["exp_avg"].shape == p.shape for p in model.params.values())
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    opt.step()


def test_state_dict_round_trip_and_resize():
    model = make_model(3)
    strategy, state = strategy_and_state(model)
    strategy.update_statistics(model, state, fake_render(3, torch.full((3, 2), 1e-5), torch.full((3, 2), 4)))
    saved = state.state_dict()
    other = strategy.initialize_state(3)
    other.load_state_dict(saved)
    assert torch.equal(other.grad_accum, state.grad_accum) and torch.equal(other.max_radii, state.max_radii)
    assert torch.equal(other.count, state.count)
    assert torch.equal(torch.randn(5, generator=other.generator), torch.randn(5, generator=state.generator))
    # the strategy holds nothing of the model: statistics of another size restart when other Gaussians arrive
    bigger = make_model(5)
    strategy.update_statistics(bigger, state, fake_render(5, torch.full((5, 2), 1e-5), torch.full((5, 2), 4)))
    assert state.count.tolist() == [1, 1, 1, 1, 1]


def test_means_lr_schedule():
    cfg = GaussianOptimConfig(means_lr_decay_steps=30_000)
    assert means_lr_at(0, cfg, 2.0, iterations=2400) == pytest.approx(3.2e-4)
    assert means_lr_at(30_000, cfg, 2.0, iterations=2400) == pytest.approx(3.2e-6)
    assert means_lr_at(15_000, cfg, 1.0, iterations=2400) == pytest.approx(1.6e-5)
    run_length = GaussianOptimConfig()  # 0: the schedule spans the run
    assert means_lr_at(1200, run_length, 1.0, iterations=2400) == pytest.approx(1.6e-5)
    assert means_lr_at(2400, run_length, 1.0, iterations=2400) == pytest.approx(1.6e-6)


def test_end_to_end_render_backward_densify_render():
    g = torch.Generator().manual_seed(0)
    xyz = 0.6 * torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=1) * torch.rand(400, 1, generator=g) ** (1 / 3)
    model = GaussianModel.from_points(xyz, torch.rand(400, 3, generator=g))
    opts = make_gaussian_optimizers(model, scene_extent=4.0)
    # every 2 steps from step 1 on, tiny threshold so that many Gaussians grow; percent_dense splits the larger half
    median_scale = float(model.scales.detach().max(dim=-1).values.median())
    cfg = DensificationConfig(start=1, every=2, grad_threshold=1e-7, percent_dense=median_scale / 4.0)
    strategy, state = strategy_and_state(model, 4.0, cfg)
    camera = orbit_camera(40, 30, distance=3.0)
    target = torch.rand(30, 40, 3, generator=g)
    sizes = [len(model)]
    reports = []
    for step in range(1, 5):
        out = rasterize(**model.render_inputs(), camera=camera, backend="cpu")
        strategy.step_pre_backward(out)
        loss = (out.rgb - target).abs().mean()
        loss.backward()
        for opt in opts.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        report = strategy.step_post_backward(model, opts, state, step, out, camera.width, camera.height)
        if report is not None:
            reports.append(report)
        sizes.append(len(model))
    assert [r.step for r in reports] == [2, 4]
    assert reports[0].cloned > 0 and reports[0].split > 0
    assert sizes[-1] > sizes[0]
    check_optimizer_consistency(model, opts)
    idx = model.particle_index
    assert idx.min() >= 0 and idx.max() < 400 and model.num_particles == 400
    out = rasterize(**model.render_inputs(), camera=camera, backend="cpu")
    assert torch.isfinite(out.rgb).all() and out.means2d.shape == (len(model), 2)
    out.rgb.mean().backward()
    assert model.params["means"].grad is not None


def test_a_gaussian_budget_keeps_the_highest_gradient_candidates():
    from pidg.training.densification import within_budget

    grads = torch.tensor([5.0, 4.0, 3.0, 2.0, 1.0, 9.0])
    candidates = torch.tensor([True, True, True, True, True, False])
    large = torch.tensor([False, True, False, True, False, False])  # splits cost split_samples - 1 = 2
    assert torch.equal(within_budget(candidates, grads, large, room=10, split_samples=3), candidates)  # 1+2+1+2+1 fits
    # room 4: 5.0 (clone, 1) and 4.0 (split, 2) fit, 3.0 (clone) makes 4, 2.0 (split) would make 6
    assert within_budget(candidates, grads, large, room=4, split_samples=3).tolist() == [True, True, True, False, False, False]
    assert not within_budget(candidates, grads, large, room=0, split_samples=3).any()
    assert not within_budget(candidates, grads, large, room=-5, split_samples=3).any()  # over budget already


def test_densification_stops_growing_at_the_budget():
    model = make_model(5, scale=0.05)
    with torch.no_grad():
        model.params["log_scales"][:] = math.log(0.005)  # all small: clones
    opts = make_gaussian_optimizers(model)
    strategy, state = strategy_and_state(model, config=DensificationConfig(max_gaussians=7))
    grad = torch.tensor([[1e-5, 0.0], [2e-5, 0.0], [3e-5, 0.0], [4e-5, 0.0], [5e-5, 0.0]])  # all above threshold
    radii = torch.full((5, 2), 3)
    strategy.step_pre_backward(fake_render(5, grad, radii, 200, 100))
    report = strategy.step_post_backward(model, opts, state, 600, fake_render(5, grad, radii, 200, 100))
    assert report is not None and report.cloned == 2 and len(model) == 7
    assert sorted(model.particle_index.tolist()[5:]) == [3, 4]  # the two steepest were cloned
