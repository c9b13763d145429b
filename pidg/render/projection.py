"""EWA projection of 3D Gaussians to screen-space 2D Gaussians, differentiable through torch autograd.

Kept separate from compositing (as in gsplat): projection is cheap per-Gaussian arithmetic where autograd is
fast enough and easy to trust; compositing is the per-pixel hot loop that needs a kernel.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from pidg.render.camera import Camera

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (3DGS convention)
ALPHA_MAX = 0.99  # per-Gaussian alpha is clamped to this so transmittance never reaches zero
TRANSMITTANCE_MIN = 1e-4  # a pixel stops compositing once its transmittance would fall below this
TILE_SIZE = 16  # pixels along a side of the compositors' square tiles (the CPU kernel takes up to its 16 lanes)
EPS2D = 0.3  # low-pass dilation (pixels^2) added to every 2D covariance
FRUSTUM_MARGIN = 1.3  # J is evaluated with x/z, y/z clamped to 1.3x the half field of view (3DGS, gsplat)


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities. Rows of culled Gaussians hold finite dummies and ``radii == 0``."""

    means2d: Tensor  # [N, 2] pixel coordinates (pixel centres at integer + 0.5), differentiable
    conics: Tensor  # [N, 3] upper triangle (a, b, c) of the inverse 2D covariance, differentiable
    depths: Tensor  # [N] camera-space z, differentiable
    radii: Tensor  # [N, 2] int32 half-extent in pixels of the region where alpha >= 1/255 (0 = culled)
    cov2d: Tensor  # [N, 3] upper triangle of the (dilated) 2D covariance, differentiable

    @property
    def visible(self) -> Tensor:
        return (self.radii > 0).all(dim=-1)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] in (w, x, y, z) order; normalised here."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(r: Tensor) -> Tensor:
    """Quaternions [N, 4] (w, x, y, z) from rotation matrices [N, 3, 3], stable for every angle.

    Each of the four standard formulas divides by one quaternion component; the one with the largest
    component is used (as in PyTorch3D's ``matrix_to_quaternion``).
    """
    m = r.reshape(-1, 9).unbind(-1)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    q_abs = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    ).clamp_min(0).sqrt()
    candidates = torch.stack(
        [
            torch.stack([q_abs[:, 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, q_abs[:, 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, q_abs[:, 2] ** 2, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[:, 3] ** 2], dim=-1),
        ],
        dim=1,
    ) / (2.0 * q_abs.clamp_min(0.1)).unsqueeze(-1)
    best = q_abs.argmax(dim=-1)
    q = candidates[torch.arange(len(best)), best]
    return q / q.norm(dim=-1, keepdim=True)


def rotate_by_inverse(quats: Tensor, v: Tensor) -> Tensor:
    """R^T v for the rotations of quaternions [N, 4] (w, x, y, z; normalised here) and vectors [N, 3].

    Two cross products on [N, 3] tensors: about half the time (forward + backward) of forming R [N, 3, 3]
    and reducing over its rows, which torch does slowly on CPU at this shape.
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, u = q[:, :1], q[:, 1:]
    uv = torch.linalg.cross(u, v)
    return v + 2.0 * (torch.linalg.cross(u, uv) - w * uv)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariance R S S^T R^T [N, 3, 3] from quaternions and (linear) scales."""
    m = quat_to_rotmat(quats) * scales.unsqueeze(-2)
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    camera: Camera,
    eps2d: float = EPS2D,
) -> Projection:
    """Project Gaussians through a pinhole camera with the EWA local affine approximation.

    Culled (radius 0): centre outside (near, far), opacity below 1/255, or footprint entirely off-screen.
    The radius is the exact half-extent of the ellipse where ``opacity * exp(-d^2/2) >= 1/255`` (per axis), so
    tiling never drops a contribution that compositing would keep: results do not depend on the tile size.
    """
    w2c = camera.world_to_camera.to(device=means.device, dtype=means.dtype)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    # x_cam = R x + t written as broadcasts: batched 3x3 products are the slowest ops on CPU at this size
    p_cam = means[:, 0:1] * rot[:, 0] + means[:, 1:2] * rot[:, 1] + means[:, 2:3] * rot[:, 2] + trans
    x, y, z = p_cam.unbind(-1)

    in_depth = (z > camera.near) & (z < camera.far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # keeps culled rows finite (0*inf would poison grads)

    # Clamp the tangent of the viewing angle for the Jacobian only: very oblique Gaussians otherwise explode.
    lim_x_pos = (camera.width - camera.cx) / camera.fx + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.width / camera.fx
    lim_x_neg = camera.cx / camera.fx + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.width / camera.fx
    lim_y_pos = (camera.height - camera.cy) / camera.fy + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.height / camera.fy
    lim_y_neg = camera.cy / camera.fy + (FRUSTUM_MARGIN - 1.0) * 0.5 * camera.height / camera.fy
    inv_z = 1.0 / z_safe
    tan_x = torch.clamp(x * inv_z, -lim_x_neg, lim_x_pos)
    tan_y = torch.clamp(y * inv_z, -lim_y_neg, lim_y_pos)

    # EWA: cov2d = (J W R S)(J W R S)^T with J the pinhole Jacobian at (tx, ty, z) and W the view rotation.
    # J W row i = J[i,i] W[i,:] + J[i,2] W[2,:], with J[0,2] = -fx tx / z^2 = -fx tan_x / z.
    jw0 = (camera.fx * inv_z).unsqueeze(-1) * rot[0] - (camera.fx * tan_x * inv_z).unsqueeze(-1) * rot[2]
    jw1 = (camera.fy * inv_z).unsqueeze(-1) * rot[1] - (camera.fy * tan_y * inv_z).unsqueeze(-1) * rot[2]
    a0 = rotate_by_inverse(quats, jw0) * scales  # [N, 3] row 0 of J W R S = (R^T (J W)_0) * s
    a1 = rotate_by_inverse(quats, jw1) * scales
    a = (a0 * a0).sum(-1) + eps2d
    b = (a0 * a1).sum(-1)
    c = (a1 * a1).sum(-1) + eps2d
    det = a * c - b * b
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = torch.stack([camera.fx * x * inv_z + camera.cx, camera.fy * y * inv_z + camera.cy], dim=-1)

    with torch.no_grad():
        opac = opacities.detach()
        keep = in_depth & det_ok & (opac > ALPHA_MIN) & torch.isfinite(means2d).all(-1)
        # squared Mahalanobis radius where opacity * exp(-r^2/2) = 1/255; tiny margin against rounding
        r2 = (2.0 * torch.log(opac.clamp_min(ALPHA_MIN) / ALPHA_MIN)).clamp_min(0.0) * (1.0 + 1e-4)
        half = torch.stack([torch.sqrt(r2 * a.clamp_min(0)), torch.sqrt(r2 * c.clamp_min(0))], dim=-1)
        m2 = means2d.detach()
        on_screen = (
            (m2[:, 0] + half[:, 0] > 0)
            & (m2[:, 0] - half[:, 0] < camera.width)
            & (m2[:, 1] + half[:, 1] > 0)
            & (m2[:, 1] - half[:, 1] < camera.height)
        )
        keep = keep & on_screen & (half > 0).all(-1)
        radii = torch.where(keep.unsqueeze(-1), torch.ceil(half).clamp_max(2**30), torch.zeros_like(half))
        radii = radii.to(torch.int32)
    return Projection(
        means2d=means2d,
        conics=conics,
        depths=z,
        radii=radii,
        cov2d=torch.stack([a, b, c], dim=-1),
    )


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """Number of tiles along x and y."""
    return math.ceil(width / tile_size), math.ceil(height / tile_size)


def image_channel_count(image_channels: int | None, n_channels: int) -> int:
    """The compositors' ``image_channels``: how many leading channels of per-Gaussian features [N, D] form the image
    (None: all D); the rest are composited into a separate ``extra`` output."""
    count = n_channels if image_channels is None else int(image_channels)
    if not 0 <= count <= n_channels:
        raise ValueError(f"image_channels must be in [0, {n_channels}] for {n_channels} feature channels, got {image_channels}")
    return count


def tile_rows_touched(pixels: Tensor, tile_size: int) -> Tensor:
    """[H, tiles_x] bool: the tile rows (a tile's pixels on one image row, up to ``tile_size`` of them: the
    compositor's unit of work) that hold a True pixel of ``pixels`` [H, W] (bool)."""
    height, width = pixels.shape
    tiles_x, _ = tile_grid(width, height, tile_size)
    padded = F.pad(pixels.to(torch.bool), (0, tiles_x * tile_size - width))
    return padded.reshape(height, tiles_x, tile_size).any(dim=2)


def tiles_touched(pixels: Tensor, tile_size: int) -> Tensor:
    """[tiles_y, tiles_x] bool: the rasterizer's tiles that hold a True pixel of ``pixels`` [H, W] (bool)."""
    height, width = pixels.shape
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    padded = F.pad(pixels.to(torch.bool), (0, tiles_x * tile_size - width, 0, tiles_y * tile_size - height))
    words = tile_size // 8 if tile_size % 8 == 0 else 0
    if words:  # a tile row's bools read as int64 words, 8 pixels each: an 8th of the elements to reduce
        if not padded.is_contiguous() or padded.storage_offset() % 8:  # (F.pad returns an unpadded input as it is)
            padded = padded.clone(memory_format=torch.contiguous_format)
        packed = padded.view(torch.uint8).view(torch.int64).reshape(tiles_y, tile_size, tiles_x * words)
        return (packed != 0).any(dim=1).reshape(tiles_y, tiles_x, words).any(dim=2)
    # two any() passes, the contiguous axis first: a third of the time of one float amax over both axes
    return padded.reshape(tiles_y, tile_size, tiles_x, tile_size).any(dim=3).any(dim=1)
