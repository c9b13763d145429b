"""Flow preprocessing on the real datasets in ../shared/data (skipped when absent). The cache goes to tmp_path: tests
never write into the shared data."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import pidg  # noqa: F401
from pidg.data import load_scene
from pidg.data.scene import DataConfig
from pidg.flow import FlowConfig, flow_target_for_pair, preprocess_flow

pytest.importorskip("cv2")


def dataset(shared_data: Path, *parts: str) -> Path:
    root = shared_data.joinpath(*parts)
    if not root.is_dir():
        pytest.skip(f"{root} is not present")
    return root


def first_frames(root: Path, n: int, out: Path) -> Path:
    """A view of a Blender-style dataset with only its first ``n`` training frames (json rewritten, files linked):
    consecutive video frames, unlike DataConfig.max_frames' evenly spread subset."""
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][:n]
    out.mkdir()
    (out / "transforms_train.json").write_text(json.dumps(meta))
    for child in root.iterdir():
        if child.is_dir():
            (out / child.name).symlink_to(child, target_is_directory=True)
    return out


def test_dry_ice_flows_and_targets(shared_data: Path, tmp_path: Path):
    root = first_frames(dataset(shared_data, "pidg", "dry_ice"), 3, tmp_path / "dry_ice")
    scene = load_scene(DataConfig(root, downscale=(240, 135), splits=("train",), progress=False))
    cache = preprocess_flow(scene, FlowConfig(), cache_root=tmp_path / "cache", progress=False)
    assert len(cache) == 2 and cache.directory == tmp_path / "cache" / "dis_240x135"
    pair = cache.pair(0)
    assert pair.forward.shape == (135, 240, 2) and pair.dt > 0
    assert pair.frame0.mask is not None  # PIDG scenes ship motion masks
    assert float(pair.valid_forward.float().mean()) > 0.5  # consecutive frames of a smooth camera path
    depth1 = torch.full((135, 240), 5.0)  # no depth in the dataset: the trainer passes its rendered depth
    target = flow_target_for_pair(pair, depth1, FlowConfig())
    assert target.flow.shape == (135, 240, 2) and target.valid.any()


def test_dnerf_flows(shared_data: Path, tmp_path: Path):
    """D-NeRF's consecutive training frames jump viewpoints, so few pixels pass the consistency check; the
    pipeline still runs (the paper trains D-NeRF without LPFM)."""
    root = dataset(shared_data, "dnerf", "bouncingballs")
    scene = load_scene(DataConfig(root, downscale=(100, 100), max_frames=3, splits=("train",), progress=False))
    cache = preprocess_flow(scene, FlowConfig(), cache_root=tmp_path, progress=False)
    assert len(cache) == 2 and cache.forward.shape == (2, 100, 100, 2)
    times = [f.time for f in cache.frames]
    assert times == sorted(times)
    assert cache.pair(0).frame0.mask is None  # no masks: flow_gt falls back to the flow-derived motion mask
    target = flow_target_for_pair(cache.pair(0), torch.full((100, 100), 4.0), FlowConfig())
    assert target.flow.shape == (100, 100, 2)
