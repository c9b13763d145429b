"""`pidg render` on a tiny full-PIDG run writes the physics and flow pictures next to the usual videos."""
import dataclasses
import json
import logging
import re

import pytest
import torch
from PIL import Image

from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.data import DataConfig, load_scene
from pidg.evaluation.images import TITLE_STRIP_PX
from pidg.evaluation.video import ffmpeg_available
from pidg.models.deformation import HashGridConfig
from pidg.pipeline import DEMO_DEPTH_CHANGE_WEIGHT, DEMO_DEPTH_WEIGHT, demo_config, render_run
from pidg.training.config import TrainConfig
from pidg.training.trainer import Trainer


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("render")
    data_dir = write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=2, width=32, height=32, n_gaussians=800, n_init_points=300), root / "data"
    )
    cfg = TrainConfig(data=DataConfig(path=data_dir, progress=False))
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=64)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=8)
    cfg.flow = dataclasses.replace(cfg.flow, kind="lpfm", max_view_change=180.0)  # a few-frame orbit: the machinery only
    cfg.densify = dataclasses.replace(cfg.densify, start=2, stop=6, every=2)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=8)
    cfg.output = dataclasses.replace(cfg.output, dir=root / "run", checkpoint_every=0, progress=False, preview_every=0)
    Trainer(cfg, load_scene(cfg.data)).train()
    return root / "run"


def test_render_writes_velocity_stress_flows_and_split(full_run):
    written = render_run(full_run, "test", fps=4, n_time_steps=3)
    # MP4 where imageio-ffmpeg is installed, else the GIF fallback (tests/evaluation/test_video.py)
    assert {p.suffix for p in written} == {".mp4" if ffmpeg_available() else ".gif"}
    assert {"fixed_view_velocity", "fixed_view_velocity_quiver", "fixed_view_stress_magnitude",
            "train_flows_motion_gaussian_velocity", "test_dynamic_red_static_blue"} <= {p.stem for p in written}
    out = full_run / "render_test"
    pairs = sorted((out / "flows_motion_gaussian_velocity").glob("*.png"))
    assert len(pairs) == 5  # 6 training frames -> 5 pairs
    assert Image.open(pairs[0]).size == (3 * 32, 32 + TITLE_STRIP_PX)  # target | Gaussian | velocity, titled
    scales = json.loads((out / "field_scales.json").read_text())
    assert scales["dt_physics_units"] == pytest.approx(1.0)  # default time_scale: one unit per training frame
    errors = json.loads((out / "flow_errors.json").read_text())
    assert len(errors) == 5 and all(e["gaussian_flow_epe"] >= 0 for e in errors)


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")  # 32 px images are below MS-SSIM's minimum
def test_cli_eval_with_lpips_none_writes_metrics_without_lpips(full_run):
    from pidg.cli import main

    assert main(["eval", str(full_run), "--split", "test", "--lpips", "none"]) == 0
    metrics = json.loads((full_run / "eval_test" / "metrics.json").read_text())
    assert metrics["mean"]["psnr"] > 0 and not any("lpips" in k for k in metrics["mean"])
    chart = (full_run / "eval_test" / "psnr_over_time.svg").read_text()  # one point per view
    assert len(re.search(r'points="([^"]+)"', chart).group(1).split()) == metrics["views"]


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")
def test_evaluating_a_run_builds_nothing_for_training(full_run, monkeypatch):
    """Loading a run for evaluation reads the scene model out of the checkpoint: no Trainer, no optimizer, no
    optical flow, no kNN initialisation."""
    import pidg.flow.preprocess
    import pidg.models.gaussians
    import pidg.training.optim
    from pidg.models.dynamic_gaussians import DynamicGaussians
    from pidg.pipeline import evaluate_run, load_run

    def forbidden(*args, **kwargs):
        raise AssertionError("evaluation must not build this")

    monkeypatch.setattr(Trainer, "__init__", forbidden)
    monkeypatch.setattr(pidg.training.optim, "make_optimizers", forbidden)
    monkeypatch.setattr(pidg.flow.preprocess, "preprocess_flow", forbidden)
    monkeypatch.setattr(pidg.models.gaussians, "knn_init_scales", forbidden)
    result = evaluate_run(full_run, "test", lpips_nets=())
    assert result["views"] == 2 and result["iterations"] == 8 and result["gaussians"] > 0
    run = load_run(full_run, ("test",))
    model = DynamicGaussians.from_run(full_run, device=run.model.device)  # the device load_run chose (auto)
    frame = run.scene.test[0]
    with torch.no_grad():
        assert torch.equal(model.render(frame.camera, frame.time).rgb, run.model.render(frame.camera, frame.time).rgb)


def test_a_folder_that_is_not_a_run_is_named(tmp_path):
    from pidg.pipeline import load_run

    with pytest.raises(FileNotFoundError, match="no config.json"):
        load_run(tmp_path)


def test_demo_trains_against_the_scene_depth_maps(tmp_path):
    """The demo's scene ships its true depth and the demo's default run trains against it; weight 0 is RGB only."""
    data_dir = write_procedural_dataset(
        ProceduralSceneConfig(n_train=4, n_test=1, width=24, height=24, n_gaussians=600, n_init_points=100), tmp_path / "data"
    )
    config = demo_config(data_dir, tmp_path / "run", iterations=4, minutes=None)
    assert config.optim.lambda_depth == DEMO_DEPTH_WEIGHT > 0
    scene = load_scene(config.data)
    assert scene.info["depth_maps"] and all(f.depth is not None for f in scene.train)
    trainer = Trainer(config, scene)  # would stop, naming the dataset, if no training frame had depth
    assert "depth_rel" in trainer.train_step()
    rgb_only = demo_config(data_dir, tmp_path / "run", 4, None, depth_weight=0.0)
    assert rgb_only.optim.lambda_depth == 0.0 and rgb_only.flow.lambda_depth_change == 0.0
    # with --flow lpfm the flow loss also matches the depth change, and trains with it
    assert config.flow.lambda_depth_change == DEMO_DEPTH_CHANGE_WEIGHT > 0


def test_demo_with_a_negative_depth_weight_stops_before_making_the_scene(tmp_path, capsys):
    from pidg.cli import main

    assert main(["demo", "--out", str(tmp_path / "demo"), "--depth-weight", "-1"]) != 0
    assert "lambda_depth must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "demo" / "data").exists()


def test_cli_eval_tells_small_images_miss_ms_ssim_in_one_log_line(full_run, caplog):
    from pidg.cli import main

    with caplog.at_level(logging.WARNING):
        assert main(["eval", str(full_run), "--split", "test", "--lpips", "none"]) == 0
    notes = [r.getMessage() for r in caplog.records if r.name == "py.warnings"]
    assert notes and notes[0].startswith("RuntimeWarning: ms_ssim reported as None: MS-SSIM") and "\n" not in notes[0]
    assert ".py:" not in notes[0]  # no file and line of pidg's source
