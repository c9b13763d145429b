"""``pidg make-scene`` with Blender (skipped without bpy): one tiny scene per kind, read back by pidg's loader, its
ground truth checked by ``--verify`` (and Blender's own ray cast and camera); velocities converge at second order."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("bpy")

from pidg.data import DataConfig, load_scene  # noqa: E402
from pidg.data.motion_gt import read_motion_gt  # noqa: E402
from pidg.scenes import KINDS, SceneOptions, make_scene  # noqa: E402
from pidg.scenes import blender_build as bb  # noqa: E402
from pidg.scenes.make_scene import collect_geometry  # noqa: E402
from pidg.scenes.verify import velocity_residuals  # noqa: E402

FRAMES = 8
OBJECT_KIND = {"rigid": "rigid", "cloth": "cloth", "soft": "soft", "kinematic": "kinematic"}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Each kind at 48 x 48, 8 images, 2 samples, verified (about a second each on 2 cores)."""
    root = tmp_path_factory.mktemp("scenes")
    options = {k: SceneOptions(k, frames=FRAMES, width=48, height=48, samples=2, denoise=False, points=500, verify=True)
               for k in KINDS}
    return {k: (root / k, make_scene(o, root / k)) for k, o in options.items()}


@pytest.mark.parametrize("kind", KINDS)
def test_scene_reads_back_with_its_ground_truth(scenes, kind):
    root, summary = scenes[kind]
    scene = load_scene(DataConfig(path=root, splits=("train", "val", "test"), progress=False))
    frames = [f for fs in scene.splits.values() for f in fs]
    assert [len(scene.splits[s]) for s in ("train", "val", "test")] == [6, 1, 1]
    assert sorted(f.time for f in frames) == pytest.approx(np.linspace(0, 1, FRAMES))
    assert scene.info["layout"] == "pidg" and scene.info["masks"] and scene.info["depth_maps"]
    assert scene.points3d is not None and 100 < len(scene.points3d.xyz) <= 500
    assert all(f.image.shape == (48, 48, 3) and f.mask is not None and f.mask.any() for f in frames)
    gt = read_motion_gt(root)
    v = gt.vertices
    assert gt.frame_interval == pytest.approx(1 / (FRAMES - 1)) and gt.duration_s == pytest.approx((FRAMES - 1) / 24)
    assert v.positions.shape[0] == FRAMES and v.positions.shape == v.velocities.shape
    assert v.faces.max() < v.positions.shape[1] and len(v.faces) > 100
    assert {o.kind for o in gt.objects} == {OBJECT_KIND[kind]}
    assert sum(o.n_vertices for o in gt.objects) == v.positions.shape[1]
    moved = np.linalg.norm(v.positions[-1] - v.positions[0], axis=-1)
    assert np.median(moved) > 0.05  # the objects really move (world units)
    flows = [gt.frame_flow(f.name) for f in frames]
    assert all(np.isfinite(ff.flow[ff.dynamic]).all() and np.abs(ff.flow[ff.dynamic]).max() > 0.2 for ff in flows)
    assert summary["render"]["engine"] == "CYCLES"


@pytest.mark.parametrize("kind", KINDS)
def test_verify_residuals_are_small(scenes, kind):
    root, summary = scenes[kind]
    report = json.loads((root / "motion_gt" / "verify.json").read_text())
    assert report == json.loads(json.dumps(summary["verify"]))
    flow, counts, blender = report["vertex_flow_px"], report["counts"], report["blender"]
    assert flow["n"] > 100 and flow["median"] < 0.15 and flow["p95"] < 0.5
    assert counts["static_nonzero_flow_px"] == 0 and counts["mask_mismatch_px"] == 0
    assert counts["depth_surface_mismatch_px"] == 0 and counts["images_without_vertex_check"] == 1
    assert counts["alpha_surface_mismatch_fraction"] < 0.03  # the renders' silhouettes: anti-aliased edges only
    assert blender["camera_projection_max_px"] < 0.01
    rays = blender["ray_cast"]
    assert rays["rays"] > 1000 and rays["hit_mismatch"] <= 0.005 * rays["rays"]
    assert rays["dynamic_mismatch"] <= 0.005 * rays["rays"] and rays["depth_p95"] < 1e-4
    if kind != "kinematic":  # 8 frames sample the keyframed path too coarsely; see the convergence test
        assert report["velocity"]["relative_to_median_speed"]["p95"] < 0.1


def test_keyframed_velocities_agree_with_finite_differences_at_second_order():
    """Doubling the frame rate over the same path divides the gap to central differences by about 4."""
    bb.import_bpy()
    gaps = []
    for n in (16, 31):
        built = bb.build_scene("kinematic", n, 0, 24, False)
        geometry, _ = collect_geometry(built, n)
        times = np.linspace(0, 1, n)
        gaps.append(velocity_residuals(times, geometry.positions[:n], geometry.velocities, 1 / (n - 1))["abs"]["median"])
    assert 3.0 < gaps[0] / gaps[1] < 5.0


