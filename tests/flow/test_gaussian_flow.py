"""Gaussian flow and velocity flow: the A matrix, the feature channels, and rendered flow against closed forms."""
from __future__ import annotations

import math

import pytest
import torch

import pidg  # noqa: F401  (before torch settings matter)
from pidg.flow.gaussian_flow import (
    decode_depth_changes,
    decode_flows,
    deformation_matrix,
    flow_channel_count,
    flow_features,
    gaussian_flow_features,
    inv_sqrtm_2x2,
    sqrtm_2x2,
)
from pidg.flow.optical_flow import pixel_centers
from pidg.render import Camera, project_gaussians, rasterize

scipy_linalg = pytest.importorskip("scipy.linalg")

F64 = torch.float64
W, H = 40, 30  # non-square on purpose


def random_spd(n: int, seed: int) -> torch.Tensor:
    """Upper triangles (a, b, c) [n, 3] of well-conditioned SPD 2x2 matrices (pixel^2 scale)."""
    gen = torch.Generator().manual_seed(seed)
    root = torch.randn(n, 2, 2, generator=gen, dtype=F64) * 2.0
    full = root @ root.transpose(-1, -2) + 0.5 * torch.eye(2, dtype=F64)
    return torch.stack([full[:, 0, 0], full[:, 0, 1], full[:, 1, 1]], dim=-1)


def full(cov: torch.Tensor) -> torch.Tensor:
    a, b, c = cov.unbind(-1)
    return torch.stack([a, b, b, c], dim=-1).reshape(cov.shape[:-1] + (2, 2))


def camera() -> Camera:
    return Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), W, H, math.radians(50.0))


def one_gaussian(mean=(0.05, 0.02, 0.0), scale=(0.25, 0.18, 0.2)) -> dict[str, torch.Tensor]:
    return {
        "means": torch.tensor([mean], dtype=F64),
        "quats": torch.tensor([[0.9, 0.1, 0.2, 0.3]], dtype=F64),
        "scales": torch.tensor([scale], dtype=F64),
        "opacities": torch.tensor([0.95], dtype=F64),
    }


def render_flows(cam: Camera, g0: dict, g1: dict, velocities=None, dt=0.0, backend="torch"):
    feats = gaussian_flow_features(
        cam, g0["means"], g0["quats"], g0["scales"], g0["opacities"], g1["means"], g1["quats"], g1["scales"],
        velocities, dt,
    )
    colors = torch.ones(len(g0["means"]), 3, dtype=F64)
    out = rasterize(
        g0["means"], g0["quats"], g0["opacities"], colors, cam, scales=g0["scales"], features=feats, backend=backend
    )
    return out, decode_flows(out.features, out.alpha)


