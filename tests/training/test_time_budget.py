"""A time budget either stops a run where it is ("stop") or shortens the run to end inside it ("fit"), with every
learning-rate schedule over the new length; a machine fast enough for the planned run trains it unchanged."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import json

import pytest
import torch

from pidg.checkpoint import load_checkpoint
from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.optim import means_lr_at
from pidg.training.trainer import Trainer

SECONDS_PER_STEP = 0.5


@pytest.fixture(scope="module")
def scene():
    return make_procedural_scene(ProceduralSceneConfig(n_train=6, n_test=2, width=24, height=24, n_gaussians=600, n_init_points=150))


def config(out_dir, budget_minutes, policy, iterations=40) -> TrainConfig:
    cfg = TrainConfig(device="cpu")
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.densify = dataclasses.replace(cfg.densify, start=2, stop=8, every=2, opacity_reset_every=100)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations, time_budget_minutes=budget_minutes, time_budget_policy=policy)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=4, progress=False, preview_every=0, log_every=1)
    return cfg


def steady_clock():
    """A clock that advances SECONDS_PER_STEP per reading: the loop reads it before and after each step."""
    now = [0.0]

    def clock() -> float:
        now[0] += SECONDS_PER_STEP
        return now[0]

    return clock


def trained(cfg, scene) -> tuple[Trainer, dict]:
    trainer = Trainer(cfg, scene)
    trainer.clock = steady_clock()
    return trainer, trainer.train()


def test_the_stop_policy_stops_where_the_budget_is_spent(scene, tmp_path):
    trainer, summary = trained(config(tmp_path, 5 * SECONDS_PER_STEP / 60, "stop"), scene)
    assert summary["stopped_by"] == "time_budget" and summary["iterations"] == 5 and summary["schedule_fit"] is None
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 5


def test_a_fitted_run_ends_inside_its_budget_with_its_schedules_over_the_new_length(scene, tmp_path):
    budget_s = 15.0
    trainer, summary = trained(config(tmp_path, budget_s / 60, "fit"), scene)
    # densification stops at 8, so the step time is measured over steps 9-12 (a tenth of the 31 steps left, < 200)
    assert trainer.fit_start() == 9
    expected = 12 + int((0.98 * budget_s - 12 * SECONDS_PER_STEP) / SECONDS_PER_STEP)
    assert summary["schedule_fit"] == {
        "step": 12, "seconds_per_step": pytest.approx(SECONDS_PER_STEP), "budget_minutes": pytest.approx(budget_s / 60),
        "iterations_planned": 40, "iterations": expected,
    }
    assert summary["iterations"] == expected == 29 and summary["stopped_by"] is None
    assert summary["train_minutes"] * 60 <= budget_s
    # the shortened length is the run's from then on: config.json, the checkpoint's config, the schedules
    assert json.loads((tmp_path / "config.json").read_text())["optim"]["iterations"] == expected
    assert load_checkpoint(tmp_path / "checkpoint.pt")["config"]["optim"]["iterations"] == expected
    g, means = trainer.config.gaussian_optim, trainer.optimizers["means"]
    base = means.optimizer.param_groups[0]["base_lr"]
    assert means.schedule(expected, base) == pytest.approx(g.means_lr_final * trainer.extent)  # decayed to the end
    assert means.schedule(expected, base) < means_lr_at(expected, g, trainer.extent, 40)
    deformation = trainer.optimizers["deformation"]
    assert deformation.schedule(expected, 1.0) == pytest.approx(0.1)  # x0.1 over the run, not over the planned 40
    # a resume keeps the fitted length and does not fit again
    again = Trainer.from_checkpoint(tmp_path / "checkpoint.pt", scene)
    assert again.config.optim.iterations == expected and again.schedule_fit == summary["schedule_fit"]


def test_a_machine_fast_enough_trains_the_planned_run_unchanged(scene, tmp_path):
    fitted, summary = trained(config(tmp_path / "fit", 60.0 / 60, "fit"), scene)
    assert summary["schedule_fit"]["iterations"] == 40 and summary["iterations"] == 40
    plain, _ = trained(config(tmp_path / "plain", None, "fit"), scene)
    for name, value in plain.model.gaussians.params.items():
        assert torch.equal(value, fitted.model.gaussians.params[name]), name


def test_the_cpu_preset_fits_d_nerf_runs_to_thirty_minutes():
    cpu = apply_preset(TrainConfig(device="cpu"), "cpu", "dnerf").optim
    assert (cpu.iterations, cpu.time_budget_minutes, cpu.time_budget_policy) == (12_000, 30.0, "fit")
    other = apply_preset(TrainConfig(device="cpu"), "cpu", "pidg").optim
    assert (other.time_budget_minutes, other.time_budget_policy) == (None, "stop")
