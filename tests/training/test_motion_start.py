"""`--optim.motion_start rigid_tracks`: a new run's deformation is fitted to rigid-body tracks before step 0; a run
that cannot have them stops at once with one line naming what it lacks."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import logging

import pytest
import torch

from pidg.cli import main
from pidg.data import DataConfig, load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig
from pidg.training.losses import StepInputs, TrackHoldLoss
from pidg.training.motion_start import TrackTargets, fit_config, identity_rows
from pidg.training.optim import deformation_optimizer
from pidg.training.run_folder import resume_config
from pidg.training.trainer import Trainer


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=1, width=48, height=48, n_gaussians=800, n_init_points=300),
        tmp_path_factory.mktemp("motion_start") / "data",
    )


def config(dataset, out_dir, start: str) -> TrainConfig:
    cfg = TrainConfig(data=DataConfig(path=dataset, progress=False))
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=64)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=8)
    cfg.flow = dataclasses.replace(cfg.flow, kind="lpfm", max_view_change=180.0)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=2, motion_start=start, motion_start_steps=150)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=0, progress=False, preview_every=0)
    return cfg


def moved(trainer: Trainer, t: float) -> float:
    """Mean distance (world units) the deformation moves the canonical Gaussians to time t."""
    field = trainer.model.deformation
    means = trainer.model.gaussians.params["means"].detach()
    quats, scales = identity_rows(len(means), means.device)
    with torch.no_grad():
        return float((field.deform(means, quats, scales, torch.full((len(means),), t, device=means.device)).means - means).norm(dim=1).mean())


def test_a_new_run_starts_from_the_tracks_and_a_resumed_one_does_not_refit(dataset, tmp_path, caplog):
    scene = load_scene(DataConfig(path=dataset, progress=False))
    rest = Trainer(config(dataset, tmp_path / "rest", "rest"), scene)
    with caplog.at_level(logging.INFO, logger="pidg.training.motion_start"):
        tracked = Trainer(config(dataset, tmp_path / "tracked", "rigid_tracks"), scene)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("motion start:")]
    assert len(lines) == 1 and "rigid bodies fitted" in lines[0] and "through all 5 intervals" in lines[0]
    assert moved(tracked, 1.0) > 10 * moved(rest, 1.0)  # the fitted field carries the moving surface, rest does not
    tracked.train()
    caplog.clear()
    resumed = Trainer.from_checkpoint(tmp_path / "tracked" / "checkpoint.pt", scene)
    assert not any(r.getMessage().startswith("motion start:") for r in caplog.records)
    assert moved(resumed, 1.0) == pytest.approx(moved(tracked, 1.0), rel=1e-6)


def test_rigid_tracks_need_the_flow(dataset, tmp_path, capsys):
    code = main(["train", "--data.path", str(dataset), "--output.dir", str(tmp_path / "run"), "--optim.motion_start",
                 "rigid_tracks", "--flow", "none", "--optim.iterations", "2", "--output.progress", "false"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--optim.motion_start rigid_tracks tracks bodies through the optical flow" in err[0]


def test_a_start_where_every_body_is_lost_stops_clearly(dataset, tmp_path, monkeypatch):
    import pidg.training.motion_start as motion_start

    real = motion_start.track_rigid_bodies

    def lost_at_frame_3(*args):  # tracked through intervals 0-1 of 5: under half
        tracks = real(*args)
        tracks.known[3:] = False
        return tracks

    monkeypatch.setattr(motion_start, "track_rigid_bodies", lost_at_frame_3)
    with pytest.raises(ValueError, match=r"rigid_tracks: every body was lost before half the training intervals .* by interval 2 of 5\): train from rest"):
        Trainer(config(dataset, tmp_path / "run", "rigid_tracks"), load_scene(DataConfig(path=dataset, progress=False)))


# ---- the tracks term (--optim.lambda_tracks): the start's tracks held through training ----------------------------

def tracks_term(trainer: Trainer) -> TrackHoldLoss:
    return next(term for term in trainer.loss_terms if isinstance(term, TrackHoldLoss))


class _Render:
    """A render stand-in: the tracks term reads only its image's dtype and device."""

    def __init__(self, device: torch.device):
        self.rgb = torch.zeros(2, 2, 3, device=device)


def step_inputs(trainer: Trainer, frame, deforming: bool = True) -> tuple[StepInputs, _Render]:
    """The term's inputs at ``frame``, and the render stand-in (on the model's device: CUDA where there is one)."""
    state = trainer.model.at(frame.time)
    return StepInputs(0, frame, trainer.model, state, deforming), _Render(trainer.model.device)


def carried(trainer: Trainer, targets: TrackTargets, k: int) -> torch.Tensor:
    quats, scales = identity_rows(len(targets.start), targets.start.device)
    with torch.no_grad():
        return trainer.model.deformation.deform(targets.start, quats, scales, targets.times[k].expand(len(targets.start))).means


