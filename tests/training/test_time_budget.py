"""A time budget either stops a run where it is ("stop"), shortens the run to end inside it ("fit"), or fits the run to
it either way ("fill": shortened if slow, lengthened up to a bound if fast), with every learning-rate schedule over
the new length; under "fit" a machine fast enough for the planned run trains it unchanged."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import json

import pytest
import torch

from pidg.checkpoint import load_checkpoint
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.optim import means_lr_at
from pidg.training.trainer import Trainer

SECONDS_PER_STEP = 0.5


@pytest.fixture
def config(small_config):
    """(out_dir, budget in minutes or None, policy) -> a 40-step run of the small config with that budget."""
    return lambda out_dir, minutes, policy: small_config(out_dir, 40, time_budget_minutes=minutes, time_budget_policy=policy)


def steady_clock():
    """A clock that advances SECONDS_PER_STEP per reading: the loop reads it before and after each step."""
    return drifting_clock(lambda: SECONDS_PER_STEP)


def drifting_clock(seconds_per_step):
    """A clock that advances ``seconds_per_step()`` per reading (the loop reads it before and after each step, so a
    step takes the value read after it)."""
    now = [0.0]

    def clock() -> float:
        now[0] += seconds_per_step()
        return now[0]

    return clock


def trained(cfg, scene, seconds_per_step=None) -> tuple[Trainer, dict]:
    """The run of ``cfg``, timed by a steady clock or one whose step time is ``seconds_per_step(trainer.step)``."""
    trainer = Trainer(cfg, scene)
    trainer.clock = steady_clock() if seconds_per_step is None else drifting_clock(lambda: seconds_per_step(trainer.step))
    return trainer, trainer.train()


def test_the_stop_policy_stops_where_the_budget_is_spent(small_scene, config, tmp_path):
    trainer, summary = trained(config(tmp_path, 5 * SECONDS_PER_STEP / 60, "stop"), small_scene)
    assert summary["stopped_by"] == "time_budget" and summary["iterations"] == 5 and summary["schedule_fit"] is None
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 5


def test_a_fitted_run_ends_inside_its_budget_with_its_schedules_over_the_new_length(small_scene, config, tmp_path):
    budget_s = 15.0
    trainer, summary = trained(config(tmp_path, budget_s / 60, "fit"), small_scene)
    # densification stops at 8, so the step time is measured over steps 9-12 (a tenth of the 31 steps left, < 200)
    assert trainer.fit_start() == 9
    expected = 12 + int((0.98 * budget_s - 12 * SECONDS_PER_STEP) / SECONDS_PER_STEP)
    assert summary["schedule_fit"] == {
        "step": 12, "seconds_per_step": pytest.approx(SECONDS_PER_STEP), "budget_minutes": pytest.approx(budget_s / 60),
        "iterations_planned": 40, "iterations": expected, "train_seconds": pytest.approx(12 * SECONDS_PER_STEP),
        # two thirds of the way from step 12 to 29 the fit is made again; a steady machine keeps the length
        "refit": {"step": 24, "seconds_per_step": pytest.approx(SECONDS_PER_STEP), "iterations": expected},
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
    again = Trainer.from_checkpoint(tmp_path / "checkpoint.pt", small_scene)
    assert again.config.optim.iterations == expected and again.schedule_fit == summary["schedule_fit"]


def test_a_machine_fast_enough_trains_the_planned_run_unchanged(small_scene, config, tmp_path):
    fitted, summary = trained(config(tmp_path / "fit", 60.0 / 60, "fit"), small_scene)
    assert summary["schedule_fit"]["iterations"] == 40 and summary["iterations"] == 40
    plain, _ = trained(config(tmp_path / "plain", None, "fit"), small_scene)
    for name, value in plain.model.gaussians.params.items():
        assert torch.equal(value, fitted.model.gaussians.params[name]), name


def test_a_filled_run_is_lengthened_to_its_budget_up_to_the_stretch_bound(small_scene, config, tmp_path):
    budget_s = 30.0  # 60 steps' worth: more than the planned 40
    trainer, summary = trained(config(tmp_path / "fill", budget_s / 60, "fill"), small_scene)
    expected = 12 + int((0.98 * budget_s - 12 * SECONDS_PER_STEP) / SECONDS_PER_STEP)
    assert expected == 58 and summary["schedule_fit"]["iterations"] == expected == summary["iterations"]
    assert summary["stopped_by"] is None and summary["train_minutes"] * 60 <= budget_s
    assert json.loads((tmp_path / "fill" / "config.json").read_text())["optim"]["iterations"] == expected
    means, deformation = trainer.optimizers["means"], trainer.optimizers["deformation"]
    g = trainer.config.gaussian_optim
    base = means.optimizer.param_groups[0]["base_lr"]
    assert means.schedule(expected, base) == pytest.approx(g.means_lr_final * trainer.extent)  # decays over the longer run
    assert means.schedule(40, base) > means_lr_at(40, g, trainer.extent, 40)
    assert deformation.schedule(expected, 1.0) == pytest.approx(0.1)
    # a much larger budget lengthens it only up to time_budget_max_stretch x the planned 40 steps
    bounded = config(tmp_path / "bounded", 600.0 / 60, "fill")
    bounded = dataclasses.replace(bounded, optim=dataclasses.replace(bounded.optim, time_budget_max_stretch=1.25))
    _, summary = trained(bounded, small_scene)
    assert summary["schedule_fit"]["iterations"] == summary["iterations"] == 50


def test_a_filled_run_on_a_slow_machine_is_shortened_as_a_fitted_one(small_scene, config, tmp_path):
    _, fitted = trained(config(tmp_path / "fit", 15.0 / 60, "fit"), small_scene)
    _, filled = trained(config(tmp_path / "fill", 15.0 / 60, "fill"), small_scene)
    assert filled["schedule_fit"] == fitted["schedule_fit"] and filled["iterations"] == fitted["iterations"] == 29


def test_a_machine_that_slows_after_the_fit_is_refitted_to_end_inside_the_budget(small_scene, config, tmp_path):
    budget_s = 15.0
    slower = 1.25 * SECONDS_PER_STEP  # from step 13 on; the fit (steps 9-12) planned 29 steps at the steady pace
    pace = lambda step: SECONDS_PER_STEP if step <= 12 else slower  # noqa: E731
    trainer, summary = trained(config(tmp_path, budget_s / 60, "fill"), small_scene, pace)
    fit = summary["schedule_fit"]
    assert fit["iterations"] == 29
    # two thirds of the way to 29 (step 24), 12 slower steps are measured: what is left of 0.98 of the budget buys one
    spent = 12 * SECONDS_PER_STEP + 12 * slower
    expected = 24 + int((0.98 * budget_s - spent) / slower)
    assert fit["refit"] == {"step": 24, "seconds_per_step": pytest.approx(slower), "iterations": expected}
    assert expected == 25 and summary["iterations"] == 25
    # the run ends by its own schedule inside the budget, not at the budget's hard stop (step 27 without the refit)
    assert summary["stopped_by"] is None and summary["train_minutes"] * 60 <= budget_s
    assert trainer.optimizers["deformation"].schedule(expected, 1.0) == pytest.approx(0.1)
    assert json.loads((tmp_path / "config.json").read_text())["optim"]["iterations"] == expected


def test_a_machine_that_speeds_up_after_the_fit_fills_its_budget_under_fill_only(small_scene, config, tmp_path):
    budget_s = 30.0
    faster = 0.75 * SECONDS_PER_STEP
    pace = lambda step: SECONDS_PER_STEP if step <= 12 else faster  # noqa: E731
    fill = config(tmp_path / "fill", budget_s / 60, "fill")
    fill = dataclasses.replace(fill, optim=dataclasses.replace(fill.optim, time_budget_max_stretch=2.0))
    _, summary = trained(fill, small_scene, pace)
    fit = summary["schedule_fit"]
    assert fit["iterations"] == 58  # the fit's pace
    refit_step = 43  # two thirds of the way from 12 to 58
    spent = 12 * SECONDS_PER_STEP + (refit_step - 12) * faster
    expected = refit_step + int((0.98 * budget_s - spent) / faster)
    assert fit["refit"] == {"step": refit_step, "seconds_per_step": pytest.approx(faster), "iterations": expected}
    assert expected == 74 <= 2 * 40 and summary["iterations"] == expected
    assert summary["stopped_by"] is None and summary["train_minutes"] * 60 <= budget_s
    # "fit" never lengthens the planned run, refit or not
    _, summary = trained(config(tmp_path / "fit", budget_s / 60, "fit"), small_scene, pace)
    assert summary["schedule_fit"]["refit"]["iterations"] == summary["iterations"] == 40


def test_a_run_resumed_between_fit_and_refit_refits_as_the_straight_run(small_scene, config, tmp_path):
    budget_s, slower = 15.0, 1.25 * SECONDS_PER_STEP
    straight, summary = trained(config(tmp_path / "straight", budget_s / 60, "fill"), small_scene,
                                lambda step: SECONDS_PER_STEP if step <= 12 else slower)
    trainer = Trainer(config(tmp_path / "cut", budget_s / 60, "fill"), small_scene)
    readings_at_20, at_20 = [0], tmp_path / "at20.pt"

    def pace() -> float:  # the reading that starts step 21 also saves the state after step 20: fitted, not refitted
        if trainer.step == 20:
            readings_at_20[0] += 1
            if readings_at_20[0] == 2:
                torch.save(trainer.state_dict(), at_20)
        return SECONDS_PER_STEP if trainer.step <= 12 else slower

    trainer.clock = drifting_clock(pace)
    trainer.train()
    fit = load_checkpoint(at_20)["schedule_fit"]
    assert fit["iterations"] == 29 and fit["refit"] is None
    resumed = Trainer.from_checkpoint(at_20, small_scene)
    resumed.clock = drifting_clock(lambda: slower)
    again = resumed.train()
    assert again["schedule_fit"] == summary["schedule_fit"] and again["iterations"] == summary["iterations"] == 25
    for name, value in straight.model.gaussians.params.items():
        assert torch.equal(value, resumed.model.gaussians.params[name]), name


def test_the_cpu_preset_fits_d_nerf_runs_to_thirty_minutes():
    cpu = apply_preset(TrainConfig(device="cpu"), "cpu", "dnerf").optim
    assert (cpu.iterations, cpu.time_budget_minutes, cpu.time_budget_policy) == (12_000, 30.0, "fill")
    assert cpu.time_budget_max_stretch == 3.0 > TrainConfig().optim.time_budget_max_stretch == 1.5
    other = apply_preset(TrainConfig(device="cpu"), "cpu", "pidg").optim
    assert (other.time_budget_minutes, other.time_budget_policy) == (None, "stop")