def closed_form(cam: Camera, g0: dict, g1: dict, means_v=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Single Gaussian: (A - I)(p - mu_t) + (mu_target - mu_t) at every pixel centre, A from scipy's sqrtm."""
    p0 = project_gaussians(g0["means"], g0["quats"], g0["scales"], g0["opacities"], cam)
    p1 = project_gaussians(g1["means"], g1["quats"], g1["scales"], g1["opacities"], cam)
    s0, s1 = full(p0.cov2d[0]).numpy(), full(p1.cov2d[0]).numpy()
    a = torch.from_numpy(scipy_linalg.sqrtm(s1).real @ scipy_linalg.inv(scipy_linalg.sqrtm(s0).real))
    target = p1.means2d[0] if means_v is None else means_v
    p = pixel_centers(H, W, F64)
    rel = p - p0.means2d[0]
    return rel @ (a - torch.eye(2, dtype=F64)).T + (target - p0.means2d[0]), a


# ---------------------------------------------------------------------------------------------------------------
def test_square_roots_match_scipy():
    cov = random_spd(20, seed=1)
    for k in range(len(cov)):
        ref = scipy_linalg.sqrtm(full(cov[k]).numpy()).real
        torch.testing.assert_close(sqrtm_2x2(cov[k]), torch.from_numpy(ref), rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(inv_sqrtm_2x2(cov[k]), torch.from_numpy(scipy_linalg.inv(ref)), rtol=1e-9, atol=1e-10)


def test_deformation_matrix_matches_scipy_and_maps_ellipse_t_onto_t1():
    cov_t, cov_t1 = random_spd(20, seed=2), random_spd(20, seed=3)
    a = deformation_matrix(cov_t, cov_t1)
    for k in range(len(cov_t)):
        ref = scipy_linalg.sqrtm(full(cov_t1[k]).numpy()).real @ scipy_linalg.inv(scipy_linalg.sqrtm(full(cov_t[k]).numpy()).real)
        torch.testing.assert_close(a[k], torch.from_numpy(ref), rtol=1e-9, atol=1e-9)
    # A Sigma_t A^T = Sigma_{t+1}: the unit ellipse at t is carried onto the one at t+1 (the swapped
    # Sigma_{t+1}^{-1/2} Sigma_t^{1/2} of the reference code does not do this).
    torch.testing.assert_close(a @ full(cov_t) @ a.transpose(-1, -2), full(cov_t1), rtol=1e-9, atol=1e-9)
    swapped = inv_sqrtm_2x2(cov_t1) @ sqrtm_2x2(cov_t)
    assert not torch.allclose(swapped @ full(cov_t) @ swapped.transpose(-1, -2), full(cov_t1), atol=1e-3)


def test_deformation_matrix_gradient_matches_finite_differences():
    cov_t, cov_t1 = random_spd(4, seed=4).requires_grad_(True), random_spd(4, seed=5).requires_grad_(True)
    assert torch.autograd.gradcheck(deformation_matrix, (cov_t, cov_t1), eps=1e-6, atol=1e-7)


def test_feature_channels_are_affine_flow_of_each_gaussian():
    """M p + b equals (A - I)(p - mu_t) + (mu_{t+1} - mu_t) at arbitrary p, per Gaussian."""
    cam = camera()
    gen = torch.Generator().manual_seed(0)
    n = 6
    g0 = {
        "means": torch.rand(n, 3, generator=gen, dtype=F64) - 0.5,
        "quats": torch.randn(n, 4, generator=gen, dtype=F64),
        "scales": 0.1 + 0.2 * torch.rand(n, 3, generator=gen, dtype=F64),
        "opacities": torch.full((n,), 0.9, dtype=F64),
    }
    g1 = {**g0, "means": g0["means"] + 0.1 * torch.randn(n, 3, generator=gen, dtype=F64),
          "scales": g0["scales"] * (1 + 0.3 * torch.rand(n, 3, generator=gen, dtype=F64))}
    p0 = project_gaussians(g0["means"], g0["quats"], g0["scales"], g0["opacities"], cam)
    p1 = project_gaussians(g1["means"], g1["quats"], g1["scales"], g1["opacities"], cam)
    feats = flow_features(p0, p1)
    assert feats.shape == (n, 6)
    p = torch.rand(n, 2, generator=gen, dtype=F64) * 40
    m = feats[:, :4].reshape(n, 2, 2)
    via_features = (m @ p.unsqueeze(-1)).squeeze(-1) + feats[:, 4:6]
    a = deformation_matrix(p0.cov2d, p1.cov2d)
    direct = ((a - torch.eye(2, dtype=F64)) @ (p - p0.means2d).unsqueeze(-1)).squeeze(-1) + p1.means2d - p0.means2d
    torch.testing.assert_close(via_features, direct)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_rendered_flow_of_translating_gaussian(backend: str):
    cam = camera()
    g0 = one_gaussian()
    g1 = {**g0, "means": g0["means"] + torch.tensor([[0.12, -0.07, 0.0]], dtype=F64)}
    out, (flow_g, flow_v, valid) = render_flows(cam, g0, g1, backend=backend)
    assert flow_v is None and flow_g.shape == (H, W, 2)
    expected, _ = closed_form(cam, g0, g1)
    seen = out.alpha > 0.02
    assert seen.sum() > 50 and valid[seen].all()
    torch.testing.assert_close(flow_g[seen], expected[seen], rtol=1e-6, atol=1e-6)
    # a translation parallel to the image plane: nearly rigid, so every pixel moves by about the centre's motion
    p0 = project_gaussians(g0["means"], g0["quats"], g0["scales"], g0["opacities"], cam).means2d[0]
    p1 = project_gaussians(g1["means"], g1["quats"], g1["scales"], g1["opacities"], cam).means2d[0]
    assert (flow_g[seen] - (p1 - p0)).norm(dim=-1).max() < 0.05 * (p1 - p0).norm()
    assert (flow_g[~valid] == 0).all()


def test_rendered_flow_of_scaling_gaussian():
    cam = camera()
    g0 = one_gaussian(scale=(0.15, 0.15, 0.15))
    g1 = {**g0, "scales": g0["scales"] * 1.5}
    out, (flow_g, _, _) = render_flows(cam, g0, g1)
    expected, a = closed_form(cam, g0, g1)
    seen = out.alpha > 0.02
    torch.testing.assert_close(flow_g[seen], expected[seen], rtol=1e-6, atol=1e-6)
    # isotropic growth about a fixed centre: flow points away from the centre, ~(s - 1) times the offset
    # (a bit less than 0.5 because of the constant 0.3 px^2 low-pass dilation of 2D covariances)
    mu = project_gaussians(g0["means"], g0["quats"], g0["scales"], g0["opacities"], cam).means2d[0]
    rel = pixel_centers(H, W, F64) - mu
    ratio = (flow_g[seen] * rel[seen]).sum(-1) / rel[seen].square().sum(-1)
    assert ratio.min() > 0.45 and ratio.max() < 0.5
    assert torch.allclose(a, a.T, atol=1e-6)  # a pure scaling of a symmetric ellipse: A is symmetric


def test_velocity_flow_of_gaussian_moving_with_known_velocity():
    cam = camera()
    g0 = one_gaussian()
    g1 = {**g0, "scales": g0["scales"] * 1.2}  # the deformation grows it but does not move it
    v, dt = torch.tensor([[0.4, 0.3, 0.0]], dtype=F64), 0.25
    out, (flow_g, flow_v, _) = render_flows(cam, g0, g1, velocities=v, dt=dt)
    assert flow_v is not None
    mu_v, _ = cam.project_points(g0["means"] + v * dt)
    expected_v, _ = closed_form(cam, g0, g1, means_v=mu_v[0])
    expected_g, _ = closed_form(cam, g0, g1)
    seen = out.alpha > 0.02
    torch.testing.assert_close(flow_v[seen], expected_v[seen], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(flow_g[seen], expected_g[seen], rtol=1e-6, atol=1e-6)
    # the two flows differ exactly by the projected velocity displacement
    mu0 = project_gaussians(g0["means"], g0["quats"], g0["scales"], g0["opacities"], cam).means2d[0]
    torch.testing.assert_close(flow_v[seen] - flow_g[seen], (mu_v[0] - mu0).expand(int(seen.sum()), 2))


def two_gaussians() -> dict[str, torch.Tensor]:
    """Two overlapping Gaussians at different depths."""
    return {
        "means": torch.tensor([[-0.1, 0.0, 0.0], [0.15, 0.05, 0.3]], dtype=F64),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.8, 0.2, 0.1, 0.0]], dtype=F64),
        "scales": torch.tensor([[0.25, 0.2, 0.2], [0.2, 0.3, 0.2]], dtype=F64),
        "opacities": torch.tensor([0.7, 0.8], dtype=F64),
    }


