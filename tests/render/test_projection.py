"""EWA projection against independent computations: pinhole formula, autograd Jacobian, Monte Carlo."""
import math

import torch

from pidg.render.camera import Camera
from pidg.render.projection import (
    ALPHA_MIN, EPS2D, covariance_3d, project_gaussians, quat_to_rotmat, rotate_by_inverse, rotmat_to_quat,
)
from pidg.render.scenes import orbit_camera, random_scene


def pinhole(camera: Camera, points: torch.Tensor) -> torch.Tensor:
    """World points -> pixel coordinates, written independently of the projection module."""
    w2c = camera.world_to_camera.to(points.dtype)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    k = camera.intrinsics.to(points.dtype)
    uvw = p @ k.T
    return uvw[..., :2] / uvw[..., 2:3]


def test_rotation_matrix_is_orthonormal_and_matches_axis_angle():
    q = torch.randn(50, 4, dtype=torch.float64)
    r = quat_to_rotmat(q)
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(50, dtype=torch.float64))
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45) maps x -> y
    rz = quat_to_rotmat(torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]], dtype=torch.float64))[0]
    assert torch.allclose(rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)


def test_rotate_by_inverse_matches_transposed_rotation_matrix():
    g = torch.Generator().manual_seed(3)
    q = torch.randn(64, 4, generator=g, dtype=torch.float64) * 3.0  # unnormalised on purpose
    v = torch.randn(64, 3, generator=g, dtype=torch.float64)
    expected = (quat_to_rotmat(q).transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(rotate_by_inverse(q, v), expected, atol=1e-12)


def test_means_and_covariance_match_pinhole_jacobian():
    camera = Camera(orbit_camera(64, 48, azimuth_deg=20).world_to_camera, 50.0, 55.0, 30.0, 26.0, 64, 48)
    scene = random_scene(40, camera, extent=0.5, dtype=torch.float64, seed=1)
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    assert torch.allclose(proj.means2d, pinhole(camera, scene.means), atol=1e-9)
    cov3d = covariance_3d(scene.quats, scene.scales)
    for i in range(scene.means.shape[0]):
        jac = torch.autograd.functional.jacobian(lambda p: pinhole(camera, p[None])[0], scene.means[i])
        expected = jac @ cov3d[i] @ jac.T + EPS2D * torch.eye(2, dtype=torch.float64)
        got = torch.tensor([[proj.cov2d[i, 0], proj.cov2d[i, 1]], [proj.cov2d[i, 1], proj.cov2d[i, 2]]], dtype=torch.float64)
        assert torch.allclose(got, expected, rtol=1e-9, atol=1e-9)
        conic = torch.tensor([[proj.conics[i, 0], proj.conics[i, 1]], [proj.conics[i, 1], proj.conics[i, 2]]], dtype=torch.float64)
        assert torch.allclose(conic @ got, torch.eye(2, dtype=torch.float64), atol=1e-9)


def test_covariance_matches_monte_carlo_for_a_small_gaussian():
    """Sample the 3D Gaussian, project the samples exactly: their covariance is the EWA estimate."""
    camera = orbit_camera(200, 150)
    mean = torch.tensor([[0.2, -0.1, 0.3]], dtype=torch.float64)
    quat = torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=torch.float64)
    scale = torch.tensor([[0.02, 0.005, 0.01]], dtype=torch.float64)
    proj = project_gaussians(mean, quat, scale, torch.tensor([0.9], dtype=torch.float64), camera, eps2d=0.0)
    gen = torch.Generator().manual_seed(0)
    chol = quat_to_rotmat(quat)[0] * scale[0]
    samples = mean + torch.randn(200_000, 3, generator=gen, dtype=torch.float64) @ chol.T
    px = pinhole(camera, samples)
    emp = torch.cov(px.T)
    got = torch.tensor([[proj.cov2d[0, 0], proj.cov2d[0, 1]], [proj.cov2d[0, 1], proj.cov2d[0, 2]]], dtype=torch.float64)
    assert torch.allclose(emp, got, rtol=0.02, atol=0.02 * got.abs().max().item())


def test_radii_bound_every_visible_contribution():
    """Brute force over all pixels: alpha >= 1/255 only inside mean +- radii."""
    camera = orbit_camera(60, 44)
    scene = random_scene(60, camera, pixel_sigma=(0.3, 12.0), dtype=torch.float64, seed=2)
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    ys, xs = torch.meshgrid(torch.arange(44, dtype=torch.float64) + 0.5, torch.arange(60, dtype=torch.float64) + 0.5, indexing="ij")
    for i in torch.nonzero(proj.visible).flatten().tolist():
        dx, dy = proj.means2d[i, 0] - xs, proj.means2d[i, 1] - ys
        a, b, c = proj.conics[i]
        alpha = scene.opacities[i] * torch.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy)
        inside = (dx.abs() <= proj.radii[i, 0]) & (dy.abs() <= proj.radii[i, 1])
        assert not ((alpha >= ALPHA_MIN) & ~inside).any()
        # and the bound is tight: the ellipse reaches within a pixel of the box edge
        assert proj.radii[i].max() <= 3.4 * math.sqrt(max(proj.cov2d[i, 0], proj.cov2d[i, 2])) + 1


def test_culling():
    camera = Camera.look_at((0, 0, 0), (0, 0, 1), (0, -1, 0), 40, 30, math.radians(60), near=0.1, far=10.0)
    means = torch.tensor([[0.0, 0, -2], [0, 0, 0.05], [0, 0, 20], [100, 0, 2], [0, 0, 2], [0, 0, 2]])
    opac = torch.tensor([0.9, 0.9, 0.9, 0.9, 0.9, 0.002])
    proj = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).expand(6, 4), torch.full((6, 3), 0.05), opac, camera)
    assert proj.visible.tolist() == [False, False, False, False, True, False]
    assert torch.isfinite(proj.means2d).all() and torch.isfinite(proj.conics).all()


def test_rotmat_to_quat_round_trip():
    q = torch.randn(500, 4, dtype=torch.float64)
    q = torch.cat([q, torch.tensor([[0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]], dtype=torch.float64)])
    r = quat_to_rotmat(q)
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(r)), r, atol=1e-10, rtol=0)
