"""Gaussian flow and velocity flow as per-Gaussian feature channels of the ordinary rasterize pass.

GaussianFlow (paper eq. for p^gaussian, supp. B): a pixel p keeps its normalised coordinates inside each 2D
Gaussian from t to t+1, so Gaussian i carries p to  mu_{t+1} + A (p - mu_t)  with

    A = Sigma_{t+1}^{1/2} Sigma_t^{-1/2}

(symmetric PSD square roots; the reference code's swapped Sigma_{t+1}^{-1/2} Sigma_t^{1/2} is a known defect).
Both 2D Gaussians come from projecting the 3D Gaussians at t and at t+1 with camera t, so camera motion cancels
(the motion flow); projecting those at t+1 with camera t+1 instead gives the total flow, which an optical flow
measures directly (GaussianFlow's form, ``FlowConfig.target = "total"``).
Gaussian i's flow at p is affine in p:

    flow_i(p) = (A - I)(p - mu_t) + (mu_{t+1} - mu_t) = M p + b,   M = A - I,   b = mu_{t+1} - mu_t - M mu_t

so compositing M (4 channels) and b (2 channels) with the colour weights w_i = alpha_i T_i gives
flow(p) = (M(p) p + b(p)) / sum_i w_i -- the normalised-weight (K -> infinity) form of the paper's top-K sum.
The velocity flow replaces mu_{t+1} by the camera-t projection of x + v dt (2 more channels, b_v).
A 2D flow sees only the motion across camera t's rays; with ``depth_change`` each Gaussian also carries its
camera-t depth change, z(x_{t+1}) - z(x_t) and z(x_t + v dt) - z(x_t) (world units), composited the same way, for
the depth-change target of :func:`pidg.flow.decomposition.depth_change_target`.
Channel layout: [m00, m01, m10, m11, b_x, b_y, (bv_x, bv_y), (dz, (dz_v))] -- 6, 7, 8 or 10 channels.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.flow.gaussian_flow_cpu import flow_channels_cpu
from pidg.flow.optical_flow import pixel_centers
from pidg.render.camera import Camera
from pidg.render.api import RenderBackend, project
from pidg.render.projection import Projection

FLOW_CHANNELS = 8  # with the velocity flow; 6 without
DECODE_MIN_ALPHA = 1e-4  # below this accumulated alpha a pixel has no flow (division by ~0)


def flow_channel_count(velocity: bool, depth_change: bool = False) -> int:
    """Channels of :func:`flow_features`: 6 (Gaussian flow), +2 with the velocity flow, +1 per flow with its depth
    change."""
    return (FLOW_CHANNELS if velocity else FLOW_CHANNELS - 2) + (int(velocity) + 1 if depth_change else 0)


def sqrtm_2x2(cov: Tensor) -> Tensor:
    """Principal square root [..., 2, 2] of SPD matrices given as upper triangles (a, b, c) [..., 3].

    Closed form: sqrt(S) = (S + s I) / t with s = sqrt(det S), t = sqrt(tr S + 2 s).
    """
    a, b, c = cov.unbind(-1)
    s = torch.sqrt(a * c - b * b)
    t = torch.sqrt(a + c + 2.0 * s)
    return torch.stack([(a + s) / t, b / t, b / t, (c + s) / t], dim=-1).reshape(cov.shape[:-1] + (2, 2))


def inv_sqrtm_2x2(cov: Tensor) -> Tensor:
    """S^{-1/2} [..., 2, 2] of SPD (a, b, c) [..., 3]: adj(S + s I) / (t s), the inverse of :func:`sqrtm_2x2`."""
    a, b, c = cov.unbind(-1)
    s = torch.sqrt(a * c - b * b)
    ts = torch.sqrt(a + c + 2.0 * s) * s
    return torch.stack([(c + s) / ts, -b / ts, -b / ts, (a + s) / ts], dim=-1).reshape(cov.shape[:-1] + (2, 2))


def deformation_matrix(cov_t: Tensor, cov_t1: Tensor) -> Tensor:
    """A = Sigma_{t+1}^{1/2} Sigma_t^{-1/2} [..., 2, 2] from 2D covariances (a, b, c) [..., 3] at t and t+1."""
    return sqrtm_2x2(cov_t1) @ inv_sqrtm_2x2(cov_t)


def _valid_covariance(cov: Tensor) -> Tensor:
    a, b, c = cov.detach().unbind(-1)
    return (a > 0) & (c > 0) & (a * c - b * b > 0) & torch.isfinite(cov.detach()).all(-1)


def flow_features(
    proj_t: Projection, proj_t1: Projection, means2d_velocity: Tensor | None = None, valid: Tensor | None = None,
    depth_changes: Tensor | None = None, kernel: bool | None = None,
) -> Tensor:
    """Per-Gaussian flow channels [N, 8] ([N, 6] without ``means2d_velocity``), differentiable.

    ``proj_t`` / ``proj_t1``: the Gaussians at t and t+1, both projected with camera t. ``means2d_velocity`` [N, 2]:
    camera-t pixels of x + v dt. ``depth_changes`` [N, 1 or 2]: appended channels (the depth changes, see the
    module docstring), zeroed with the rest. Rows are zero (the Gaussian carries no flow; it still occludes) for Gaussians
    culled at t (radius 0: not drawn anyway), for degenerate t+1 covariances, and where ``valid`` [N] is False
    (e.g. behind camera t at t+1, see :func:`gaussian_flow_features`). A Gaussian that merely leaves the image
    by t+1 keeps its flow: that motion is real.
    ``kernel``: the numba kernels of :mod:`pidg.flow.gaussian_flow_cpu` (the default for CPU tensors) or, False,
    the torch form below (any device; the reference the tests compare with).
    """
    cov_t, cov_t1 = proj_t.cov2d, proj_t1.cov2d
    keep = (proj_t.radii > 0).all(-1) & _valid_covariance(cov_t) & _valid_covariance(cov_t1)
    keep = keep & torch.isfinite(proj_t1.means2d.detach()).all(-1)
    if valid is not None:
        keep = keep & valid.to(keep.device)
    mu_t = proj_t.means2d
    if means2d_velocity is not None and tuple(means2d_velocity.shape) != tuple(mu_t.shape):
        raise ValueError(f"means2d_velocity must be [N, 2] = {list(mu_t.shape)}, got {list(means2d_velocity.shape)}")
    if kernel is None:
        kernel = mu_t.device.type == "cpu"
    if kernel:
        features = flow_channels_cpu(cov_t, cov_t1, mu_t, proj_t1.means2d, means2d_velocity, keep)
        if depth_changes is None:
            return features
        return torch.cat([features, torch.where(keep.unsqueeze(-1), depth_changes, torch.zeros_like(depth_changes))], dim=-1)
    # Substitute the identity covariance on dropped rows so no NaN reaches the (masked) gradient.
    eye = cov_t.new_tensor([1.0, 0.0, 1.0])
    k3 = keep.unsqueeze(-1)
    a = deformation_matrix(torch.where(k3, cov_t, eye), torch.where(k3, cov_t1, eye))
    m = a - torch.eye(2, dtype=a.dtype, device=a.device)
    m_mu = (m @ mu_t.unsqueeze(-1)).squeeze(-1)
    channels = [m.reshape(-1, 4), proj_t1.means2d - mu_t - m_mu]
    if means2d_velocity is not None:
        channels.append(means2d_velocity - mu_t - m_mu)
    if depth_changes is not None:
        channels.append(depth_changes)
    features = torch.cat(channels, dim=-1)
    return torch.where(k3, features, torch.zeros_like(features))


def decode_flows(
    features: Tensor, alpha: Tensor, min_alpha: float = DECODE_MIN_ALPHA
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Rendered flow channels [H, W, 6, 7, 8 or 10] and accumulated alpha [H, W] -> (Gaussian flow [H, W, 2],
    velocity flow [H, W, 2] or None, valid [H, W]) in pixels at the pixel centres; flows are 0 where alpha <=
    min_alpha. Depth-change channels are ignored (:func:`decode_depth_changes`)."""
    h, w = alpha.shape
    _check_rendered(features, h, w)
    return decode_flows_at(features, alpha, pixel_centers(h, w, features.dtype, features.device), min_alpha)


