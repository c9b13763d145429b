"""Camera conventions and the spherical-harmonics basis."""
import math

import pytest
import torch

from pidg.render.camera import Camera
from pidg.render.sh import rgb_to_sh_dc, sh_basis, sh_to_rgb


def test_blender_camera_convention():
    """An OpenGL camera-to-world matrix: the centre is its translation, -z (GL) is forward and +y is up."""
    angle = 0.7
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    cam = Camera.from_fov(c2w, 80, 60, fov_x=math.radians(70))
    assert torch.allclose(cam.camera_center.double(), c2w[:3, 3], atol=1e-6)
    ahead = c2w @ torch.tensor([0.0, 0.0, -2.0, 1.0], dtype=torch.float64)  # 2 units in front (GL looks along -z)
    up = c2w @ torch.tensor([0.0, 0.5, -2.0, 1.0], dtype=torch.float64)
    w2c = cam.world_to_camera.double()
    p, q = w2c @ ahead, w2c @ up
    assert p[2] == pytest.approx(2.0, abs=1e-6) and q[2] == pytest.approx(2.0, abs=1e-6)
    u = cam.fx * p[0] / p[2] + cam.cx
    v_up = cam.fy * q[1] / q[2] + cam.cy
    assert u == pytest.approx(40.0, abs=1e-4) and v_up < 30.0  # centred; "up" is towards the top row
    assert cam.fov_x == pytest.approx(math.radians(70))
    assert cam.fov_y == pytest.approx(2 * math.atan(math.tan(math.radians(35)) * 60 / 80))


def test_resize_and_errors():
    cam = Camera.look_at((0, 0, -3), (0, 0, 0), (0, -1, 0), 100, 50, 1.0)
    small = cam.resized(50, 25)
    assert small.fx == pytest.approx(cam.fx / 2) and small.cx == pytest.approx(25.0) and small.fov_x == pytest.approx(cam.fov_x)
    bad = torch.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="not a rotation"):
        Camera(bad, 10, 10, 5, 5, 10, 10)
    with pytest.raises(ValueError, match="NaN"):
        Camera(torch.full((4, 4), float("nan")), 10, 10, 5, 5, 10, 10)
    with pytest.raises(ValueError, match="near"):
        Camera(torch.eye(4), 10, 10, 5, 5, 10, 10, near=1.0, far=0.5)


def test_viewing_direction_points_from_the_eye_to_the_target():
    cam = Camera.look_at((1.0, 2.0, 3.0), (1.0, 2.0 + 3.0, 3.0 - 4.0), (0, 0, 1), 32, 32, 1.0)
    assert torch.allclose(cam.viewing_direction, torch.tensor([0.0, 0.6, -0.8]), atol=1e-6)
    depth = cam.project_points(torch.tensor([[1.0, 5.0, -1.0]]))[1]  # the target: on the axis, 5 units away
    assert float(depth[0]) == pytest.approx(5.0, rel=1e-5)


def test_sh_basis_is_orthonormal():
    """Quadrature over the sphere: the 16 basis functions are orthonormal (an independent check of constants)."""
    n_t, n_p = 200, 400
    theta = (torch.arange(n_t, dtype=torch.float64) + 0.5) * math.pi / n_t
    phi = (torch.arange(n_p, dtype=torch.float64) + 0.5) * 2 * math.pi / n_p
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    dirs = torch.stack([torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)], dim=-1).reshape(-1, 3)
    weights = (torch.sin(t) * (math.pi / n_t) * (2 * math.pi / n_p)).reshape(-1)
    basis = sh_basis(3, dirs)
    gram = (basis * weights[:, None]).T @ basis
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-4)


def test_sh_colour_conventions():
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    coeffs = torch.zeros(1, 16, 3)
    coeffs[:, 0] = rgb_to_sh_dc(rgb)
    assert torch.allclose(sh_to_rgb(coeffs, torch.tensor([[0.3, -2.0, 1.0]]), 3), rgb, atol=1e-6)
    # degree 1 uses the 3DGS sign convention: -C1*y, C1*z, -C1*x
    coeffs[:, 1:4] = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    out = sh_to_rgb(coeffs, torch.tensor([[1.0, 0.0, 0.0]]), 1)
    assert torch.allclose(out, rgb + torch.tensor([[0.0, 0.0, -0.4886025]]), atol=1e-6)
    with pytest.raises(ValueError):
        sh_to_rgb(torch.zeros(1, 4, 3), torch.ones(1, 3), 2)


def test_project_points_matches_intrinsics():
    cam = Camera.look_at((0, 0, -3), (0, 0, 0), (0, -1, 0), 64, 48, 1.0)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.25, 1.0]])
    uv, z = cam.project_points(pts)
    p = pts @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    expected = (p @ cam.intrinsics.T)[:, :2] / p[:, 2:3]
    assert torch.allclose(uv, expected, atol=1e-5) and torch.allclose(z, p[:, 2])
    assert torch.allclose(uv[0], torch.tensor([32.0, 24.0]), atol=1e-5)
