"""The ground-truth maths of ``pidg make-scene`` without bpy: ray casting, flow, velocities, surface samples, the
capture schedule and the verifier, against closed forms; and the command's one-line errors (bpy absent too)."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from pidg.cli import main
from pidg.scenes import SceneOptions
from pidg.scenes.capture import HELD_OUT_AZIMUTH_DEG, Orbit, Shot, look_at_gl, pidg_camera, shot_list
from pidg.scenes.ground_truth import (
    Triangles,
    cast_rays,
    central_difference,
    interior_finite_differences,
    object_motion_flow,
    sample_surface,
)
from pidg.scenes.verify import bilinear, vertex_residuals

W, H = 48, 40


def _camera(elevation_deg: float = 35.0, azimuth_deg: float = 20.0):
    c2w = look_at_gl((0.0, 0.0, 0.0), 4.0, math.radians(azimuth_deg), math.radians(elevation_deg))
    return pidg_camera(c2w, W, H, math.radians(45.0))


def _pixel_rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """World origin [3] and directions [H, W, 3] through the pixel centres, written out independently of the caster."""
    w2c = camera.world_to_camera.to(torch.float64).numpy()
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(j - camera.cx) / camera.fx, (i - camera.cy) / camera.fy, np.ones_like(j)], axis=-1)
    return -rot.T @ trans, d_cam @ rot


def _plane_hits(camera, height: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed form: where each pixel ray meets the plane z = height, and its camera z (NaN for no forward hit)."""
    origin, d = _pixel_rays(camera)
    s = (height - origin[2]) / d[..., 2]
    s = np.where(s > 0, s, np.nan)
    return origin + s[..., None] * d, s  # d has camera z = 1, so s is the camera depth


def _floor(half: float, height: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-half, -half, height], [half, -half, height], [half, half, height], [-half, half, height]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_rays_meet_a_plane_where_the_closed_form_says():
    camera = _camera()
    v, f = _floor(50.0)  # reaches behind the camera: those triangles take the whole-image path
    hits = cast_rays(camera, Triangles(v, f, np.zeros(2, bool)))
    point, depth = _plane_hits(camera)
    assert np.array_equal(hits.surface, np.isfinite(depth))  # the horizon: rays above it see nothing
    assert hits.surface.mean() > 0.5
    np.testing.assert_allclose(hits.depth[hits.surface], depth[hits.surface], rtol=1e-6)
    assert (hits.depth[~hits.surface] == 0).all()
    recon = np.einsum("hwk,hwkc->hwc", hits.bary, v[f[np.maximum(hits.face, 0)]])
    np.testing.assert_allclose(recon[hits.surface], point[hits.surface], atol=1e-5)


def test_rays_find_a_small_triangle_and_the_nearest_of_two():
    camera = _camera()
    tri = np.array([[-0.6, -0.5, 0.0], [0.7, -0.4, 0.0], [0.0, 0.8, 0.0]])
    point, _ = _plane_hits(camera)
    # closed-form inside test in the plane
    a, b, c = tri
    def side(p, q, r):
        return (q[0] - p[0]) * (r[..., 1] - p[1]) - (q[1] - p[1]) * (r[..., 0] - p[0])
    inside = (side(a, b, point) > 0) & (side(b, c, point) > 0) & (side(c, a, point) > 0)
    hits = cast_rays(camera, Triangles(tri, np.array([[0, 1, 2]]), np.zeros(1, bool)))
    assert inside.sum() > 50
    assert np.array_equal(hits.surface, inside)
    # a copy lifted by 0.3 towards the camera hides the first one where it covers it
    two = np.concatenate([tri, tri + [0.0, 0.0, 0.3]])
    hits2 = cast_rays(camera, Triangles(two, np.array([[0, 1, 2], [3, 4, 5]]), np.array([False, True])))
    lifted, _ = _plane_hits(camera, 0.3)
    over = (side(a, b, lifted) > 0) & (side(b, c, lifted) > 0) & (side(c, a, lifted) > 0)
    assert (hits2.face[over] == 1).all() and over.sum() > 50
    assert (hits2.face[inside & ~over] == 0).all()


