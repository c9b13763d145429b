"""The procedural demo scene: determinism, image statistics, motion masks, ground-truth motion, disk round trip."""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

import pidg  # noqa: F401  (before torch is used)
from pidg.data import DataConfig, load_scene
from pidg.data.procedural import (
    BALLS,
    FLOOR_HALF_SIZE,
    FLOOR_Z,
    ProceduralScene,
    ProceduralSceneConfig,
    composite_rgba,
    contact_sheet,
    make_procedural_scene,
    motion_at,
    write_procedural_dataset,
)
from pidg.data.scene import SceneData
from pidg.render import rasterize
from pidg.render.projection import quat_to_rotmat

# Small enough to make in a fraction of a second, big enough to have every split and a visible ring.
SMALL = ProceduralSceneConfig(n_train=8, n_test=3, n_val=2, width=48, height=40, n_gaussians=2500, n_init_points=300)


@pytest.fixture(scope="module")
def default_scene() -> tuple[SceneData, float]:
    # The budget is for generating the scene, not for numba compiling the rasterizer on a cold cache (a fresh
    # clone, as in CI): compile first with a tiny scene of the same kind.
    make_procedural_scene(ProceduralSceneConfig(n_train=2, n_test=1, width=16, height=16, n_gaussians=500, n_init_points=50))
    start = time.perf_counter()
    scene = make_procedural_scene(ProceduralSceneConfig())
    return scene, time.perf_counter() - start


def dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    return F.max_pool2d(mask.float()[None, None], 2 * radius + 1, 1, radius)[0, 0] > 0