def test_two_gaussians_flow_is_normalised_weighted_average():
    """flow(p) = sum_i w_i flow_i(p) / sum_i w_i with the compositing weights (the K -> infinity top-K form)."""
    cam = camera()
    g0 = two_gaussians()
    shift = torch.tensor([[0.15, 0.0, 0.0], [0.0, -0.1, 0.0]], dtype=F64)
    g1 = {**g0, "means": g0["means"] + shift, "scales": g0["scales"] * torch.tensor([[1.0], [1.3]], dtype=F64)}
    feats = gaussian_flow_features(cam, *(g0[k] for k in ("means", "quats", "scales", "opacities")),
                                   g1["means"], g1["quats"], g1["scales"])
    one_hot = torch.eye(2, dtype=F64)
    out = rasterize(g0["means"], g0["quats"], g0["opacities"], torch.ones(2, 3, dtype=F64), cam,
                    scales=g0["scales"], features=torch.cat([feats, one_hot], dim=-1), backend="torch")
    flow_g, _, _ = decode_flows(out.features[..., :6], out.alpha)
    weights = out.features[..., 6:8]  # w_i per pixel
    per_gaussian = []
    for i in range(2):
        gi = {k: v[i : i + 1] for k, v in g0.items()}
        gi1 = {k: v[i : i + 1] for k, v in g1.items()}
        per_gaussian.append(closed_form(cam, gi, gi1)[0])
    expected = (weights[..., 0:1] * per_gaussian[0] + weights[..., 1:2] * per_gaussian[1]) / out.alpha.unsqueeze(-1)
    seen = out.alpha > 0.02
    torch.testing.assert_close(flow_g[seen], expected[seen], rtol=1e-6, atol=1e-6)


