"""A CPU run's torch thread count (``TrainConfig.cpu_torch_threads``) and its denormal flushing
(``TrainConfig.flush_denormals``) hold during its steps and no longer."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses

import pytest
import torch

from pidg.models import parallel_linear
from pidg.training.optim import adam
from pidg.training.trainer import Trainer, denormals_flushed


@pytest.mark.parametrize("threads", [1, 0])
def test_cpu_steps_run_torch_on_the_configured_threads_and_training_restores_them(small_scene, small_config, tmp_path, threads):
    """``cpu_torch_threads`` holds during every step (0: torch's own count, untouched); train() gives the caller's
    count back when it returns."""
    trainer = Trainer(dataclasses.replace(small_config(tmp_path, 3), cpu_torch_threads=threads), small_scene)
    seen: list[int] = []
    step = trainer.train_step
    trainer.train_step = lambda **kw: (seen.append(torch.get_num_threads()), step(**kw))[1]  # type: ignore[method-assign]
    caller = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        trainer.train()
        assert seen == [threads or 3] * 3 and torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(caller)


@pytest.mark.parametrize(("torch_threads", "matmul", "expected"), [(1, 0, 3), (1, 2, 2), (0, 2, None)])
def test_cpu_steps_run_the_networks_products_on_cpu_matmul_threads(small_scene, small_config, tmp_path, torch_threads, matmul, expected):
    """With torch on ``cpu_torch_threads``, the layers' products run on ``cpu_matmul_threads`` (0: the caller's
    count); with torch's own count (0) nothing switches; after train() no switch is left behind."""
    config = dataclasses.replace(small_config(tmp_path, 2), cpu_torch_threads=torch_threads, cpu_matmul_threads=matmul)
    trainer = Trainer(config, small_scene)
    seen: list[int | None] = []
    step = trainer.train_step
    trainer.train_step = lambda **kw: (seen.append(parallel_linear._threads), step(**kw))[1]  # type: ignore[method-assign]
    caller = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        trainer.train()
        assert seen == [expected] * 2 and parallel_linear._threads is None
    finally:
        torch.set_num_threads(caller)


@pytest.mark.parametrize(("flush", "caller_flushes"), [(True, False), (False, False), (True, True), (False, True)])
def test_training_flushes_denormals_during_its_steps_and_gives_the_caller_its_mode_back(
    small_scene, small_config, tmp_path, flush, caller_flushes
):
    """``flush_denormals`` holds during every step (False: the caller's mode, untouched); train() restores the
    caller's mode when it returns."""
    trainer = Trainer(dataclasses.replace(small_config(tmp_path, 2), flush_denormals=flush), small_scene)
    seen: list[bool] = []
    step = trainer.train_step
    trainer.train_step = lambda **kw: (seen.append(denormals_flushed()), step(**kw))[1]  # type: ignore[method-assign]
    try:
        torch.set_flush_denormal(caller_flushes)
        trainer.train()
        assert seen == [flush or caller_flushes] * 2 and denormals_flushed() == caller_flushes
    finally:
        torch.set_flush_denormal(False)


@pytest.mark.parametrize("flush", [False, True])
def test_adams_first_moment_of_a_zero_gradient_sticks_in_the_denormal_range_unless_flushed(flush):
    """Why training flushes: after its gradient stops, an entry's first moment decays by beta1 = 0.9 a step; in the
    denormal range a few units of the last place are fixed points of that (round to nearest), so it never reaches
    zero, and every later update computes on a denormal. Flushed, it is exactly zero once it leaves float32's
    normal range."""
    tiny = torch.finfo(torch.float32).tiny
    weight = torch.nn.Parameter(torch.ones(4))
    optimizer = adam([{"params": [weight], "lr": 1e-3}], betas=(0.9, 0.999), eps=1e-15)
    try:
        torch.set_flush_denormal(flush)
        for step in range(1200):  # 0.9 ** 1200 * 1e-2 ~ 1e-57: far below the smallest denormal, 1.4e-45
            weight.grad = torch.full((4,), 1e-2 if step == 0 else 0.0)
            optimizer.step()
        moment = optimizer.state[weight]["exp_avg"]
        if flush:
            assert torch.all(moment == 0)
        else:
            assert torch.all((moment != 0) & (moment.abs() < tiny))
        assert torch.isfinite(weight).all()
    finally:
        torch.set_flush_denormal(False)


def test_a_fused_adam_step_is_counted_in_the_parameters_versions_and_grid4d_renders_the_update():
    """The fused CPU kernel writes the parameters without bumping their versions; `adam` bumps them per step, so a
    cache keyed by versions (Grid4D's attention, reused by deformations without autograd) does not serve the
    parameters from before the step."""
    from pidg.models.deformation import Bounds, Grid4D, Grid4DConfig, HashGridConfig

    weight = torch.nn.Parameter(torch.ones(4))
    optimizer = adam([{"params": [weight], "lr": 1e-3}], betas=(0.9, 0.999), eps=1e-15)
    assert optimizer.defaults["fused"]
    for step in (1, 2):
        weight.grad = torch.ones(4)
        optimizer.step()
        assert weight._version == step
    field = Grid4D(Grid4DConfig(spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16),
                                width=16), Bounds.from_aabb((-1, -1, -1), (1, 1, 1)))
    torch.nn.init.normal_(field.head_warp.weight, std=0.1)  # heads that move the points, so the attention shows
    points, quats, scales, times = torch.rand(64, 3) - 0.5, torch.tensor([[1.0, 0, 0, 0]]).repeat(64, 1), torch.zeros(64, 3), torch.full((64,), 0.5)
    optimizer = adam([{"params": list(field.parameters()), "lr": 1e-2}], betas=(0.9, 0.999), eps=1e-15)
    with torch.no_grad():
        before = field.deform(points, quats, scales, times).means  # fills the attention cache
    field.deform(points, quats, scales, times).means.square().sum().backward()
    optimizer.step()
    with torch.no_grad():
        cached = field.deform(points, quats, scales, times).means
        field._attention_cache = None
        fresh = field.deform(points, quats, scales, times).means
    assert not torch.equal(before, fresh)
    assert torch.equal(cached, fresh)
