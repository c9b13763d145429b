"""`pidg bench views`: its probe ground truth is the dataset's, and it refuses runs on other data."""
import json

import pytest
import torch

from pidg.bench.views import PROBES, procedural_config_of, probe_times, probe_truth, score_probes
from pidg.data.procedural import ProceduralScene, ProceduralSceneConfig, make_procedural_scene
from pidg.data.scene import DatasetError
from pidg.models.deformation import DeformationConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig

CONFIG = ProceduralSceneConfig(n_train=6, n_test=2, width=32, height=32, n_gaussians=800, n_init_points=200)


def test_probe_truth_is_the_datasets_frames():
    data, scene = make_procedural_scene(CONFIG), ProceduralScene(CONFIG)
    times = probe_times(scene)
    assert times["train"] == pytest.approx([f.time for f in data.train])
    for frame in data.train:  # training times from the orbit: exactly the training images and masks
        camera, truth, mask = probe_truth(scene, frame.time, "train")
        assert torch.equal(truth, frame.image) and torch.equal(mask, frame.mask)
        assert torch.allclose(camera.world_to_camera, frame.camera.world_to_camera)
    for frame in data.splits["test"]:  # held-out times from the test rig: exactly the test split
        assert any(abs(frame.time - t) < 1e-12 for t in times["held_out"])
        _, truth, _ = probe_truth(scene, frame.time, "test")
        assert torch.equal(truth, frame.image)


def test_scores_cover_every_probe_set_and_reject_bad_options():
    data, scene = make_procedural_scene(CONFIG), ProceduralScene(CONFIG)
    model = DynamicGaussians.from_scene(data, GaussianModelConfig(), DeformationConfig(kind="identity"), None)
    scores = score_probes(model, scene, every=2)
    assert [s.name for s in scores] == [p[0] for p in PROBES]
    assert [s.views for s in scores] == [3, 3, 3, 3]
    assert all(0 < s.psnr < 60 for s in scores)
    with pytest.raises(ValueError, match="every"):
        score_probes(model, scene, every=0)


def test_a_run_on_other_data_is_refused(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "config.json").write_text(json.dumps({"data": {"path": str(tmp_path / "data")}}))
    with pytest.raises(DatasetError, match="procedural.json"):
        procedural_config_of(tmp_path)
