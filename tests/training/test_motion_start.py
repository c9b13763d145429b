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
from pidg.training.motion_start import identity_rows
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
        return float((field.deform(means, quats, scales, torch.full((len(means),), t)).means - means).norm(dim=1).mean())


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