def test_culled_and_degenerate_gaussians_carry_no_flow():
    cam = camera()
    means = torch.tensor([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.1, 0.0, 0.0], [-0.1, 0.1, 0.0]], dtype=F64)
    g0 = {"means": means, "quats": torch.tensor([[1.0, 0, 0, 0]], dtype=F64).expand(4, 4),
          "scales": torch.full((4, 3), 0.1, dtype=F64), "opacities": torch.full((4,), 0.9, dtype=F64)}
    means1 = means.clone()
    means1[0] += torch.tensor([0.05, 0.0, 0.0], dtype=F64)  # ordinary motion
    means1[2] += torch.tensor([0.0, 0.0, -6.0], dtype=F64)  # ends up behind camera t at t+1
    means1[3] += torch.tensor([5.0, 0.0, 0.0], dtype=F64)  # leaves the image by t+1: still tracked
    feats = gaussian_flow_features(cam, g0["means"], g0["quats"], g0["scales"], g0["opacities"],
                                   means1, g0["quats"], g0["scales"])
    assert feats[0].abs().sum() > 0
    assert (feats[1] == 0).all()  # off-screen at t (radius 0): not drawn anyway
    assert (feats[2] == 0).all()  # behind the camera at t+1: no meaningful projection
    assert feats[3].abs().sum() > 0
    assert torch.isfinite(feats).all()


@pytest.mark.parametrize("depth_change", [False, True])
def test_flow_features_gradient_reaches_both_times(depth_change: bool):
    cam = camera()
    g0 = one_gaussian()
    means1 = (g0["means"] + 0.05).requires_grad_(True)
    scales1 = (g0["scales"] * 1.1).requires_grad_(True)
    means0 = g0["means"].clone().requires_grad_(True)
    velocities = torch.tensor([[0.1, 0.2, 0.0]], dtype=F64, requires_grad=True)

    def feats(m0, m1, s1, v):
        return gaussian_flow_features(cam, m0, g0["quats"], g0["scales"], g0["opacities"], m1, g0["quats"], s1, v, 0.5,
                                      depth_change=depth_change)

    assert torch.autograd.gradcheck(feats, (means0, means1, scales1, velocities), eps=1e-6, atol=1e-6)


def test_decode_flows_rejects_wrong_layout():
    alpha = torch.ones(H, W)
    with pytest.raises(ValueError, match="features"):
        decode_flows(torch.zeros(8, H, W), alpha)
    with pytest.raises(ValueError, match="features"):
        decode_flows(torch.zeros(H, W, 5), alpha)