def test_flow_of_a_moving_triangle_is_the_projected_displacement():
    camera = _camera()
    floor_v, floor_f = _floor(3.0)
    tri = np.array([[-0.6, -0.5, 0.2], [0.7, -0.4, 0.2], [0.0, 0.8, 0.2]])
    vertices = np.concatenate([floor_v, tri])
    faces = np.concatenate([floor_f, [[4, 5, 6]]])
    scene = Triangles(vertices, faces, np.array([False, False, True]))
    shift = np.array([0.05, -0.08, 0.03])
    moved = vertices.copy()
    moved[4:] += shift
    flow, dynamic, hits = object_motion_flow(camera, scene, moved)
    p, _ = _plane_hits(camera, 0.2)
    w2c = camera.world_to_camera.to(torch.float64).numpy()

    def project(x):  # pinhole written out, not Camera.project_points
        c = x @ w2c[:3, :3].T + w2c[:3, 3]
        return np.stack([camera.fx * c[..., 0] / c[..., 2] + camera.cx, camera.fy * c[..., 1] / c[..., 2] + camera.cy], -1)

    expected = project(p + shift) - project(p)
    assert dynamic.sum() > 50 and np.array_equal(dynamic, hits.face == 2)
    np.testing.assert_allclose(flow[dynamic], expected[dynamic], atol=2e-4)
    static = hits.surface & ~dynamic
    assert static.sum() > 100 and (flow[static] == 0).all()  # exactly 0 on static surfaces
    assert np.isnan(flow[~hits.surface]).all()
    assert np.abs(flow[dynamic]).max() > 0.3


def test_central_difference_is_second_order():
    t = 0.3
    exact = 3 * np.cos(3 * t)
    errors = [abs(float(central_difference(np.sin(3 * (t - h)), np.sin(3 * (t + h)), h)) - exact) for h in (0.02, 0.01)]
    assert 3.6 < errors[0] / errors[1] < 4.4
    # a quadratic is differentiated exactly, also on a grid
    times = np.linspace(0, 1, 11)
    x = (2.0 * times**2 - times)[:, None, None] * np.ones((1, 2, 3))
    np.testing.assert_allclose(interior_finite_differences(times, x), (4.0 * times[1:-1] - 1)[:, None, None] * np.ones((1, 2, 3)))


def test_surface_samples_lie_on_the_triangles_in_proportion_to_area():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 1, 1.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 1.5
    points, face = sample_surface(v, f, 4000, np.random.default_rng(0))
    assert abs((face == 1).mean() - 0.75) < 0.03
    for k, (a, b, c) in enumerate(v[f]):
        p = points[face == k]
        m = np.stack([b - a, c - a], axis=1)[:2]
        uv = np.linalg.solve(m, (p - a)[:, :2].T).T
        assert (uv >= -1e-9).all() and (uv.sum(axis=1) <= 1 + 1e-9).all()
        np.testing.assert_allclose(p[:, 2], a[2])


def test_shots_interleave_splits_on_one_time_grid():
    shots = shot_list(60)
    assert [s.time for s in shots] == pytest.approx(np.linspace(0, 1, 60))
    assert shots[0].split == shots[-1].split == "train"
    held = [s for s in shots if s.split != "train"]
    assert {s.split for s in held} == {"test", "val"} and all(s.index % 4 == 2 for s in held)
    assert sum(s.split == "test" for s in shots) == 8 and sum(s.split == "val" for s in shots) == 7
    assert len({s.file_name for s in shots}) == 60
    assert [s.split for s in shot_list(4)] == ["train", "train", "test", "train"]
    with pytest.raises(ValueError, match="at least 4"):
        shot_list(3)


@pytest.mark.parametrize("split", ["train", "test", "val"])
def test_orbit_cameras_look_at_the_target(split):
    orbit = Orbit(target=(0.1, -0.2, 0.5), radius=5.0, azimuth0_deg=40.0)
    shot = [s for s in shot_list(20) if s.split == split][1]
    c2w = orbit.camera_to_world(shot)
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    camera = pidg_camera(c2w, W, H, 0.8)
    uv, z = camera.project_points(torch.tensor([orbit.target], dtype=torch.float64))
    np.testing.assert_allclose(uv[0].numpy(), [W / 2, H / 2], atol=1e-4)
    assert z.item() == pytest.approx(5.0, rel=1e-6)
    static = Orbit(target=(0, 0, 0), radius=5.0, static=True)
    train = [s for s in shot_list(20) if s.split == "train"]
    np.testing.assert_allclose(static.camera_to_world(train[0]), static.camera_to_world(train[-1]))