def decode_flows_at(
    features: Tensor, alpha: Tensor, centers: Tensor, min_alpha: float = DECODE_MIN_ALPHA
) -> tuple[Tensor, Tensor | None, Tensor]:
    """:func:`decode_flows` for channels gathered at any set of pixels: ``features`` [..., C], ``alpha`` [...],
    ``centers`` [..., 2] the pixels' centres (x + 0.5, y + 0.5). A loss that reads a few pixels decodes only those."""
    if features.shape[-1] not in (6, 7, 8, 10) or features.shape[:-1] != alpha.shape or centers.shape != (*alpha.shape, 2):
        raise ValueError(f"decode_flows_at: features [..., 6, 7, 8 or 10], alpha [...] and centers [..., 2] must share their "
                         f"leading shape, got {list(features.shape)}, {list(alpha.shape)}, {list(centers.shape)}")
    velocity = features.shape[-1] in (8, 10)
    m, b_g, b_v = features[..., : 8 if velocity else 6].split([4, 2, 2 if velocity else 0], dim=-1)  # split: one backward
    mp = (m.unflatten(-1, (2, 2)) * centers.unsqueeze(-2)).sum(-1)  # the 2x2 map applied to the centres
    valid, inv_alpha = _inverse_alpha(alpha, min_alpha)
    inv_alpha = inv_alpha.unsqueeze(-1)
    flow_g = (mp + b_g) * inv_alpha
    flow_v = (mp + b_v) * inv_alpha if velocity else None
    return flow_g, flow_v, valid