def test_total_flow_of_a_static_surface_is_the_camera_induced_flow():
    """FlowConfig.target "total": the Gaussians at t seen by camera t and at t+1 by camera t+1. For a static plane of
    small flat splats the rendered flow must be the plane's camera-induced optical flow, computed independently by
    back-projecting each pixel onto the plane (ray-plane intersection) and projecting it into camera t+1; and the
    motion flow (camera t at both times) of the same static Gaussians must be zero. (Measured: mean error 0.15 px, max
    0.34 px, mean bias 0.03 px, against a 5.5 px flow.)"""
    cam0 = camera()
    cam1 = Camera.look_at((1.3, 0.5, -3.6), (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), W, H, math.radians(50.0))
    # the plane z = 0.3 covered by a dense grid of flat splats (thin along z)
    xs = torch.linspace(-2.2, 2.2, 90, dtype=F64)
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    n = gx.numel()
    g = {
        "means": torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((n,), 0.3, dtype=F64)], dim=-1),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64).expand(n, 4),
        "scales": torch.tensor([[0.04, 0.04, 0.002]], dtype=F64).expand(n, 3),
        "opacities": torch.full((n,), 0.9, dtype=F64),
    }
    feats = gaussian_flow_features(cam0, g["means"], g["quats"], g["scales"], g["opacities"], g["means"], g["quats"],
                                   g["scales"], camera_t1=cam1)
    out = rasterize(g["means"], g["quats"], g["opacities"], torch.ones(n, 3, dtype=F64), cam0, scales=g["scales"],
                    features=feats, backend="torch")
    flow, _, valid = decode_flows(out.features, out.alpha)
    # independent: the ray of each pixel centre of camera 0 meets the plane at one point, seen by camera 1
    p = pixel_centers(H, W, F64)
    ray_cam = torch.stack([(p[..., 0] - cam0.cx) / cam0.fx, (p[..., 1] - cam0.cy) / cam0.fy, torch.ones(H, W, dtype=F64)], -1)
    c2w = torch.linalg.inv(cam0.world_to_camera.to(F64))
    origin, dirs = c2w[:3, 3], ray_cam @ c2w[:3, :3].T
    hit = origin + dirs * ((0.3 - origin[2]) / dirs[..., 2]).unsqueeze(-1)
    p1, _ = cam1.project_points(hit.reshape(-1, 3))
    expected = p1.reshape(H, W, 2) - p
    seen = out.alpha > 0.99
    assert seen.sum() > 0.9 * H * W and valid[seen].all()
    assert expected[seen].norm(dim=-1).mean() > 2.0  # the camera move is a real flow
    # each splat moves affinely by A = Sigma1^(1/2) Sigma0^(-1/2), which cannot hold the homography's local rotation
    # (GaussianFlow's approximation), and the splats are ~0.5 px apart: small errors, and no bias
    error = flow[seen] - expected[seen]
    assert error.norm(dim=-1).mean() < 0.2 and error.norm(dim=-1).max() < 0.4 and error.mean(0).norm() < 0.05
    # the motion flow of the same static Gaussians: camera motion cancels
    motion = gaussian_flow_features(cam0, g["means"], g["quats"], g["scales"], g["opacities"], g["means"], g["quats"], g["scales"])
    assert motion.abs().max() < 1e-9


# ---- depth-change channels (--flow.lambda_depth_change) -------------------------------------------------------------
def camera_depth(cam: Camera, points: torch.Tensor) -> torch.Tensor:
    """Camera z of world points, written out from the world-to-camera matrix (not through project_points)."""
    w2c = cam.world_to_camera.to(F64)
    return points @ w2c[2, :3] + w2c[2, 3]


def test_depth_change_channels_are_each_gaussians_camera_t_depth_change_composited():
    cam = camera()
    g0 = two_gaussians()
    g1 = {**g0, "means": g0["means"] + torch.tensor([[0.05, 0.0, 0.2], [0.0, -0.1, -0.3]], dtype=F64)}
    v, dt = torch.tensor([[0.1, 0.0, 0.6], [0.0, 0.2, -0.4]], dtype=F64), 0.5
    args = (cam, *(g0[k] for k in ("means", "quats", "scales", "opacities")), g1["means"], g1["quats"], g1["scales"])
    feats = gaussian_flow_features(*args, v, dt, depth_change=True)
    assert feats.shape == (2, flow_channel_count(velocity=True, depth_change=True)) == (2, 10)
    torch.testing.assert_close(feats[:, :8], gaussian_flow_features(*args, v, dt))  # the flows are unchanged
    z0 = camera_depth(cam, g0["means"])
    torch.testing.assert_close(feats[:, 8], camera_depth(cam, g1["means"]) - z0)
    torch.testing.assert_close(feats[:, 9], camera_depth(cam, g0["means"] + v * dt) - z0)
    # composited: sum_i w_i dz_i / sum_i w_i, with the weights rendered as one-hot channels
    out = rasterize(g0["means"], g0["quats"], g0["opacities"], torch.ones(2, 3, dtype=F64), cam, scales=g0["scales"],
                    features=torch.cat([feats, torch.eye(2, dtype=F64)], dim=-1), backend="torch")
    dz, dz_v = decode_depth_changes(out.features[..., :10], out.alpha)
    weights = out.features[..., 10:12]
    seen = out.alpha > 0.02
    torch.testing.assert_close(dz[seen], ((weights @ feats[:, 8]) / out.alpha)[seen])
    torch.testing.assert_close(dz_v[seen], ((weights @ feats[:, 9]) / out.alpha)[seen])
    # without velocities: 7 channels, one depth change
    seven = gaussian_flow_features(*args, depth_change=True)
    assert seven.shape == (2, 7) and torch.equal(seven[:, 6], feats[:, 8])
    assert decode_flows(out.features[..., :10], out.alpha)[1] is not None