def test_held_out_views_on_the_orbit_are_where_the_training_camera_is_at_their_time():
    """--held-out-on-orbit: a held-out view's camera is the training camera's at its time (novel times only); by
    default it is 30 degrees of azimuth round the orbit from there (novel views too)."""
    on = Orbit(target=(0.1, -0.2, 0.5), radius=5.0, azimuth0_deg=40.0, held_out_on_orbit=True)
    off = Orbit(target=(0.1, -0.2, 0.5), radius=5.0, azimuth0_deg=40.0)
    shots = shot_list(20)
    for shot in shots:
        as_training = Shot(shot.index, shot.time, "train")
        np.testing.assert_array_equal(on.camera_to_world(shot), off.camera_to_world(as_training))
        if shot.split == "train":
            np.testing.assert_array_equal(on.camera_to_world(shot), off.camera_to_world(shot))
            continue
        # the eyes' bearings round the target, seen from above: the default's is the azimuth offset further on
        a, b = (o.camera_to_world(shot)[:2, 3] - np.array(o.target[:2]) for o in (off, on))
        turn = math.degrees(math.atan2(b[0] * a[1] - b[1] * a[0], b @ a))
        assert turn == pytest.approx(HELD_OUT_AZIMUTH_DEG[shot.split], abs=1e-9)


def test_bilinear_is_exact_on_linear_fields():
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    image = np.stack([2 * j - i, 0.5 * i + 3], axis=-1)
    uv = np.array([[3.2, 4.7], [10.5, 20.5], [40.1, 30.9]])
    values, taps, inside = bilinear(image, uv)
    np.testing.assert_allclose(values, np.stack([2 * uv[:, 0] - uv[:, 1], 0.5 * uv[:, 1] + 3], -1))
    assert inside.all() and taps.shape == (3, 4)
    assert not bilinear(image, np.array([[0.2, 5.0]]))[2][0]


def test_verifier_finds_the_flow_of_visible_vertices():
    """A dense moving grid's vertices, projected with pidg's camera, agree with the flow made from its faces; an
    occluded one is left out; a wrong flow is caught."""
    camera = _camera()
    n = 21
    g = np.linspace(-0.8, 0.8, n)
    x, y = np.meshgrid(g, g)
    grid = np.stack([x.ravel(), y.ravel(), np.full(n * n, 0.3)], axis=-1)
    quads = [(r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c) for r in range(n - 1) for c in range(n - 1)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    scene = Triangles(grid, faces, np.ones(len(faces), bool))
    moved = grid + [0.04, 0.02, -0.01]
    flow, dynamic, hits = object_motion_flow(camera, scene, moved)
    err, depth_err = vertex_residuals(camera, flow, dynamic, hits.depth, grid, moved)
    assert len(err) > 200
    assert np.median(err) < 1e-4 and err.max() < 1e-3 and depth_err.max() < 2e-3  # depth is not linear in pixels
    hidden = grid - [0.0, 0.0, 0.2]  # below the grid: its depth disagrees, so it is not "visible"
    assert len(vertex_residuals(camera, flow, dynamic, hits.depth, hidden, hidden + 0.01)[0]) == 0
    wrong, _ = vertex_residuals(camera, flow * 1.5, dynamic, hits.depth, grid, moved)
    assert np.median(wrong) > 0.1


def test_make_scene_without_bpy_says_what_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "bpy", None)  # import bpy now raises ImportError
    out = tmp_path / "scene"
    assert main(["make-scene", "rigid", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'pip install -e ".[scenes]"' in err
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--resolution", "200"], "--resolution '200': give WIDTHxHEIGHT"),
    (["--resolution", "8x8"], "each side must be 16-4096"),
    (["--frames", "3"], "--frames 3"),
])
def test_make_scene_rejects_bad_options_in_one_line(tmp_path, capsys, args, message):
    assert main(["make-scene", "cloth", "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err


def test_scene_options_name_an_unknown_texture():
    with pytest.raises(ValueError, match="--texture 'stripes': choose one of cells, checker"):
        SceneOptions("rigid", texture="stripes")


def test_make_scene_refuses_an_existing_folder(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["make-scene", "soft", "--out", str(tmp_path)]) == 2
    assert "already exists; give --overwrite" in capsys.readouterr().err
    assert main(["make-scene", "soft", "--out", str(tmp_path), "--overwrite"]) == 2  # not a make-scene output
    assert "replaces only" in capsys.readouterr().err and (tmp_path / "keep.txt").is_file()
    with pytest.raises(SystemExit):
        main(["make-scene", "fluid", "--out", str(tmp_path / "y")])
