"""The training loop on a tiny procedural scene: it learns, and an interrupted run resumes to the same result."""
import dataclasses

import pytest
import torch

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig
from pidg.training.trainer import Trainer


@pytest.fixture(scope="module")
def scene():
    return make_procedural_scene(ProceduralSceneConfig(n_train=8, n_test=2, width=40, height=40, n_gaussians=1500, n_init_points=400))


def tiny_config(out_dir, iterations=16) -> TrainConfig:
    cfg = TrainConfig()
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.densify = dataclasses.replace(cfg.densify, start=3, stop=12, every=4, opacity_reset_every=8)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations, static_warmup=2)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=0, progress=False, preview_every=0)
    return cfg


def test_training_reduces_the_loss_and_densifies(scene, tmp_path):
    cfg = tiny_config(tmp_path, iterations=60)
    cfg.output = dataclasses.replace(cfg.output, log_every=1)
    trainer = Trainer(cfg, scene)
    points_before = scene.points3d.xyz.clone()
    summary = trainer.train()
    assert summary["iterations"] == 60
    losses = [h["loss"] for h in trainer.history]
    assert sum(losses[-10:]) / 10 < 0.9 * sum(losses[:10]) / 10
    assert torch.equal(scene.points3d.xyz, points_before)  # training never writes into the dataset
    assert summary["gaussians"] != 400  # densification and pruning ran
    assert set(summary["step_breakdown_ms"]) == {"deformation", "render", "loss", "backward", "optimizer", "densification"}
    assert (tmp_path / "checkpoint.pt").is_file() and (tmp_path / "config.json").is_file()
    assert trainer.decoupled  # the procedural scene has motion masks


def test_resume_matches_an_uninterrupted_run(scene, tmp_path):
    full = Trainer(tiny_config(tmp_path / "full"), scene)
    full.train()
    half = Trainer(tiny_config(tmp_path / "half"), scene)
    half.train(iterations=7)  # stops between densification rounds, writes its checkpoint
    resumed = Trainer.from_checkpoint(tmp_path / "half" / "checkpoint.pt", scene)
    assert resumed.step == 7
    resumed.train()
    assert resumed.step == full.step
    for name, p in full.model.params.items():
        q = resumed.model.params[name]
        assert p.shape == q.shape, name
        assert torch.allclose(p, q, atol=1e-5, rtol=1e-4), name
    assert torch.equal(full.model.particle_index, resumed.model.particle_index)
    for (n1, a), (n2, b) in zip(full.deformation.state_dict().items(), resumed.deformation.state_dict().items()):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4), n1