def test_simulation_sub_frames_interpolate(scenes):
    """Cached physics evaluated half-way between frames lies between them (so sub-frame velocities are meaningful)."""
    for kind in ("rigid", "cloth", "soft"):
        check = read_motion_gt(scenes[kind][0]).meta["subframe_check"]
        assert 0.1 * check["frame_step"] < check["half_vs_frame"] and check["half_vs_linear_midpoint"] < 0.5 * check["frame_step"]


def test_static_camera_keeps_every_training_view(tmp_path):
    options = SceneOptions("rigid", frames=6, width=32, height=32, samples=1, denoise=False, points=200,
                           static_camera=True, verify=True)
    summary = make_scene(options, tmp_path / "static")
    train = json.loads((tmp_path / "static" / "transforms_train.json").read_text())["frames"]
    test = json.loads((tmp_path / "static" / "transforms_test.json").read_text())["frames"]
    assert len(train) == 5 and all(f["transform_matrix"] == train[0]["transform_matrix"] for f in train)
    assert test[0]["transform_matrix"] != train[0]["transform_matrix"]  # held-out views stay novel views
    assert summary["verify"]["counts"]["static_nonzero_flow_px"] == 0
    assert summary["verify"]["blender"]["ray_cast"]["hit_mismatch"] == 0


def test_held_out_on_orbit_changes_the_held_out_views_only(tmp_path):
    """--held-out-on-orbit makes a twin: the same simulation, ground truth and training images (a run trained on one
    is a run trained on the other), its val and test views on the training camera's path at their times."""
    for name, on_orbit in (("off", False), ("on", True)):
        make_scene(SceneOptions("kinematic", frames=8, width=32, height=32, samples=1, denoise=False, points=200,
                                held_out_on_orbit=on_orbit), tmp_path / name)
    off, on = tmp_path / "off", tmp_path / "on"
    a, b = read_motion_gt(off), read_motion_gt(on)
    assert np.array_equal(a.vertices.positions, b.vertices.positions) and np.array_equal(a.vertices.velocities, b.vertices.velocities)
    assert json.loads((off / "transforms_train.json").read_text()) == json.loads((on / "transforms_train.json").read_text())
    scenes = [load_scene(DataConfig(path=p, splits=("train", "test"), progress=False)) for p in (off, on)]
    assert all(torch.equal(f.image_u8, g.image_u8) for f, g in zip(scenes[0].train, scenes[1].train))
    held_off, held_on = scenes[0].test[0], scenes[1].test[0]
    assert held_off.time == held_on.time and not torch.equal(held_off.camera.world_to_camera, held_on.camera.world_to_camera)
    # on the path: its eye between the training eyes of the frames before and after it (the orbit turns ~51 deg a frame)
    before, after = (min(scenes[1].train, key=lambda f, s=s: abs(f.time - held_on.time - s / 7)) for s in (-1, 1))
    eye = lambda f: torch.linalg.inv(f.camera.world_to_camera)[:3, 3]  # noqa: E731
    gap = (eye(before) - eye(after)).norm()
    assert (eye(held_on) - eye(before)).norm() < gap and (eye(held_on) - eye(after)).norm() < gap


def test_the_textures_change_the_surfaces_only(tmp_path):
    """Each texture draws the same random numbers, so the scenes differ in their pixels alone: the same simulation,
    ground-truth motion, cameras and masks (the checker scenes of docs/motion.md's earlier tables stay reproducible)."""
    for texture in bb.TEXTURES:
        make_scene(SceneOptions("rigid", frames=6, width=32, height=32, samples=1, denoise=False, points=200,
                                texture=texture), tmp_path / texture)
    cells, checker = (tmp_path / t for t in ("cells", "checker"))
    a, b = read_motion_gt(cells), read_motion_gt(checker)
    assert np.array_equal(a.vertices.positions, b.vertices.positions) and np.array_equal(a.vertices.velocities, b.vertices.velocities)
    for name in ("transforms_train.json", "transforms_test.json"):
        assert json.loads((cells / name).read_text()) == json.loads((checker / name).read_text())
    scenes = [load_scene(DataConfig(path=p, progress=False)) for p in (cells, checker)]
    for f, g in zip(scenes[0].train, scenes[1].train):
        assert f.mask is not None and g.mask is not None and bool((f.mask == g.mask).all())
        assert float((f.image - g.image).abs()[f.mask.bool()].mean()) > 0.02  # the moving objects look different
