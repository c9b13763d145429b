"""Shared by the training tests: a small procedural scene and the small run config that trains on it in seconds."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
from collections.abc import Callable

import pytest

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.data.scene import SceneData
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig


@pytest.fixture(scope="module")
def small_scene() -> SceneData:
    """Six 24x24 training views of the procedural scene (150 initial points)."""
    return make_procedural_scene(ProceduralSceneConfig(n_train=6, n_test=2, width=24, height=24, n_gaussians=600, n_init_points=150))


def _small_config(out_dir, iterations=10, **optim) -> TrainConfig:
    cfg = TrainConfig(device="cpu")
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.densify = dataclasses.replace(cfg.densify, start=2, stop=8, every=2, opacity_reset_every=100)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations, **optim)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=4, progress=False, preview_every=0, log_every=1)
    return cfg


@pytest.fixture
def small_config() -> Callable[..., TrainConfig]:
    """(out_dir, iterations=10, **optim options) -> a run config for ``small_scene``: tiny Grid4D grids, densification
    every 2 steps until 8, a checkpoint every 4 steps, a log line every step, no progress bar or previews."""
    return _small_config
