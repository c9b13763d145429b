"""The pinhole camera: the single place where camera conventions are converted.

Internally every camera is OpenCV-style: a world-to-camera rigid transform (x right, y down, z forward) and
intrinsics in pixels, with pixel (i, j) covering [j, j+1) x [i, i+1), so its centre is at (j + 0.5, i + 0.5).
Dataset readers build cameras with the constructors below; nothing else touches conventions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

# OpenGL/Blender camera axes (x right, y up, looking along -z) -> OpenCV axes (x right, y down, looking along +z).
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def _check_rigid(matrix: Tensor, what: str, atol: float = 1e-3) -> None:
    """Raise if ``matrix`` is not a 4x4 rigid transform (rotation + translation, last row 0 0 0 1)."""
    if tuple(matrix.shape) != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {tuple(matrix.shape)}")
    m = matrix.detach().to(torch.float64).cpu()
    if not torch.isfinite(m).all():
        raise ValueError(f"{what}: matrix contains NaN or infinite values")
    if not torch.allclose(m[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=atol):
        raise ValueError(f"{what}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    err = (rot @ rot.T - torch.eye(3, dtype=torch.float64)).abs().max().item()
    if err > atol or torch.linalg.det(rot).item() < 0:
        raise ValueError(
            f"{what}: the 3x3 block is not a rotation (|R R^T - I| = {err:.2e}, det = {torch.linalg.det(rot).item():.3f})"
        )


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in OpenCV convention.

    ``world_to_camera`` is a 4x4 rigid transform (float32 or float64). ``near``/``far`` bound the depth range
    (camera z) of the Gaussians that are drawn.
    """

    world_to_camera: Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"Camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not (0 < self.near < self.far):
            raise ValueError(f"Camera: need 0 < near < far, got near={self.near}, far={self.far}")
        _check_rigid(self.world_to_camera, "Camera.world_to_camera")

    # ---- constructors -------------------------------------------------------------------------------------
    @classmethod
    def from_fov(
        cls,
        camera_to_world_gl: Tensor,
        width: int,
        height: int,
        fov_x: float,
        fov_y: float | None = None,
        near: float = 0.01,
        far: float = 1e10,
    ) -> "Camera":
        """Camera from an OpenGL/Blender camera-to-world matrix and field(s) of view in radians.

        ``fov_x`` is the horizontal field of view (D-NeRF's ``camera_angle_x``); without ``fov_y`` pixels are
        square (fy = fx), which is right for non-square images too (the vertical FoV follows from the aspect).
        """
        c2w = torch.as_tensor(camera_to_world_gl, dtype=torch.float64)
        _check_rigid(c2w, "camera-to-world matrix")
        fx = 0.5 * width / math.tan(0.5 * fov_x)
        fy = fx if fov_y is None else 0.5 * height / math.tan(0.5 * fov_y)
        w2c = torch.linalg.inv(c2w @ _GL_TO_CV)
        return cls(w2c.to(torch.float32), fx, fy, 0.5 * width, 0.5 * height, width, height, near, far)

    @classmethod
    def look_at(
        cls,
        eye: tuple[float, float, float],
        target: tuple[float, float, float],
        up: tuple[float, float, float],
        width: int,
        height: int,
        fov_x: float,
        near: float = 0.01,
        far: float = 1e10,
    ) -> "Camera":
        """Camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image."""
        eye_t, target_t, up_t = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
        forward = target_t - eye_t
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, up_t)
        if right.norm() < 1e-9:
            raise ValueError("Camera.look_at: 'up' is parallel to the viewing direction")
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = rot
        w2c[:3, 3] = -rot @ eye_t
        fx = 0.5 * width / math.tan(0.5 * fov_x)
        return cls(w2c.to(torch.float32), fx, fx, 0.5 * width, 0.5 * height, width, height, near, far)

    # ---- derived quantities -------------------------------------------------------------------------------
    @property
    def intrinsics(self) -> Tensor:
        """3x3 intrinsic matrix K (float32)."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def camera_center(self) -> Tensor:
        """Camera position in world coordinates [3]."""
        w2c = self.world_to_camera
        return -w2c[:3, :3].T @ w2c[:3, 3]

    @property
    def viewing_direction(self) -> Tensor:
        """The camera's +z axis (where it looks) in world coordinates [3], a unit vector."""
        return self.world_to_camera[2, :3]

    @property
    def fov_x(self) -> float:
        return 2.0 * math.atan(0.5 * self.width / self.fx)

    @property
    def fov_y(self) -> float:
        return 2.0 * math.atan(0.5 * self.height / self.fy)

    def project_points(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] -> pixel coordinates [N, 2] (centres at +0.5) and camera depth [N].

        Points at or behind the camera get finite but meaningless pixels: test ``depth > near`` before use.
        """
        w2c = self.world_to_camera.to(device=points.device, dtype=points.dtype)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        inv_z = 1.0 / z.clamp_min(1e-6)
        uv = torch.stack([self.fx * p[:, 0] * inv_z + self.cx, self.fy * p[:, 1] * inv_z + self.cy], dim=-1)
        return uv, z

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera rendering an image of another size (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width, height=height)

    def to(self, device: torch.device | str) -> "Camera":
        """The same camera with its matrix on ``device`` (itself when it is there already: no copy, no check)."""
        if self.world_to_camera.device == torch.device(device):
            return self
        return replace(self, world_to_camera=self.world_to_camera.to(device))


def orbit_camera_to_world(target: Tensor | tuple[float, float, float], radius: float, azimuth: float, elevation: float) -> Tensor:
    """OpenGL camera-to-world [4, 4] float64 (columns right, up, backward, eye) of a camera on the sphere of
    ``radius`` (world units) around ``target``, upright (world z up) and looking at ``target``; angles in radians.
    The camera rigs of the generated scenes (procedural demo, ``pidg make-scene``) all come from here."""
    t = torch.as_tensor(target, dtype=torch.float64)
    eye = t + radius * torch.tensor(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)], dtype=torch.float64
    )
    forward = (t - eye) / (t - eye).norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = right / right.norm()
    up = torch.linalg.cross(right, forward)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, eye
    return c2w
