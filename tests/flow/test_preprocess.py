"""Optical-flow estimation, the forward-backward check, and the on-disk flow cache."""
from __future__ import annotations

import json
import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import pidg  # noqa: F401
from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.data.scene import DatasetError, SceneData
from pidg.flow.config import FlowConfig
from pidg.flow.optical_flow import (
    FlowEstimatorUnavailable,
    forward_backward_consistency,
    make_estimator,
    pixel_centers,
    upsampled,
)
from pidg.flow.preprocess import INDEX_FILE, FlowPair, preprocess_flow

pytest.importorskip("cv2")


def textured(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random RGB texture (sum of a few sinusoids), good for any flow estimator."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w, 3))
    for _ in range(12):
        fx, fy, phase = rng.uniform(0.05, 0.35), rng.uniform(0.05, 0.35), rng.uniform(0, 6.3)
        img += rng.uniform(0.2, 1.0, 3) * np.sin(fx * xx + fy * yy + phase)[..., None]
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


@pytest.mark.parametrize("estimator", ["dis", "deepflow"])
def test_estimators_recover_a_translation(estimator: str):
    big = textured(80, 100)
    image0, image1 = big[10:60, 10:80], big[8:58, 7:77]  # content moves by (+3, +2) pixels from 0 to 1
    flow = make_estimator(FlowConfig(estimator=estimator))(image0, image1)
    assert flow.shape == (50, 70, 2) and flow.dtype == np.float32
    inner = flow[10:-10, 10:-10].reshape(-1, 2)
    np.testing.assert_allclose(np.median(inner, axis=0), [3.0, 2.0], atol=0.25)


def test_upsampled_estimation_brings_the_flow_back_to_the_image_grid():
    """The wrapper's bookkeeping, with fake estimators: a flow of c high-resolution pixels is c / k image pixels,
    and a field that is the high-resolution pixel centres averages to the image's pixel centres (x k)."""
    image = textured(6, 8)
    seen = []

    def constant(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        seen.append(a.shape)
        return np.full(a.shape[:2] + (2,), 3.0, np.float32)

    def centres(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return pixel_centers(a.shape[0], a.shape[1]).numpy()

    for k in (2, 3):
        np.testing.assert_allclose(upsampled(constant, k)(image, image), np.full((6, 8, 2), 3.0 / k), rtol=1e-6)
        assert seen[-1] == (6 * k, 8 * k, 3)
        np.testing.assert_allclose(upsampled(centres, k)(image, image), pixel_centers(6, 8).numpy(), atol=1e-5)
    assert upsampled(constant, 1) is constant


def test_upsampled_dis_recovers_a_translation_and_keys_its_cache_apart():
    big = textured(80, 100)
    image0, image1 = big[10:60, 10:80], big[8:58, 7:77]  # content moves by (+3, +2) pixels from 0 to 1
    estimator = make_estimator(FlowConfig(upsample=2))
    flow = estimator(image0, image1)
    assert flow.shape == (50, 70, 2)
    np.testing.assert_allclose(np.median(flow[10:-10, 10:-10].reshape(-1, 2), axis=0), [3.0, 2.0], atol=0.25)
    assert estimator.settings["upsample"] == 2 and "upsample" not in make_estimator(FlowConfig(upsample=1)).settings


def test_tvl1_is_available():
    estimator = make_estimator(FlowConfig(estimator="tvl1"))
    assert estimator.name == "tvl1" and "opencv" in estimator.settings


def test_consistency_check():
    h, w = 12, 16
    forward = torch.zeros(h, w, 2)
    forward[..., 0], forward[..., 1] = 2.0, 1.0
    valid = forward_backward_consistency(forward, -forward)
    # consistent everywhere except where p + f(p) leaves the image (last 2 columns... and half-pixel ring)
    assert valid[:-1, :-2].all() and not valid[:, -1].any() and not valid[-1].any()
    assert not forward_backward_consistency(forward, forward).any()
    # the tolerance grows with the flow: a 10 % error on a 40-pixel flow passes, on a 4-pixel flow it does not
    big = torch.zeros(64, 64, 2)
    big[..., 0] = 40.0
    assert forward_backward_consistency(big, -0.9 * big)[:, :20].all()
    small = big / 10
    assert not forward_backward_consistency(small, -0.5 * small).any()


# ---------------------------------------------------------------------------------------------------------------
# the cache
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene() -> SceneData:
    """Four consecutive training frames of a slowly orbiting capture (a few pixels of motion per frame)."""
    full = make_procedural_scene(
        ProceduralSceneConfig(n_train=30, n_test=1, width=64, height=48, n_gaussians=1500, orbit_turns=0.2)
    )
    return replace(full, splits={"train": full.train[:4]})


def copy_scene(scene: SceneData) -> SceneData:
    """Fresh Frame objects (images may then be edited without touching the module-scoped scene)."""
    frames = [replace(f, image_u8=f.image_u8.clone()) for f in scene.train]
    return replace(scene, splits={"train": frames})


def test_cache_layout_and_contents(scene: SceneData, tmp_path: Path):
    cache = preprocess_flow(scene, FlowConfig(), cache_root=tmp_path, progress=False)
    directory = tmp_path / "dis_64x48"
    assert cache.directory == directory and len(cache) == 3 and cache.computed == 3 and cache.reused == 0
    index = json.loads((directory / INDEX_FILE).read_text())
    assert index["format"] == 1 and index["estimator"] == "dis" and (index["width"], index["height"]) == (64, 48)
    names = [p["file"] for p in index["pairs"]]
    assert names == ["train_r_0000__train_r_0002.npz", "train_r_0002__train_r_0004.npz", "train_r_0004__train_r_0006.npz"]
    assert [p["frame0"] for p in index["pairs"]] == ["train/r_0000", "train/r_0002", "train/r_0004"]
    assert all(p["time1"] > p["time0"] for p in index["pairs"])
    assert sorted(os.listdir(directory)) == sorted([*names, INDEX_FILE])
    with np.load(directory / names[1]) as data:
        assert data["forward"].dtype == np.float32 and data["forward"].shape == (48, 64, 2)
        assert data["valid_backward"].dtype == bool and data["valid_backward"].shape == (48, 64)
        np.testing.assert_allclose(cache.pair(1).forward.numpy(), data["forward"], atol=0.02)  # float16 in memory
    pair = cache.pair(1)
    assert pair.frame0 is scene.train[1] and pair.frame1 is scene.train[2]
    assert "forward" not in vars(pair) and "backward" not in vars(pair)  # nothing converted until read
    assert pair.forward.dtype == torch.float32 and pair.valid_forward.dtype == torch.bool
    assert pair.forward is pair.forward and torch.equal(pair.forward, cache.forward[1].float())  # converted once
    assert torch.equal(pair.backward, cache.backward[1].float())
    assert pair.dt == pytest.approx(scene.train[2].time - scene.train[1].time)
    assert cache.pair_starting_at(scene.train[2]).index == 2
    assert cache.pair_starting_at(scene.train[3]) is None
    # the pair back from a frame (--flow.directions both): the one ending there, reversed
    back = cache.pair_back_from(scene.train[2])
    assert back.frame0 is scene.train[2] and back.frame1 is scene.train[1] and back.dt == pytest.approx(-pair.dt)
    assert torch.equal(back.forward, pair.backward) and torch.equal(back.backward, pair.forward)
    assert torch.equal(back.valid_forward, pair.valid_backward) and torch.equal(back.valid_backward, pair.valid_forward)
    again = back.reversed()
    assert again.frame0 is pair.frame0 and again.frame1 is pair.frame1 and torch.equal(again.forward, pair.forward)
    assert cache.pair_back_from(scene.train[0]) is None
    assert cache.pair_back_from(replace(scene.train[3])).frame1 is scene.train[2]  # by name, as for pair_starting_at
    # the ring moves and the camera orbits: real flow, mostly consistent
    assert pair.forward.norm(dim=-1).mean() > 0.5
    assert pair.valid_forward.float().mean() > 0.5


def test_moving_coverage_is_the_share_of_the_masks_pixels_whose_flow_passed_the_check(scene: SceneData):
    frame0, frame1 = scene.train[0], replace(scene.train[1], mask=None)
    h, w = 48, 64
    mask, valid = torch.zeros(h, w, dtype=torch.bool), torch.zeros(h, w, dtype=torch.bool)
    mask[10:12, 20:25] = True  # 10 moving pixels
    valid[10, 20:23] = True  # 3 of them consistent
    valid[30:40, 30:40] = True  # consistent pixels outside the mask do not count
    flow = torch.zeros(h, w, 2)

    def pair(frame_mask: torch.Tensor | None) -> FlowPair:
        return FlowPair(0, replace(frame0, mask=frame_mask), frame1, flow, flow, valid, ~valid)

    assert pair(mask).moving_coverage() == pytest.approx(0.3)
    assert pair(mask).reversed().moving_coverage() is None  # frame1 has no mask
    assert pair(None).moving_coverage() is None
    assert pair(torch.zeros_like(mask)).moving_coverage() is None  # nothing moves: nothing to judge


def test_cache_is_incremental(scene: SceneData, tmp_path: Path):
    config = FlowConfig()
    preprocess_flow(scene, config, cache_root=tmp_path, progress=False)
    directory = tmp_path / "dis_64x48"
    stamps = {p.name: p.stat().st_mtime_ns for p in directory.glob("*.npz")}

    again = preprocess_flow(scene, config, cache_root=tmp_path, progress=False)
    assert again.computed == 0 and again.reused == 3
    assert stamps == {p.name: p.stat().st_mtime_ns for p in directory.glob("*.npz")}

    edited = copy_scene(scene)
    edited.train[1].image_u8[20:24] = 128  # frame 1 belongs to pairs 0 and 1
    assert preprocess_flow(edited, config, cache_root=tmp_path, progress=False).computed == 2

    changed = preprocess_flow(edited, replace(config, consistency_alpha=0.02), cache_root=tmp_path, progress=False)
    assert changed.computed == 3  # settings are part of every pair's key

    fewer = replace(edited, splits={"train": edited.train[:3]})
    assert preprocess_flow(fewer, replace(config, consistency_alpha=0.02), cache_root=tmp_path, progress=False).computed == 0
    assert len(list(directory.glob("*.npz"))) == 2  # the pair no frame list refers to any more is gone
    assert not list(directory.glob("*.tmp"))


def test_corrupt_cache_file_is_recomputed(scene: SceneData, tmp_path: Path):
    preprocess_flow(scene, FlowConfig(), cache_root=tmp_path, progress=False)
    victim = next((tmp_path / "dis_64x48").glob("*.npz"))
    victim.write_bytes(b"not a zip file")
    assert preprocess_flow(scene, FlowConfig(), cache_root=tmp_path, progress=False).computed == 1


def test_training_frames_are_sorted_by_time(scene: SceneData, tmp_path: Path):
    shuffled = replace(scene, splits={"train": scene.train[::-1]})
    cache = preprocess_flow(shuffled, FlowConfig(), cache_root=tmp_path, progress=False)
    assert [f.name for f in cache.frames] == [f.name for f in scene.train]


def test_size_mismatch_names_the_frame(scene: SceneData, tmp_path: Path):
    bad = copy_scene(scene)
    bad.train[2].image_u8 = bad.train[2].image_u8[:, :-2].clone()
    with pytest.raises(DatasetError, match=r"train/r_0004.*62x48"):
        preprocess_flow(bad, FlowConfig(), cache_root=tmp_path, progress=False)


def test_default_cache_location_needs_a_dataset_folder(scene: SceneData):
    with pytest.raises(ValueError, match="cache_root"):
        preprocess_flow(scene, FlowConfig(), progress=False)  # an in-memory scene has no folder


def test_default_cache_lives_next_to_the_dataset(scene: SceneData, tmp_path: Path):
    cache = preprocess_flow(replace(scene, root=tmp_path), FlowConfig(cache_dir="flows"), progress=False)
    assert cache.directory == tmp_path / "flows" / "dis_64x48"


def test_raft_needs_local_weights(scene: SceneData, tmp_path: Path):
    with pytest.raises(FlowEstimatorUnavailable, match="raft_weights.*Nothing is downloaded"):
        preprocess_flow(scene, FlowConfig(estimator="raft"), cache_root=tmp_path, progress=False)
    with pytest.raises(FlowEstimatorUnavailable, match="does not exist"):
        make_estimator(FlowConfig(estimator="raft", raft_weights=tmp_path / "raft.pt"))


def test_raft_runs_a_local_exported_program(tmp_path: Path):
    """The RAFT plumbing (padding to multiples of 8, [-1, 1] input, last refinement, cropping) with a stand-in."""

    class ConstantFlow(torch.nn.Module):
        def forward(self, image0: torch.Tensor, image1: torch.Tensor) -> list[torch.Tensor]:
            n, _, h, w = image0.shape
            first = torch.zeros(n, 2, h, w)
            return [first, first + (image1.mean() - image0.mean() + 1.5)]

    example = (torch.zeros(1, 3, 32, 48), torch.zeros(1, 3, 32, 48))  # 30x45 padded to multiples of 8
    path = tmp_path / "raft.pt2"
    torch.export.save(torch.export.export(ConstantFlow(), example), str(path))
    estimator = make_estimator(FlowConfig(estimator="raft", raft_weights=path))
    flow = estimator(np.zeros((30, 45, 3), np.uint8), np.zeros((30, 45, 3), np.uint8))
    assert flow.shape == (30, 45, 2) and np.allclose(flow, 1.5)
    assert len(estimator.settings["weights_sha1"]) == 40


def _orbit_frames(angles_deg: list[float]) -> list:
    """Frames at times 0..1 whose cameras look at the origin from the horizon at the given azimuths."""
    from pidg.data.scene import Frame
    from pidg.render.camera import Camera

    frames = []
    for k, angle in enumerate(angles_deg):
        a = math.radians(angle)
        camera = Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 8, 8, 1.0)
        frames.append(Frame(camera, k / max(len(angles_deg) - 1, 1), torch.zeros(8, 8, 3, dtype=torch.uint8), name=f"f{k}"))
    return frames


def test_median_view_change_is_the_angle_between_consecutive_views():
    from pidg.flow import median_view_change

    orbit = _orbit_frames([5.0 * k for k in range(12)])  # a video: 5 degrees a frame
    assert median_view_change(orbit) == pytest.approx(5.0, abs=1e-3)
    assert median_view_change(list(reversed(orbit))) == pytest.approx(5.0, abs=1e-3)  # the same turns backwards
    jumping = _orbit_frames([0.0, 90.0, 10.0, 170.0, 20.0, 100.0, 30.0])  # D-NeRF-like: views jump
    assert median_view_change(jumping) == pytest.approx(80.0, abs=1e-3)
    assert median_view_change(orbit[:1]) == 0.0


def test_the_trainer_refuses_the_flow_loss_where_consecutive_views_jump(tmp_path: Path):
    """One line naming the dataset, the measured turn and the option; the same data trains with the check off."""
    from pidg.training.config import TrainConfig
    from pidg.training.trainer import Trainer

    scene = make_procedural_scene(ProceduralSceneConfig(n_train=6, n_test=2, width=24, height=24, n_gaussians=600, n_init_points=150))
    cfg = TrainConfig()
    cfg.flow = replace(cfg.flow, kind="lpfm")  # six frames orbit once: ~60 degrees between flow pairs
    cfg.output = replace(cfg.output, dir=tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match=r"--flow lpfm: .*turn by \d+ degrees at the median .*--flow.max_view_change 30.*--flow none"):
        Trainer(cfg, scene)
    cfg.flow = replace(cfg.flow, max_view_change=180.0)
    assert Trainer(cfg, scene).flow_cache is not None


def test_the_viewpoint_check_reads_the_training_frames_in_time_order():
    """The check measures the flow pairs, consecutive in time, not the order the frames were listed in."""
    from pidg.flow import check_flow_viewpoints, median_view_change

    scene = make_procedural_scene(ProceduralSceneConfig(n_train=24, n_test=2, width=24, height=24, n_gaussians=600, n_init_points=150))
    order = torch.randperm(len(scene.train), generator=torch.Generator().manual_seed(0)).tolist()
    shuffled = replace(scene, splits={**scene.splits, "train": [scene.train[k] for k in order]})
    assert median_view_change(shuffled.train) > 30.0  # listed out of order, the views jump
    check_flow_viewpoints(shuffled, FlowConfig())  # in time order they turn by 15 degrees a pair: accepted