def static_only_image(generator: ProceduralScene, frame, background=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """The frame re-rendered without the ring, through the same RGBA -> uint8 -> composite path."""
    g = generator.gaussians(frame.time)
    keep = ~generator.is_dynamic
    with torch.no_grad():
        out = rasterize(
            g.means[keep], g.quats[keep], g.opacities[keep], g.colors[keep], frame.camera,
            scales=g.scales[keep], backend="cpu",
        )
    a = out.alpha.clamp(0, 1).unsqueeze(-1)
    straight = torch.where(a > 1e-6, out.rgb / a.clamp_min(1e-6), 0.0).clamp(0, 1)
    rgba = torch.round(torch.cat([straight, a], dim=-1) * 255).to(torch.uint8).numpy()
    return torch.from_numpy(composite_rgba(rgba, background)).float() / 255


# ---------------------------------------------------------------------------------------------------------------
# default scene: size, speed, what the images show
# ---------------------------------------------------------------------------------------------------------------
def test_default_scene_layout_and_speed(default_scene):
    scene, seconds = default_scene
    assert seconds < 10.0, f"generation took {seconds:.1f} s (budget 5 s on a 2-core CPU, 2x slack for CI)"
    assert set(scene.splits) == {"train", "test"}
    assert (len(scene.train), len(scene.test)) == (60, 20)
    for f in scene.train + scene.test:
        assert f.image_u8.dtype == torch.uint8 and f.image_u8.shape == (128, 128, 3)
        assert f.mask is not None and f.mask.dtype == torch.bool and f.mask.shape == (128, 128)
        assert (f.camera.width, f.camera.height) == (128, 128)
    torch.testing.assert_close(scene.times("train"), torch.arange(60, dtype=torch.float32) / 59)
    train_times, test_times = set(scene.times("train").tolist()), scene.times("test").tolist()
    assert not train_times & set(test_times) and all(0 < t < 1 for t in test_times)
    assert test_times == sorted(test_times) and test_times[-1] - test_times[0] > 0.9  # held-out times span the video
    assert len({f.name for f in scene.train + scene.test}) == 80
    torch.testing.assert_close(scene.background, torch.zeros(3))
    assert scene.points3d is not None and len(scene.points3d) == 2000
    assert scene.bounds.radius > 1.0 and scene.bounds.points_min is not None


def test_ring_visible_masks_plausible_and_images_change(default_scene):
    scene, _ = default_scene
    frames = scene.train + scene.test
    for f in frames:
        frac = f.mask.float().mean().item()
        assert 0.03 < frac < 0.4, f"{f.name}: mask covers {frac:.3f} of the image"
        ys, xs = torch.nonzero(f.mask, as_tuple=True)
        assert ys.min() > 0 and xs.min() > 0 and ys.max() < 127 and xs.max() < 127, f"{f.name}: ring leaves the view"
        image = f.image
        assert image.std() > 0.1  # textured, not flat
        # the ring is colourful (saturated), the floor greyish: the masked pixels are the saturated ones
        sat = image.amax(-1) - image.amin(-1)
        assert sat[f.mask].mean() > sat[~f.mask].mean() + 0.15
    # a monocular video: every consecutive pair of frames differs, the masked part most
    for a, b in zip(scene.train, scene.train[1:]):
        assert (a.image - b.image).abs().mean() > 0.01
        assert not torch.equal(a.mask, b.mask)


def test_motion_mask_is_exactly_where_the_ring_changes_the_image(default_scene):
    scene, _ = default_scene
    generator = ProceduralScene(ProceduralSceneConfig())
    for f in scene.train[::12] + scene.test[::7]:
        diff = (f.image - static_only_image(generator, f)).abs().amax(-1)
        assert (diff[f.mask] > 0.05).float().mean() > 0.95  # inside: the ring, not the floor
        # outside (allowing the 1-pixel antialiased rim below the 50 % coverage threshold): the static scene exactly
        assert diff[~dilate(f.mask, 1)].max() == 0


def test_same_camera_different_time_changes_only_the_ring():
    config = ProceduralSceneConfig(width=64, height=64, n_gaussians=3000)
    gen = ProceduralScene(config)
    camera = gen.camera(gen.camera_to_world("train", 0.0))
    (rgba0, m0), (rgba1, m1) = gen.render(0.0, camera), gen.render(0.3, camera)
    img0, img1 = (torch.from_numpy(composite_rgba(x, (0, 0, 0))).float() / 255 for x in (rgba0, rgba1))
    moving = dilate(torch.from_numpy(m0 | m1), 1)
    assert (img0 - img1).abs()[moving].mean() > 0.1
    assert torch.equal(img0[~moving], img1[~moving])


def test_monocular_camera_moves_between_consecutive_frames(default_scene):
    scene, _ = default_scene
    centres = torch.stack([f.camera.camera_center for f in scene.train])
    steps = (centres[1:] - centres[:-1]).norm(dim=-1)
    assert steps.min() > 0.2  # ~6 degrees of orbit per frame at 3.5 units
    forward = torch.stack([f.camera.world_to_camera[2, :3] for f in scene.train])
    angles = torch.rad2deg(torch.arccos((forward[1:] * forward[:-1]).sum(-1).clamp(-1, 1)))
    assert angles.min() > 3.0
    # one full turn: the views surround the scene
    azimuths = torch.atan2(centres[:, 1], centres[:, 0])
    assert torch.cos(azimuths).min() < -0.95 and torch.cos(azimuths).max() > 0.95
    # test views are novel views, not only novel times: far from the training views just before and after them
    for f in scene.test:
        i = int(f.time * 59)
        near = centres[i : i + 2]
        assert (near - f.camera.camera_center).norm(dim=-1).min() > 1.0


# ---------------------------------------------------------------------------------------------------------------
# determinism and configuration
# ---------------------------------------------------------------------------------------------------------------
def assert_same_scene(a: SceneData, b: SceneData) -> None:
    assert a.splits.keys() == b.splits.keys()
    for split in a.splits:
        for fa, fb in zip(a.frames(split), b.frames(split), strict=True):
            assert fa.name == fb.name and fa.time == fb.time
            assert torch.equal(fa.image_u8, fb.image_u8) and torch.equal(fa.mask, fb.mask)
            assert torch.equal(fa.camera.world_to_camera, fb.camera.world_to_camera)
    assert torch.equal(a.points3d.xyz, b.points3d.xyz) and torch.equal(a.points3d.rgb, b.points3d.rgb)


def test_deterministic_given_seed():
    a, b = make_procedural_scene(SMALL), make_procedural_scene(SMALL)
    assert_same_scene(a, b)
    c = make_procedural_scene(replace(SMALL, seed=1))
    assert not torch.equal(a.train[0].image_u8, c.train[0].image_u8)
    assert not torch.equal(a.points3d.xyz, c.points3d.xyz)


def test_splits_sit_at_distinct_held_out_times():
    scene = make_procedural_scene(SMALL)
    assert [len(scene.frames(s)) for s in ("train", "val", "test")] == [8, 2, 3]
    times = {s: set(scene.times(s).tolist()) for s in scene.splits}
    assert not times["train"] & times["val"] and not times["train"] & times["test"] and not times["val"] & times["test"]
    # frames are numbered on the common time grid: number / max number = time
    for f in scene.train + scene.frames("val") + scene.test:
        assert f.time == pytest.approx(int(f.name.split("_")[-1]) / 14, abs=1e-12)


def test_white_background_and_alpha():
    config = replace(SMALL, background="white")
    scene = make_procedural_scene(config)
    torch.testing.assert_close(scene.background, torch.ones(3))
    corner = scene.train[0].image[0, 0]  # the sky above the floor's far edge
    torch.testing.assert_close(corner, torch.ones(3))


@pytest.mark.parametrize(
    "change",
    [
        {"n_train": 1},
        {"n_test": 0},
        {"n_test": 5, "n_val": 3},  # more held-out frames than gaps between 8 training frames
        {"width": 4},
        {"background": "grey"},
        {"n_gaussians": 10},
        {"motion": 2.0},
        {"init_points": "sfm"},
    ],
)
def test_config_validation(change):
    with pytest.raises(ValueError):
        replace(SMALL, **change)


def test_initial_points():
    surface = make_procedural_scene(SMALL).points3d
    assert surface is not None and surface.rgb is not None and len(surface) == 300
    gen = ProceduralScene(SMALL)
    # "surface": within a few cm of the ground-truth Gaussians at t = 0
    assert torch.cdist(surface.xyz.double(), gen.means).min(dim=1).values.max() < 0.1
    assert torch.equal(surface.rgb, torch.round(surface.rgb * 255) / 255)  # 8-bit, as the PLY stores it
    random = ProceduralScene(replace(SMALL, init_points="random")).initial_points()
    assert random.xyz[:, 2].min() >= FLOOR_Z and random.xyz[:, :2].abs().max() <= 2.0
    assert torch.cdist(random.xyz.double(), gen.means).min(dim=1).values.max() > 0.2


# ---------------------------------------------------------------------------------------------------------------
# ground-truth Gaussians
# ---------------------------------------------------------------------------------------------------------------
def test_deformation_is_identity_at_zero_and_jacobian_is_exact():
    gen = ProceduralScene(SMALL)
    ring = gen.means[gen.is_dynamic]
    pos, jac = gen.deform(ring, 0.0)
    torch.testing.assert_close(pos, ring)
    torch.testing.assert_close(jac, torch.eye(3, dtype=torch.float64).expand_as(jac))
    h = 1e-6
    for t in (0.13, 0.4, 0.77):
        pos, jac = gen.deform(ring, t)
        steps = torch.eye(3, dtype=torch.float64) * h
        fd = torch.stack([(gen.deform(ring + e, t)[0] - gen.deform(ring - e, t)[0]) / (2 * h) for e in steps], dim=-1)
        torch.testing.assert_close(jac, fd, atol=1e-7, rtol=0)
        # the rasterizer's covariance is the pushed-forward one: R S S R^T = J Sigma0 J^T
        g = gen.gaussians(t)
        m = quat_to_rotmat(g.quats.double()) * g.scales.double().unsqueeze(-2)
        m0 = jac @ (gen.rotations[gen.is_dynamic] * gen.scales[gen.is_dynamic].unsqueeze(-2))
        torch.testing.assert_close((m @ m.mT)[gen.is_dynamic], m0 @ m0.mT, atol=1e-9, rtol=1e-4)
        # static Gaussians do not move
        assert torch.equal(g.means[~gen.is_dynamic], gen.means[~gen.is_dynamic].float())


def test_ring_moves_smoothly_stays_above_floor_and_motion_zero_is_static():
    gen = ProceduralScene(SMALL)
    previous = None
    for t in np.linspace(0, 1, 61):
        ring = gen.gaussians(float(t)).means[gen.is_dynamic]
        assert ring[:, 2].min() > FLOOR_Z
        if previous is not None:  # a few pixels per training frame at most
            assert (ring - previous).norm(dim=-1).max() < 0.1
        previous = ring
    mo = motion_at(0.2)
    assert mo.bend != 0 and mo.squash != 1 and mo.spin != 0 and any(mo.offset)
    still = ProceduralScene(replace(SMALL, motion=0.0))
    torch.testing.assert_close(still.gaussians(0.6).means, still.gaussians(0.0).means)


# ---------------------------------------------------------------------------------------------------------------
# disk round trip
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("background", ["black", "white"])
def test_write_and_load_round_trip(tmp_path, background, caplog):
    config = replace(SMALL, background=background)
    memory = make_procedural_scene(config)
    root = write_procedural_dataset(config, tmp_path / "scene")
    assert root == tmp_path / "scene"
    meta = json.loads((root / "transforms_train.json").read_text())
    assert meta["camera_angle_x"] == pytest.approx(math.radians(config.fov_x_deg))
    assert {"file_path", "time", "transform_matrix"} <= set(meta["frames"][0])
    assert (root / "points3d.ply").is_file() and (root / "mask" / "r_0000.png").is_file()
    assert Image.open(root / "train" / "r_0000.png").mode == "RGBA"

    with caplog.at_level("WARNING"):
        disk = load_scene(DataConfig(root, background=background, splits=("train", "val", "test"), progress=False))
    assert not [r for r in caplog.records if r.levelname == "WARNING"]  # json times agree with frame numbers
    assert disk.time_source == "json" and disk.info["masks"] is True
    for split in ("train", "val", "test"):
        for fm, fd in zip(memory.frames(split), disk.frames(split), strict=True):
            assert fd.name == fm.name and fd.time == fm.time
            torch.testing.assert_close(fd.camera.world_to_camera, fm.camera.world_to_camera, atol=1e-5, rtol=0)
            assert (fd.camera.fx, fd.camera.fy, fd.camera.cx, fd.camera.cy) == pytest.approx(
                (fm.camera.fx, fm.camera.fy, fm.camera.cx, fm.camera.cy)
            )
            assert (fd.image_u8.int() - fm.image_u8.int()).abs().max() <= 1
            assert torch.equal(fd.mask, fm.mask)
            assert fd.depth is not None and fm.depth is not None and torch.equal(fd.depth, fm.depth)
    assert disk.info["depth_maps"] is True
    torch.testing.assert_close(disk.points3d.xyz, memory.points3d.xyz)
    torch.testing.assert_close(disk.points3d.rgb, memory.points3d.rgb)
    torch.testing.assert_close(disk.bounds.center, memory.bounds.center)
    assert disk.bounds.radius == pytest.approx(memory.bounds.radius)
    torch.testing.assert_close(disk.background, memory.background)


def test_depth_maps_are_camera_z_of_the_floor_where_only_the_floor_is_seen():
    """Independent check: on pixels whose ray meets the floor away from the balls and the ring, the stored depth is
    the camera z of the ray's intersection with the plane z = FLOOR_Z, to the splats' own spread."""
    config = ProceduralSceneConfig(n_train=4, n_test=1, width=64, height=64, n_init_points=50)
    scene = make_procedural_scene(config)
    generator = ProceduralScene(config)
    balls = torch.tensor([[x, y, FLOOR_Z + r, r] for (x, y), r in BALLS], dtype=torch.float64)
    checked = 0
    for frame in scene.train + scene.test:
        cam = frame.camera
        assert frame.depth is not None and frame.depth.shape == (cam.height, cam.width)
        assert frame.depth.dtype == torch.float32 and (frame.depth >= 0).all()
        v, u = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64) + 0.5,
                              torch.arange(cam.width, dtype=torch.float64) + 0.5, indexing="ij")
        dirs_cam = torch.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, torch.ones_like(u)], dim=-1)  # z = 1
        w2c = cam.world_to_camera.to(torch.float64)
        dirs = dirs_cam @ w2c[:3, :3]  # world direction per unit of camera z
        origin = cam.camera_center.to(torch.float64)
        z_plane = (FLOOR_Z - origin[2]) / dirs[..., 2]  # camera z where the ray meets the floor plane
        hit = origin + z_plane.unsqueeze(-1) * dirs
        inside = (z_plane > 0) & (hit[..., :2].abs() < FLOOR_HALF_SIZE - 0.3).all(-1)
        # rays that pass within a margin of a ball (closest approach to its centre) are left out
        for bx, by, bz, r in balls.tolist():
            c = torch.tensor([bx, by, bz], dtype=torch.float64) - origin
            unit = dirs / dirs.norm(dim=-1, keepdim=True)
            miss = (torch.cross(unit, c.expand_as(unit), dim=-1)).norm(dim=-1)
            inside &= miss > r + 0.15
        ring = generator.ring_positions(frame.time)
        uv, _ = cam.project_points(ring)
        near_ring = torch.zeros(cam.height, cam.width, dtype=torch.bool)
        px = uv.floor().long()
        ok = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        near_ring[px[ok, 1], px[ok, 0]] = True
        floor_only = inside & ~dilate(near_ring, 4)
        assert floor_only.sum() > 100
        expected = z_plane[floor_only]
        # Expected depth of splats, not of the plane: splats nearer the camera cover more of a pixel, which puts the
        # floor 1.6-3.1 % nearer than the plane (measured); a ray length instead of camera z would be 10-20 % off at
        # the corners, a missing alpha normalisation far more.
        rel = (frame.depth[floor_only].double() - expected) / expected
        assert rel.abs().max() < 0.04, rel.abs().max()
        checked += int(floor_only.sum())
        assert (frame.depth[frame.mask] > 0).all()  # the ring is opaque where it is seen
    assert checked > 1000


def test_contact_sheet_shape():
    scene = make_procedural_scene(SMALL)
    sheet = contact_sheet(scene.train[:5], columns=3)
    assert sheet.shape == (4 * (40 + 2) + 2, 3 * (48 + 2) + 2, 3)
    assert 0 <= sheet.min() and sheet.max() <= 1
