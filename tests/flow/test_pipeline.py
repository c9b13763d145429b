"""End to end on the procedural scene, whose true Gaussians are known: the motion flow decomposed from estimated
optical flow must agree with the Gaussian flow rendered from the true Gaussians at t and t+1. This pins every sign
and grid convention between preprocessing, decomposition and rendering at once."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import torch

import pidg  # noqa: F401
from pidg.data.procedural import (
    ProceduralScene,
    ProceduralSceneConfig,
    composite_rgba,
    write_procedural_dataset,
)
from pidg.data.scene import DataConfig, Frame
from pidg.flow import (
    FlowConfig,
    decode_flows,
    depth_from_render,
    flow_target_for_pair,
    forward_backward_consistency,
    gaussian_flow_features,
    lpfm_loss,
    make_estimator,
    motion_flow_target,
    run_preprocess,
)
from pidg.flow.decomposition import motion_mask_from_flow
from pidg.flow.lpfm import total_flow_target
from pidg.flow.preprocess import FlowPair, preprocess_flow
from pidg.render import Camera, rasterize

pytest.importorskip("cv2")

SLOW_ORBIT = ProceduralSceneConfig(n_train=60, n_test=1, width=128, height=96, n_gaussians=4000, orbit_turns=0.2)


@pytest.fixture(scope="module")
def truth() -> ProceduralScene:
    return ProceduralScene(SLOW_ORBIT)


class ObservedPair(NamedTuple):
    """Two consecutive training views of the true scene (times, cameras, frame t's motion mask) and the optical flow
    estimated between them with its consistency masks, as preprocessing computes it."""

    t1: float
    cam0: Camera
    cam1: Camera
    mask0: np.ndarray
    forward: torch.Tensor
    backward: torch.Tensor
    valid_f: torch.Tensor
    valid_b: torch.Tensor


def observe_pair(truth: ProceduralScene, t0: float) -> ObservedPair:
    t1 = t0 + 1.0 / (SLOW_ORBIT.n_train - 1)
    cam0, cam1 = (truth.camera(truth.camera_to_world("train", t)) for t in (t0, t1))
    (rgba0, mask0), (rgba1, _) = truth.render(t0, cam0), truth.render(t1, cam1)
    image0, image1 = composite_rgba(rgba0, (0.0, 0.0, 0.0)), composite_rgba(rgba1, (0.0, 0.0, 0.0))
    estimator = make_estimator(FlowConfig())
    forward, backward = torch.from_numpy(estimator(image0, image1)), torch.from_numpy(estimator(image1, image0))
    valid_f, valid_b = forward_backward_consistency(forward, backward), forward_backward_consistency(backward, forward)
    return ObservedPair(t1, cam0, cam1, mask0, forward, backward, valid_f, valid_b)


@pytest.mark.parametrize("t0", [0.3, 0.6])
def test_decomposed_flow_matches_true_gaussian_flow(truth: ProceduralScene, t0: float):
    t1, cam0, cam1, mask0, forward, backward, valid_f, valid_b = observe_pair(truth, t0)

    g0, g1 = truth.gaussians(t0), truth.gaussians(t1)
    render1 = rasterize(g1.means, g1.quats, g1.opacities, g1.colors, cam1, scales=g1.scales)
    depth1 = depth_from_render(render1)  # as the trainer passes it
    target = motion_flow_target(depth1, cam0, cam1, forward, backward, valid_f, valid_b,
                                motion_mask0=torch.from_numpy(mask0))

    feats = gaussian_flow_features(cam0, g0.means, g0.quats, g0.scales, g0.opacities, g1.means, g1.quats, g1.scales)
    render0 = rasterize(g0.means, g0.quats, g0.opacities, g0.colors, cam0, scales=g0.scales, features=feats)
    flow_g, flow_v, _ = decode_flows(render0.features, render0.alpha)
    assert flow_v is None

    supervised = target.valid & (render0.alpha > 0.9)
    assert supervised.sum() > 0.8 * mask0.sum()
    motion = target.flow[supervised].norm(dim=-1).mean()
    epe = (flow_g - target.flow).norm(dim=-1)[supervised]
    assert motion > 0.7  # pixels per frame at this resolution
    assert epe.median() < 0.35 * motion  # DIS is good to a few tenths of a pixel here
    # the true motion explains the target far better than no motion
    config = FlowConfig()
    truth_loss = lpfm_loss(flow_g, None, target, render0.alpha, config).loss
    still_loss = lpfm_loss(torch.zeros_like(flow_g), None, target, render0.alpha, config).loss
    assert truth_loss < 0.4 * still_loss
    # a mask derived from the motion flow finds the moving ring
    derived = motion_flow_target(depth1, cam0, cam1, forward, backward, valid_f, valid_b, motion_threshold=0.5)
    ring = torch.from_numpy(mask0)
    assert (derived.valid & ring).sum() > 0.5 * derived.valid.sum()
    assert motion_mask_from_flow(target.flow, target.valid, 0.5).sum() > 0


@pytest.mark.parametrize("t0", [0.3, 0.6])
def test_total_flow_of_the_true_gaussians_matches_the_optical_flow(truth: ProceduralScene, t0: float):
    """FlowConfig.target "total": the true Gaussians at t seen by camera t and at t+1 by camera t+1 render the optical
    flow itself (camera and object motion together), which the estimated flow must match everywhere it is
    consistent, ring and static floor alike; the motion flow (camera t twice) does not match it on static pixels."""
    t1, cam0, cam1, mask0, forward, backward, valid_f, valid_b = observe_pair(truth, t0)
    frame0 = Frame(cam0, t0, torch.zeros(1, 1, 3, dtype=torch.uint8), name="a")
    frame1 = Frame(cam1, t1, torch.zeros(1, 1, 3, dtype=torch.uint8), name="b")
    target = total_flow_target(FlowPair(0, frame0, frame1, forward, backward, valid_f, valid_b), FlowConfig())
    assert torch.equal(target.valid, valid_f)  # no mask on these frames: every consistent pixel

    g0, g1 = truth.gaussians(t0), truth.gaussians(t1)
    total = gaussian_flow_features(cam0, g0.means, g0.quats, g0.scales, g0.opacities, g1.means, g1.quats, g1.scales,
                                   camera_t1=cam1)
    motion = gaussian_flow_features(cam0, g0.means, g0.quats, g0.scales, g0.opacities, g1.means, g1.quats, g1.scales)
    flows = []
    for feats in (total, motion):
        out = rasterize(g0.means, g0.quats, g0.opacities, g0.colors, cam0, scales=g0.scales, features=feats)
        flows.append(decode_flows(out.features, out.alpha)[0])
    supervised = target.valid & (out.alpha > 0.9)
    ring, static = supervised & torch.from_numpy(mask0), supervised & ~torch.from_numpy(mask0)
    assert ring.sum() > 50 and static.sum() > 500
    size = target.flow[supervised].norm(dim=-1).mean()
    assert size > 0.8  # the orbit moves every pixel
    for region in (ring, static):
        epe = (flows[0] - target.flow).norm(dim=-1)[region]
        assert epe.median() < 0.35 * size  # DIS is good to a few tenths of a pixel here (measured 0.14-0.26 px)
    assert (flows[1] - target.flow).norm(dim=-1)[static].median() > 0.5 * size  # the motion flow is not the optical flow


def test_run_preprocess_on_a_dataset_folder(tmp_path: Path):
    root = write_procedural_dataset(replace(SLOW_ORBIT, n_train=5, width=64, height=48, n_gaussians=1500), tmp_path / "scene")
    data = DataConfig(root, progress=False)
    summary = run_preprocess(data, FlowConfig())
    assert summary["pairs"] == 4 and summary["computed"] == 4 and (summary["width"], summary["height"]) == (64, 48)
    assert Path(summary["cache_dir"]) == root / "flow_cache" / "dis_64x48"
    assert (root / "flow_cache" / "dis_64x48" / "index.json").is_file()
    assert summary["valid_forward_fraction"] > 0.3 and summary["median_forward_px"] > 0.0
    assert run_preprocess(data, FlowConfig())["reused"] == 4


def test_flow_target_for_a_cached_pair(tmp_path: Path):
    """The trainer's path: cache -> pair -> target with the dataset's motion mask of frame t."""
    from pidg.data import load_scene

    root = write_procedural_dataset(replace(SLOW_ORBIT, n_train=5, width=64, height=48, n_gaussians=1500), tmp_path / "scene")
    scene = load_scene(DataConfig(root, splits=("train",), progress=False))
    cache = preprocess_flow(scene, FlowConfig(), progress=False)
    pair = cache.pair(0)
    assert pair.frame0.mask is not None
    depth1 = torch.full((48, 64), 3.5)  # any plausible depth: this checks plumbing, not accuracy
    config = FlowConfig(mask_dilation=2)
    target = flow_target_for_pair(pair, depth1, config)
    assert target.flow.shape == (48, 64, 2) and target.valid.dtype == torch.bool
    grown = torch.nn.functional.max_pool2d(pair.frame0.mask.float()[None, None], 5, 1, 2)[0, 0] > 0
    assert not (target.valid & ~grown).any()  # only inside the dilated dataset mask