def test_the_tracks_term_is_the_mean_absolute_position_error_at_the_frames_time(dataset, tmp_path, monkeypatch):
    import pidg.training.losses as losses

    scene = load_scene(DataConfig(path=dataset, progress=False))
    cfg = config(dataset, tmp_path / "run", "rigid_tracks")
    trainer = Trainer(dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, lambda_tracks=2.0)), scene)
    term = tracks_term(trainer)
    targets = term.targets
    assert targets is not None and targets.positions.shape == (len(targets.times), len(targets.start), 3)
    assert torch.allclose(targets.times, torch.tensor([f.time for f in scene.train], device=targets.times.device))
    monkeypatch.setattr(losses, "TRACK_POINTS_PER_STEP", len(targets.start))  # every point: a closed form
    k = 3
    frame = scene.train[k]
    # targets where the field already carries the points: no error; then 0.3 off along x only: a mean of 0.1
    term.targets = TrackTargets(targets.start, carried(trainer, targets, k)[None].expand(len(targets.times), -1, -1).clone(),
                                targets.times, torch.ones_like(targets.known))
    inputs, render = step_inputs(trainer, frame)
    value, scalars = term.loss(inputs, render, None)
    assert float(value.detach()) == pytest.approx(0.0, abs=1e-6)
    term.targets.positions[k, :, 0] += 0.3
    value, scalars = term.loss(inputs, render, None)
    assert scalars["tracks"] == pytest.approx(0.1, rel=1e-4) and float(value.detach()) == pytest.approx(0.2, rel=1e-4)
    # only the points known at that time count: the others are 10 off and change nothing
    term.targets.known[k, ::2] = False
    term.targets.positions[k, ::2] += 10.0
    assert term.loss(inputs, render, None)[1]["tracks"] == pytest.approx(0.1, rel=1e-4)
    # a time the tracks do not hold, or a step before the deformation runs: nothing
    off_time = dataclasses.replace(frame, time=float(frame.time) + 0.01)
    for args in ((off_time, True), (frame, False)):
        inputs, render = step_inputs(trainer, *args)
        value, scalars = term.loss(inputs, render, None)
        assert float(value.detach()) == 0.0 and scalars == {}


def test_the_tracks_term_holds_the_deformation_and_its_tracks_survive_a_resume(dataset, tmp_path):
    scene = load_scene(DataConfig(path=dataset, progress=False))
    cfg = config(dataset, tmp_path / "run", "rigid_tracks")
    cfg = dataclasses.replace(cfg, optim=dataclasses.replace(cfg.optim, lambda_tracks=1.0, motion_start_steps=5))
    trainer = Trainer(cfg, scene)
    term = tracks_term(trainer)
    targets = term.targets
    # the field fitted for 5 steps only is far from its tracks; steps of the tracks term alone bring it near
    optimizer = deformation_optimizer(trainer.model.deformation, fit_config(cfg, 400), scene_extent=1.0)

    def error() -> float:
        return float(sum((carried(trainer, targets, k) - targets.positions[k]).abs()[targets.known[k]].mean()
                         for k in range(len(targets.times))) / len(targets.times))

    before = error()
    for step in range(400):
        inputs, render = step_inputs(trainer, scene.train[step % len(scene.train)])
        value, _ = term.loss(inputs, render, None)
        optimizer.zero_grad()
        value.backward()
        optimizer.step(step)
    assert error() < 0.5 * before
    trainer.train()
    resumed = Trainer.from_checkpoint(tmp_path / "run" / "checkpoint.pt", scene)
    kept = tracks_term(resumed)
    # a checkpoint's targets load on the CPU and move to the run's device at the first step that reads them
    assert kept.targets is not None and all(torch.equal(getattr(kept.targets, f).cpu(), getattr(term.targets, f).cpu())
                                            for f in ("start", "positions", "times", "known"))
    assert torch.equal(kept.generator.get_state(), term.generator.get_state())


def test_the_tracks_term_needs_the_tracks_start(dataset, tmp_path, capsys):
    code = main(["train", "--data.path", str(dataset), "--output.dir", str(tmp_path / "run"), "--optim.lambda_tracks",
                 "1", "--optim.iterations", "2", "--output.progress", "false"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--optim.lambda_tracks 1.0 holds the deformation to the tracks" in err[0]
    assert "--optim.motion_start rigid_tracks" in err[0]


def test_a_resumed_run_cannot_add_the_tracks_term():
    saved = TrainConfig()
    with pytest.raises(ValueError, match=r"a tracks term \(optim.lambda_tracks\): the run kept no tracks to hold"):
        resume_config(saved, {"optim.lambda_tracks": "1"})