def test_depth_change_channels_need_the_motion_flow_and_a_layout_that_has_them():
    cam = camera()
    g = one_gaussian()
    with pytest.raises(ValueError, match="motion flow"):
        gaussian_flow_features(cam, g["means"], g["quats"], g["scales"], g["opacities"], g["means"], g["quats"],
                               g["scales"], camera_t1=cam, depth_change=True)
    with pytest.raises(ValueError, match="no depth-change channels"):
        decode_depth_changes(torch.zeros(H, W, 8), torch.ones(H, W))


@pytest.mark.parametrize("velocity, depth_change", [(False, False), (True, False), (True, True)])
def test_the_kernel_matches_the_torch_form_values_and_gradients(velocity: bool, depth_change: bool):
    """The numba channels (pidg.flow.gaussian_flow_cpu) against autograd through the torch form, in float64 and
    float32, on rows of every kind: kept, culled at t, degenerate or non-finite at t+1, and not ``valid``."""
    from pidg.render.projection import Projection

    n = 64
    gen = torch.Generator().manual_seed(4)
    cov_t, cov_t1 = random_spd(n, 5), random_spd(n, 6)
    cov_t1[3] = torch.tensor([1.0, 1.0, 1.0], dtype=F64)  # singular at t+1
    cov_t1[4, 0] = float("nan")
    mu_t, mu_t1, mu_v = (torch.randn(n, 2, generator=gen, dtype=F64) * 20 + 15 for _ in range(3))
    mu_t1[5] = float("inf")
    radii = torch.randint(1, 9, (n, 2), generator=gen)
    radii[6] = 0  # culled at t
    valid = torch.ones(n, dtype=torch.bool)
    valid[7] = False
    dz = torch.randn(n, 2 if velocity else 1, generator=gen, dtype=F64)
    upstream = torch.randn(n, flow_channel_count(velocity, depth_change), generator=gen, dtype=F64)
    for dtype, tol in ((F64, 1e-10), (torch.float32, 2e-4)):
        results = []
        for kernel in (True, False):
            leaves = [t.to(dtype).clone().requires_grad_(True) for t in (cov_t, cov_t1, mu_t, mu_t1, mu_v, dz)]
            c0, c1, m0, m1, mv, d = leaves
            zeros = torch.zeros(n, dtype=dtype)
            feats = flow_features(Projection(m0, c0, zeros, radii, c0), Projection(m1, c1, zeros, radii, c1),
                                  mv if velocity else None, valid, d if depth_change else None, kernel=kernel)
            (feats * upstream.to(dtype)).sum().backward()
            results.append((feats.detach(), [leaf.grad for leaf in leaves]))
        (got, got_grads), (want, want_grads) = results
        assert got.dtype == dtype and got.shape == want.shape
        assert (got[3:8] == 0).all() and got[:3].abs().sum() > 0
        scale = float(want.abs().max())
        torch.testing.assert_close(got, want, rtol=tol, atol=tol * scale)
        for name, g, w in zip(("cov_t", "cov_t1", "mu_t", "mu_t1", "mu_v", "dz"), got_grads, want_grads):
            if g is None and w is None:  # an input this layout does not read
                continue
            w = torch.zeros_like(g) if w is None else w
            g = torch.zeros_like(w) if g is None else g
            torch.testing.assert_close(g, w, rtol=tol, atol=tol * float(w.abs().max().clamp_min(1.0)),
                                       msg=lambda m, k=name: f"grad {k} ({dtype}): {m}")


def test_the_kernel_computes_in_float64_whatever_the_inputs():
    """Unchanged covariances give A = I: M is 0 to float64 rounding from float32 inputs too (float32 arithmetic
    leaves ~1e-7), as the kernel module says."""
    from pidg.render.projection import Projection

    cov = random_spd(200, 9).to(torch.float32)
    mu = torch.randn(200, 2, generator=torch.Generator().manual_seed(2)) * 50
    proj = Projection(mu, cov, torch.zeros(200), torch.ones(200, 2, dtype=torch.int64), cov)
    m = flow_features(proj, proj, kernel=True)[:, :4]
    assert m.dtype == torch.float32 and float(m.abs().max()) < 1e-12