def _inverse_alpha(alpha: Tensor, min_alpha: float) -> tuple[Tensor, Tensor]:
    """Where a pixel has flow (alpha > ``min_alpha``) and 1 / alpha there (0 elsewhere): composited channels divided
    by it are the normalised-weight averages of the Gaussians' values."""
    valid = alpha > min_alpha
    return valid, torch.where(valid, 1.0 / alpha.clamp_min(min_alpha), torch.zeros_like(alpha))


def _check_rendered(features: Tensor, h: int, w: int) -> None:
    if features.dim() != 3 or tuple(features.shape[:2]) != (h, w) or features.shape[-1] not in (6, 7, 8, 10):
        raise ValueError(f"features must be [H, W, 6, 7, 8 or 10] = [{h}, {w}, 8], got {list(features.shape)}")


def decode_depth_changes(features: Tensor, alpha: Tensor, min_alpha: float = DECODE_MIN_ALPHA) -> tuple[Tensor, Tensor | None]:
    """Rendered channels [H, W, 7 or 10] -> the composited depth change of the Gaussians [H, W] and of the velocity
    advection [H, W] or None (10 channels only), world units of camera-t depth; 0 where alpha <= min_alpha."""
    h, w = alpha.shape
    _check_rendered(features, h, w)
    return decode_depth_changes_at(features, alpha, min_alpha)


def decode_depth_changes_at(features: Tensor, alpha: Tensor, min_alpha: float = DECODE_MIN_ALPHA) -> tuple[Tensor, Tensor | None]:
    """:func:`decode_depth_changes` for channels gathered at any set of pixels: ``features`` [..., 7 or 10],
    ``alpha`` [...]."""
    if features.shape[-1] not in (7, 10):
        raise ValueError(f"features carry no depth-change channels ({features.shape[-1]} channels; 7 or 10 do)")
    _, inv_alpha = _inverse_alpha(alpha, min_alpha)
    if features.shape[-1] == 7:
        return features[..., 6] * inv_alpha, None
    dz = features[..., 8:10] * inv_alpha.unsqueeze(-1)
    return dz[..., 0], dz[..., 1]


def project_velocity_means(means: Tensor, velocities: Tensor, dt: float, camera: Camera) -> tuple[Tensor, Tensor]:
    """Camera pixels [N, 2] and depths [N] of the means advected by their velocities, x + v dt."""
    return camera.project_points(means + velocities * dt)


def gaussian_flow_features(
    camera_t: Camera,
    means_t: Tensor,
    quats_t: Tensor,
    scales_t: Tensor,
    opacities: Tensor,
    means_t1: Tensor,
    quats_t1: Tensor,
    scales_t1: Tensor,
    velocities: Tensor | None = None,
    dt: float = 0.0,
    camera_t1: Camera | None = None,
    backend: RenderBackend = "auto",
    depth_change: bool = False,
) -> Tensor:
    """Feature channels [N, 8] (or [N, 6] without velocities; +2 or +1 with ``depth_change``) for
    ``rasterize(..., features=)`` at time t.

    Projects the Gaussians at t with camera t -- the same projection rasterize does for the image -- and those at t+1
    (and x_t + v dt) with ``camera_t1``: None (camera t) gives the motion flow, in which camera motion cancels; frame
    t+1's camera gives the total flow, the optical flow the model predicts. Gaussians whose t+1 (or advected) centre
    is not in front of that camera are dropped. ``backend``: the render's (which projection implementation).
    ``depth_change``: append the camera-t depth changes (motion flow only: the module docstring).
    """
    if depth_change and camera_t1 is not None:
        raise ValueError("depth-change channels are defined for the motion flow (camera t at both times) only")
    later = camera_t if camera_t1 is None else camera_t1
    proj_t = project(means_t, quats_t, scales_t, opacities, camera_t, backend)
    proj_t1 = project(means_t1, quats_t1, scales_t1, opacities, later, backend)
    valid = proj_t1.depths.detach() > later.near
    means2d_velocity = None
    if velocities is not None:
        means2d_velocity, depth_v = project_velocity_means(means_t, velocities, dt, later)
        valid = valid & (depth_v.detach() > later.near)
    depth_changes = None
    if depth_change:
        changes = [proj_t1.depths - proj_t.depths] + ([depth_v - proj_t.depths] if velocities is not None else [])
        depth_changes = torch.stack(changes, dim=-1)
    return flow_features(proj_t, proj_t1, means2d_velocity, valid, depth_changes)
