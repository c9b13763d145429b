"""Never lose a good run: a failure never overwrites the last good checkpoint, non-finite steps roll back with
smaller learning rates, Ctrl-C stops after the step with a checkpoint, run folders are not silently replaced, a
resume refuses to change the data or the model, and every bad option is one line naming it."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import itertools
import json
import os
import signal

import pytest
import torch

from pidg.checkpoint import load_checkpoint
from pidg.cli import main
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.errors import NonFiniteError, TrainingFailed
from pidg.training import losses
from pidg.training.optim import ScheduledOptimizer
from pidg.training.trainer import Trainer, _check_finite


def nan_photometric_loss(monkeypatch, steps):
    """The photometric term returns NaN at the given steps (the first time each is reached, or every time)."""
    original = losses.PhotometricLoss.loss
    seen = set()

    def loss(self, inputs, render, features):
        value, scalars = original(self, inputs, render, features)
        if inputs.step in steps and (steps is ALWAYS or inputs.step not in seen):
            seen.add(inputs.step)
            value = value * float("nan")
        return value, scalars

    monkeypatch.setattr(losses.PhotometricLoss, "loss", loss)


class _Always(set):
    def __contains__(self, step):
        return step >= 6


ALWAYS = _Always()


def finite_checkpoint_step(path) -> int:
    state = load_checkpoint(path)
    params = state["model"]["gaussians"]["params"]
    assert all(torch.isfinite(p).all() for p in params.values())
    return int(state["step"])


def test_a_diverging_run_stops_clearly_and_keeps_the_last_good_checkpoint(small_scene, small_config, tmp_path, monkeypatch):
    nan_photometric_loss(monkeypatch, ALWAYS)
    trainer = Trainer(small_config(tmp_path, max_rollbacks=2), small_scene)
    with pytest.raises(TrainingFailed, match=r"diverged at step 6: the loss is nan.*after 2 rollbacks.*step 4"):
        trainer.train()
    assert finite_checkpoint_step(tmp_path / "checkpoint.pt") == 4  # the failure did not overwrite it
    failed = load_checkpoint(tmp_path / "checkpoint.failed.pt")
    assert failed["format"] == "pidg-failed-state" and failed["rollbacks"] == 2


def test_a_transient_nan_rolls_back_with_smaller_learning_rates(small_scene, small_config, tmp_path, monkeypatch):
    nan_photometric_loss(monkeypatch, {6})
    trainer = Trainer(small_config(tmp_path), small_scene)
    summary = trainer.train()
    assert summary["iterations"] == 10 and summary["rollbacks"] == 1 and summary["lr_scale"] == 0.5
    means = trainer.optimizers["means"]
    assert means.optimizer.param_groups[0]["lr"] == pytest.approx(0.5 * means.schedule(9, means.optimizer.param_groups[0]["base_lr"]))
    assert finite_checkpoint_step(tmp_path / "checkpoint.pt") == 10


def test_a_rollback_to_a_checkpoint_before_the_budget_fit_fits_the_planned_run_again(small_scene, small_config, tmp_path,
                                                                                    monkeypatch):
    """A budget fit lengthens the run after its last checkpoint, then a step diverges: the rollback restores the
    length that checkpoint was written under with its state, so the fit is made again from the planned steps, as the
    straight run made it (the stretch bound never applies to an already stretched length), and the loop runs to it."""

    def run(out_dir):
        cfg = small_config(out_dir, 40, time_budget_minutes=10.0, time_budget_policy="fill", time_budget_max_stretch=1.25)
        cfg = dataclasses.replace(cfg, output=dataclasses.replace(cfg.output, checkpoint_every=10))
        trainer = Trainer(cfg, small_scene)
        trainer.clock = lambda readings=itertools.count(1): 0.5 * next(readings)  # 0.5 s a step: the budget is ample
        return trainer.train()

    straight = run(tmp_path / "straight")
    assert straight["schedule_fit"]["step"] == 12 and straight["iterations"] == 50  # the bound: 1.25 x 40
    nan_photometric_loss(monkeypatch, {14})  # after the fit at step 12; the last checkpoint is step 10's
    rolled = run(tmp_path / "rolled")
    assert rolled["rollbacks"] == 1 and rolled["iterations"] == 50 and rolled["stopped_by"] is None
    assert rolled["schedule_fit"] == straight["schedule_fit"]  # planned 40, fitted 50 at step 12, refitted at 38
    assert json.loads((tmp_path / "rolled" / "config.json").read_text())["optim"]["iterations"] == 50


def test_non_finite_parameters_after_the_optimizer_step_roll_back(small_scene, small_config, tmp_path, monkeypatch):
    original = ScheduledOptimizer.step
    poisoned = []

    def step(self, step, lr_scale=1.0):
        original(self, step, lr_scale)
        if step == 5 and not poisoned and self.optimizer.param_groups[0].get("name") == "opacity_logits":
            poisoned.append(step)
            with torch.no_grad():
                self.optimizer.param_groups[0]["params"][0][0] = float("nan")  # as an eps=0 Adam update would

    monkeypatch.setattr(ScheduledOptimizer, "step", step)
    trainer = Trainer(small_config(tmp_path), small_scene)
    summary = trainer.train()
    assert poisoned == [5] and summary["rollbacks"] == 1 and summary["iterations"] == 10


def test_a_nan_gradient_under_a_finite_loss_rolls_back_naming_the_gradient(small_scene, small_config, tmp_path, monkeypatch):
    """From step 6 the positions' gradient is NaN while the loss stays finite: the step is found (through the
    parameters it makes non-finite) and named by its gradient; the stale gradients are cleared for the retry."""
    original = losses.PhotometricLoss.loss

    def loss(self, inputs, render, features):
        value, scalars = original(self, inputs, render, features)
        if inputs.step >= 6:
            means = inputs.model.gaussians.params["means"] * 1.0
            means.register_hook(lambda grad: grad * float("nan"))
            value = value + 0.0 * means.sum()
        return value, scalars

    monkeypatch.setattr(losses.PhotometricLoss, "loss", loss)
    trainer = Trainer(small_config(tmp_path, max_rollbacks=1), small_scene)
    with pytest.raises(TrainingFailed, match=r"diverged at step 6: non-finite gradients at step 6 in gaussians\.means\b.*after 1 rollback"):
        trainer.train()
    assert finite_checkpoint_step(tmp_path / "checkpoint.pt") == 4
    assert all(p.grad is None for _, p in trainer._named_parameters())


def test_an_error_keeps_the_last_good_checkpoint_and_names_both_files(small_scene, small_config, tmp_path, monkeypatch):
    trainer = Trainer(small_config(tmp_path), small_scene)
    original = trainer.train_step

    def failing_step(**kwargs):
        if trainer.step == 6:
            raise RuntimeError("disk on fire")
        return original(**kwargs)

    monkeypatch.setattr(trainer, "train_step", failing_step)
    with pytest.raises(TrainingFailed, match=r"failed at step 6 \(RuntimeError: disk on fire\).*checkpoint.pt \(step 4\).*checkpoint.failed.pt"):
        trainer.train()
    assert finite_checkpoint_step(tmp_path / "checkpoint.pt") == 4


def test_ctrl_c_finishes_the_step_and_checkpoints(small_scene, small_config, tmp_path, monkeypatch):
    trainer = Trainer(small_config(tmp_path), small_scene)
    original = trainer.train_step

    def step_with_interrupt(**kwargs):
        if trainer.step == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return original(**kwargs)

    monkeypatch.setattr(trainer, "train_step", step_with_interrupt)
    before = signal.getsignal(signal.SIGINT)  # default, or ignored when the tests run in the background
    summary = trainer.train()
    assert summary["stopped_by"] == "interrupt" and summary["iterations"] == 3
    assert finite_checkpoint_step(tmp_path / "checkpoint.pt") == 3
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_stale_temporaries_of_interrupted_saves_are_removed(small_scene, small_config, tmp_path):
    (tmp_path / ".checkpoint.pt.abc123.tmp").write_bytes(b"half a checkpoint")
    Trainer(small_config(tmp_path, iterations=1), small_scene).train()
    assert not list(tmp_path.glob(".*.tmp"))


# ---- the command line ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_procedural_dataset(
        ProceduralSceneConfig(n_train=5, n_test=1, width=16, height=16, n_gaussians=500, n_init_points=100),
        tmp_path_factory.mktemp("cli") / "data",
    )


def run_cli(capsys, *argv) -> tuple[int, list[str]]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip().splitlines()


SMALL = ["--deformation.grid4d.width", "8", "--deformation.grid4d.spatial_grid.log2_table_size", "10",
         "--deformation.grid4d.temporal_grid.log2_table_size", "10", "--output.progress", "false"]


def test_a_run_folder_is_not_replaced_silently(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli(capsys, "train", "--data.path", dataset, "--output.dir", run, "--optim.iterations", "2", *SMALL)[0] == 0
    before = (run / "checkpoint.pt").read_bytes()
    code, err = run_cli(capsys, "train", "--data.path", dataset, "--output.dir", run, "--optim.iterations", "3", *SMALL)
    assert code == 2 and len(err) == 1 and "already holds a run" in err[0] and "--overwrite" in err[0]
    assert (run / "checkpoint.pt").read_bytes() == before
    assert run_cli(capsys, "train", "--data.path", dataset, "--output.dir", run, "--optim.iterations", "3", "--overwrite", *SMALL)[0] == 0
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 3


def test_an_unusable_run_folder_fails_before_training(dataset, tmp_path, capsys):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    code, err = run_cli(capsys, "train", "--data.path", dataset, "--output.dir", not_a_folder, *SMALL)
    assert code == 2 and len(err) == 1 and "is a file" in err[0]


def test_resume_refuses_other_data_or_model_and_applies_a_new_schedule(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli(capsys, "train", "--data.path", dataset, "--output.dir", run, "--optim.iterations", "2", *SMALL)[0] == 0
    code, err = run_cli(capsys, "train", "--resume", "--output.dir", run, "--data.downscale", "2", "--deformation.grid4d.width", "16")
    assert code == 2 and len(err) == 1
    assert "data.downscale 1.0 -> 2.0" in err[0] and "deformation.grid4d.width 8 -> 16" in err[0]
    code = main(["train", "--resume", "--output.dir", str(run), "--optim.iterations", "4", "--gaussian_optim.quats_lr", "0.002"])
    assert code == 0
    saved = json.loads((run / "config.json").read_text())
    assert saved["optim"]["iterations"] == 4 and saved["gaussian_optim"]["quats_lr"] == 0.002  # applied and recorded
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["step"] == 4 and state["optimizers"]["quats"]["param_groups"][0]["lr"] == 0.002  # not the saved 0.001


def test_a_run_trained_from_a_relative_path_is_found_from_any_folder(dataset, tmp_path, capsys, monkeypatch):
    """config.json names the dataset absolutely: eval from another folder finds it, and --resume accepts the same
    folder named from there, but not another one."""
    monkeypatch.chdir(dataset.parent)
    run = tmp_path / "run"
    assert run_cli(capsys, "train", "--data.path", dataset.name, "--output.dir", run, "--optim.iterations", "2", *SMALL)[0] == 0
    assert json.loads((run / "config.json").read_text())["data"]["path"] == str(dataset.resolve())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["eval", str(run), "--lpips", "none"]) == 0 and (run / "eval_test" / "metrics.json").is_file()
    same = os.path.relpath(dataset, elsewhere)
    assert main(["train", "--resume", "--output.dir", str(run), "--data.path", same, "--optim.iterations", "3"]) == 0
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 3
    capsys.readouterr()
    other = write_procedural_dataset(ProceduralSceneConfig(n_train=5, n_test=1, width=16, height=16, n_gaussians=500,
                                                           n_init_points=100), tmp_path / "other")
    code, err = run_cli(capsys, "train", "--resume", "--output.dir", run, "--data.path", other, "--optim.iterations", "4")
    assert code == 2 and len(err) == 1 and f"data.path {dataset.resolve()} -> {other}" in err[0]


@pytest.mark.parametrize(
    "option, value, message",
    [
        ("--optim.iterations", "-5", "--optim.iterations -5: OptimConfig.iterations must be >= 1"),
        ("--output.checkpoint_every", "-1", "--output.checkpoint_every -1: OutputConfig.checkpoint_every must be >= 0"),
        ("--optim.lambda_dssim", "nan", "--optim.lambda_dssim nan: OptimConfig.lambda_dssim must be a finite number"),
        ("--gaussian_optim.means_lr", "nan", "--gaussian_optim.means_lr nan: GaussianOptimConfig.means_lr must be a finite"),
        ("--gaussian_optim.eps", "0", "--gaussian_optim.eps 0: GaussianOptimConfig.eps must be > 0"),
        ("--densify.opacity_reset_value", "1", "--densify.opacity_reset_value 1: DensificationConfig.opacity_reset_value must be in (0, 1)"),
    ],
)
def test_bad_numbers_are_one_line_naming_the_option(dataset, tmp_path, capsys, option, value, message):
    code, err = run_cli(capsys, "train", "--data.path", dataset, "--output.dir", tmp_path / "run", option, value)
    assert code == 2 and len(err) == 1 and message in err[0]
    assert not (tmp_path / "run").exists()


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(FileNotFoundError, match="no config.json"):
        main(["--debug", "eval", str(tmp_path)])


def test_a_bad_choice_is_one_line_too(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--physics", "pde"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and "invalid choice: 'pde'" in err[0] and "pidg train -h" in err[0]


def test_the_finiteness_check_reads_a_sparse_gradient_parameter_at_its_updated_rows():
    """A parameter with a sparse gradient (the material field's index embedding) is checked at the rows its sparse
    optimiser updated: a NaN written there is found and named; the other rows are not read (no update touched
    them), while a dense-gradient parameter is read whole."""
    table = torch.nn.Parameter(torch.zeros(6, 2))
    table.grad = torch.sparse_coo_tensor(torch.tensor([[1, 3, 1]]), torch.ones(3, 2), (6, 2))
    dense = torch.nn.Parameter(torch.zeros(4))
    dense.grad = torch.zeros(4)
    named = [("embedding", table), ("dense", dense)]
    with torch.no_grad():
        table[0] = float("nan")  # a row no gradient touched this step
    _check_finite("parameters", named, 0)
    with torch.no_grad():
        table[3, 1] = float("inf")
    with pytest.raises(NonFiniteError, match=r"non-finite parameters at step 0 in embedding$"):
        _check_finite("parameters", named, 0)
    with torch.no_grad():
        table[3, 1] = 0.0
        dense[2] = float("nan")
    with pytest.raises(NonFiniteError, match=r"in dense$"):
        _check_finite("parameters", named, 0)
    table.grad = torch.sparse_coo_tensor(torch.tensor([[2]]), torch.tensor([[float("nan"), 0.0]]), (6, 2))
    with pytest.raises(NonFiniteError, match=r"non-finite gradients at step 0 in embedding$"):
        _check_finite("gradients", named[:1], 0, grads=True)
