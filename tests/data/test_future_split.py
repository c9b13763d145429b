"""The future-prediction protocol's frame selection: training frames up to a time, evaluation frames after it, with
the times and scene bounds of the whole recording."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.data import DataConfig, load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.data.scene import DatasetError


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    config = ProceduralSceneConfig(n_train=11, n_test=5, width=16, height=16, n_gaussians=500, n_init_points=50)
    return write_procedural_dataset(config, tmp_path_factory.mktemp("future") / "scene")


def test_training_keeps_the_past_and_evaluation_the_future(root):
    full = load_scene(DataConfig(root, progress=False))
    split = load_scene(DataConfig(root, train_until=0.8, progress=False))
    for name, frames in full.splits.items():
        expected = [f.name for f in frames if (f.time <= 0.8) == (name == "train")]
        assert [f.name for f in split.frames(name)] == expected and expected, name
    assert max(split.times("train")) <= 0.8 < min(split.times("test"))
    assert len(split.train) < len(full.train)
    # same coordinates and clock as the whole recording
    assert torch.equal(split.bounds.center, full.bounds.center) and split.bounds.radius == full.bounds.radius
    kept = {f.name: f.time for f in split.test}
    assert all(kept[f.name] == f.time for f in full.test if f.name in kept)
    assert split.info["train_until"] == 0.8


def test_a_range_that_leaves_a_split_empty_names_the_split(root):
    with pytest.raises(DatasetError, match="no test frame has a time after train_until=1.0"):
        load_scene(DataConfig(root, train_until=1.0, progress=False))
    with pytest.raises(ValueError, match="train_until"):
        DataConfig(root, train_until=1.5)
