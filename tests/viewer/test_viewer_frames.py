"""What the viewer shows, without a server: the browser's pose -> a pidg camera, every view mode's picture, the
progressive-quality sizes and the frame-time measurement."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import numpy as np
import pytest
import torch

from pidg.cli import main
from pidg.evaluation.images import to_uint8
from pidg.export import open_run_model
from pidg.render import Camera
from pidg.render.projection import quat_to_rotmat, rotmat_to_quat
from pidg.viewer import Quality, ViewRenderer, camera_from_pose, pose_of_camera, view_modes
from pidg.viewer.frames import COLOUR, DEPTH, SPLIT, STRESS, VELOCITY_ARROWS, VELOCITY_COLOURS
from pidg.viewer.server import cameras_focus, training_views


def test_a_camera_survives_the_trip_through_a_viser_pose():
    camera = Camera.look_at((1.0, -3.0, 2.0), (0.1, 0.2, 0.3), (0.0, 0.0, 1.0), 64, 48, math.radians(55))
    wxyz, position = pose_of_camera(camera)
    again = camera_from_pose(wxyz, position, camera.fov_y, 64, 48)
    torch.testing.assert_close(again.world_to_camera, camera.world_to_camera, atol=1e-5, rtol=0)
    assert (again.fx, again.fy, again.cx, again.cy) == pytest.approx((camera.fx, camera.fy, camera.cx, camera.cy))
    np.testing.assert_allclose(position, camera.camera_center.numpy(), atol=1e-5)
    # quaternions (the viewer uses pidg's pair): every branch of the matrix -> quaternion conversion
    for angle, axis in ((0.3, (1, 0, 0)), (3.1, (1, 0, 0)), (3.1, (0, 1, 0)), (3.1, (0, 0, 1)), (2.0, (1, 2, 3))):
        axis = np.array(axis, float) / np.linalg.norm(axis)
        q = torch.tensor(np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis]))
        np.testing.assert_allclose(rotmat_to_quat(quat_to_rotmat(q[None]))[0].numpy(), q.numpy(), atol=1e-9)


def test_previews_are_a_fraction_of_the_canvas_and_full_frames_are_capped():
    quality = Quality(preview_scale=0.25, max_side=1600)
    assert quality.size(800, 800, full=True) == (800, 800)
    assert quality.size(800, 800, full=False) == (200, 200)
    assert quality.size(3200, 1600, full=True) == (1600, 800)
    assert quality.size(40, 30, full=False) == (16, 16)  # never below 16 px a side
    with pytest.raises(ValueError, match="preview scale 2: must be in"):
        Quality(preview_scale=2.0)


def test_every_view_mode_renders_and_colour_is_the_models_render(viewer_run):
    model = open_run_model(viewer_run, "cpu")
    renderer = ViewRenderer(model)
    assert renderer.modes == view_modes(model) == [COLOUR, DEPTH, VELOCITY_ARROWS, VELOCITY_COLOURS, STRESS, SPLIT]
    camera = training_views(viewer_run)[0].camera.resized(64, 48)
    pictures = {}
    for mode in renderer.modes:
        view = renderer.render(camera, 0.4, mode)
        assert view.image.shape == (48, 64, 3) and view.image.dtype == np.uint8 and view.render_ms > 0
        assert view.image.std() > 0, mode  # something is drawn
        pictures[mode] = view
    with torch.no_grad():
        expected = to_uint8(model.render(camera, 0.4).rgb)
    np.testing.assert_array_equal(pictures[COLOUR].image, expected)
    assert "px per training frame" in pictures[VELOCITY_ARROWS].caption and "world units" in pictures[DEPTH].caption
    # the stress colour scale is fixed for the session: the same at another time
    assert f"{renderer.stress_scale:.3g}" in pictures[STRESS].caption
    assert f"{renderer.stress_scale:.3g}" in renderer.render(camera, 0.9, STRESS).caption
    with pytest.raises(ValueError, match="view mode 'normals'"):
        renderer.render(camera, 0.4, "normals")


def test_training_cameras_come_from_the_runs_dataset_and_look_at_one_point(viewer_run):
    views = training_views(viewer_run)
    assert len(views) == 6 and views[0].time == 0.0 and views[-1].time == 1.0
    focus = cameras_focus([v.camera for v in views])
    assert focus is not None and np.linalg.norm(focus) < 1.0  # the procedural orbit looks near the origin


def test_cli_view_measure_prints_frame_times_without_a_server(viewer_run, capsys):
    assert main(["view", str(viewer_run), "--measure", "64x48", "--repeats", "1", "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "full 64x48:" in out and "preview 16x16:" in out and "ms while the camera moves" in out
