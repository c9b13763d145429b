"""What the viewer shows, without the web server: cameras from the browser's pose, one picture per view mode, and
the progressive-quality rule. Nothing here imports viser, so it is tested and timed on its own.

Conventions: viser reports the browser's camera as T_world_camera in OpenCV axes (x right, y down, z forward, the
same as :class:`pidg.render.Camera`), its vertical field of view in radians and the canvas size in pixels. Time is
dataset time in [0, 1]. Velocities are drawn in pixels per training-frame interval; stress is the Frobenius norm of
the material field's sigma on a colour scale that stays fixed while the time changes.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.evaluation.images import colorize_scalar, to_uint8
from pidg.evaluation.visualize import dynamic_split_image, material_field_images
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.material_field import stress_magnitude
from pidg.render import Camera
from pidg.render.projection import quat_to_rotmat, rotmat_to_quat

COLOUR = "colour"
DEPTH = "depth"
VELOCITY_ARROWS = "velocity (arrows)"
VELOCITY_COLOURS = "velocity (colour wheel)"
STRESS = "stress magnitude"
SPLIT = "dynamic (red) / static (blue)"


def view_modes(model: DynamicGaussians) -> list[str]:
    """The pictures this model can show: colour and depth always; velocity and stress with a material field; the
    dynamic/static split once decoupling has run."""
    modes = [COLOUR, DEPTH]
    if model.material_field is not None:
        modes += [VELOCITY_ARROWS, VELOCITY_COLOURS, STRESS]
    if model.dynamic_mask is not None:
        modes.append(SPLIT)
    return modes


# ---- cameras ---------------------------------------------------------------------------------------------------
def camera_from_pose(
    wxyz: np.ndarray, position: np.ndarray, fov_y: float, width: int, height: int, near: float = 0.01, far: float = 1e10
) -> Camera:
    """A pidg camera from a viser pose: rotation ``wxyz`` and ``position`` of the camera in the world (OpenCV
    axes), vertical field of view ``fov_y`` in radians, square pixels."""
    rotation = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, np.float64))[None])[0].numpy()  # camera -> world
    w2c = np.eye(4)
    w2c[:3, :3] = rotation.T
    w2c[:3, 3] = -rotation.T @ np.asarray(position, np.float64)
    fy = 0.5 * height / math.tan(0.5 * fov_y)
    near = max(float(near), 1e-4)
    return Camera(torch.tensor(w2c, dtype=torch.float32), fy, fy, 0.5 * width, 0.5 * height, width, height, near, max(float(far), near * 2))


def pose_of_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a pidg camera in the world, as viser wants them for a frustum or the browser camera."""
    w2c = camera.world_to_camera.detach().to(torch.float64).cpu().numpy()
    rotation = w2c[:3, :3].T
    wxyz = rotmat_to_quat(torch.from_numpy(rotation)[None])[0].numpy()
    return wxyz * (1.0 if wxyz[0] >= 0 else -1.0), -rotation @ w2c[:3, 3]  # the one with w >= 0


# ---- progressive quality ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Quality:
    """How the viewer trades resolution for speed: while the camera moves (or the time plays) frames are rendered at
    ``preview_scale`` of the canvas, and once nothing has changed for ``rest_seconds`` at full size, capped at
    ``max_side`` pixels (the browser stretches the picture to its canvas)."""

    preview_scale: float = 0.25
    rest_seconds: float = 0.25
    max_side: int = 1600
    jpeg_quality_preview: int = 70
    jpeg_quality_full: int = 90

    def __post_init__(self) -> None:
        if not 0.05 <= self.preview_scale <= 1.0:
            raise ValueError(f"preview scale {self.preview_scale:g}: must be in [0.05, 1] (a fraction of the canvas size)")
        if self.max_side < 64:
            raise ValueError(f"max side {self.max_side}: must be >= 64 pixels")
        if not self.rest_seconds >= 0:
            raise ValueError(f"rest seconds {self.rest_seconds:g}: must be >= 0")

    def size(self, width: int, height: int, full: bool) -> tuple[int, int]:
        """The rendered (width, height) for a canvas of ``width`` x ``height``, in full quality or as a preview."""
        width, height = max(int(width), 1), max(int(height), 1)
        scale = min(1.0, self.max_side / max(width, height)) * (1.0 if full else self.preview_scale)
        return max(16, round(width * scale)), max(16, round(height * scale))


# ---- pictures ---------------------------------------------------------------------------------------------------
@dataclass
class RenderedView:
    """One picture: uint8 [H, W, 3], what it shows, and how long it took to render (ms, on the model's device)."""

    image: np.ndarray
    mode: str
    t: float
    render_ms: float
    caption: str = ""


class ViewRenderer:
    """Renders views of one model at any time and camera; thread-safe (one render at a time: the numba kernel and
    the GPU are shared), and keeps the Gaussians of the last time asked for, so that a moving camera at a fixed time
    only rasterizes."""

    def __init__(self, model: DynamicGaussians) -> None:
        self.model = model
        self.modes = view_modes(model)
        self._lock = threading.Lock()
        self._state: tuple[float, DeformedGaussians] | None = None
        self._stress_scale: float | None = None

    def state_at(self, t: float) -> DeformedGaussians:
        if self._state is None or self._state[0] != t:
            self._state = (t, self.model.at(t))
        return self._state[1]

    @property
    def stress_scale(self) -> float:
        """The stress value drawn brightest: the 99th percentile of the Gaussians' |sigma|_F over five times (fixed for
        the session, so colours mean the same thing at every time and view)."""
        if self._stress_scale is None:
            values = []
            for t in (0.0, 0.25, 0.5, 0.75, 1.0):
                _, sigma = self.model.field_values(self.model.at(t).means, t)
                values.append(stress_magnitude(sigma))
            self._stress_scale = max(float(torch.quantile(torch.cat(values).float().cpu(), 0.99)), 1e-12)
        return self._stress_scale

    @torch.no_grad()
    def render(self, camera: Camera, t: float, mode: str = COLOUR) -> RenderedView:
        """The picture of ``mode`` (one of :attr:`modes`) from ``camera`` at dataset time ``t``."""
        if mode not in self.modes:
            raise ValueError(f"view mode {mode!r}: this run shows {', '.join(self.modes)}")
        with self._lock:
            device = self.model.device
            camera = camera.to(device)
            start = time.perf_counter()
            image, caption = self._picture(camera, float(t), mode)
            out = to_uint8(image)
            return RenderedView(out, mode, float(t), 1000.0 * (time.perf_counter() - start), caption)

    def _picture(self, camera: Camera, t: float, mode: str) -> tuple[Tensor, str]:
        model = self.model
        if mode in (COLOUR, DEPTH):
            out = model.render_state(self.state_at(t), camera)
            if mode == COLOUR:
                return out.rgb, ""
            valid = out.alpha > 0.5
            depth = out.depth_normalized()
            if not bool(valid.any()):
                return torch.zeros_like(out.rgb), "depth: nothing opaque in view"
            lo, hi = float(depth[valid].min()), float(depth[valid].max())
            return colorize_scalar(depth, valid=valid), f"depth {lo:.3g} (dark) to {hi:.3g} (yellow) world units"
        frame = Frame(camera, t, torch.zeros(camera.height, camera.width, 3, dtype=torch.uint8))
        if mode == SPLIT:
            return dynamic_split_image(model, frame), "red: dynamic Gaussians, blue: static"
        dt = model.time_axis.frame_dt  # one training-frame interval, in the field's physics time units
        images = material_field_images(model, frame, dt, max_stress=self.stress_scale if mode == STRESS else None)
        if mode == STRESS:
            return images.stress, f"|sigma| 0 (dark) to {images.max_stress:.3g} (yellow), field units"
        picture = images.quiver if mode == VELOCITY_ARROWS else images.velocity
        return picture, f"largest on screen: {images.max_velocity_px:.3g} px per training frame"


# ---- frame time -----------------------------------------------------------------------------------------------------
def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """The JPEG the browser receives (OpenCV, as viser encodes it)."""
    import cv2

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()


def measure_frame_times(
    renderer: ViewRenderer, camera: Camera, quality: Quality | None = None, repeats: int = 5, t: float = 0.5
) -> dict[str, Any]:
    """Median milliseconds of the viewer's frames at ``camera``'s size (full) and as a preview, when only the camera
    moves (the Gaussians at this time are kept: rasterize + JPEG) and when the time changes too (deform + rasterize +
    JPEG); for the other view modes, camera moving (``modes``: mode -> full_ms, preview_ms, half the repeats). The
    network and the browser's drawing are not included."""
    quality = quality or Quality()
    device = renderer.model.device
    full_size = quality.size(camera.width, camera.height, True)
    preview_size = quality.size(camera.width, camera.height, False)
    result: dict[str, float | int | str] = {
        "width": full_size[0], "height": full_size[1], "preview_width": preview_size[0], "preview_height": preview_size[1],
        "gaussians": renderer.model.num_gaussians, "device": str(device), "repeats": repeats,
    }
    for name, (w, h), jpeg in (("full", full_size, quality.jpeg_quality_full), ("preview", preview_size, quality.jpeg_quality_preview)):
        cam = camera.resized(w, h)
        renderer.render(cam, t)  # warm-up: compiled kernels, the Gaussians at t
        for kind in ("camera_moves", "time_changes"):
            samples = []
            for i in range(repeats):
                start = time.perf_counter()
                view = renderer.render(cam, t if kind == "camera_moves" else t + 1e-3 * (i + 1))
                encode_jpeg(view.image, jpeg)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                samples.append(1000.0 * (time.perf_counter() - start))
            result[f"{name}_{kind}_ms"] = float(np.median(samples))
    modes: dict[str, dict[str, float]] = {}
    for mode in renderer.modes[1:]:  # the other pictures, camera moving (their colour scales set in the warm-up)
        modes[mode] = {}
        for name, (w, h), jpeg in (("full", full_size, quality.jpeg_quality_full), ("preview", preview_size, quality.jpeg_quality_preview)):
            cam = camera.resized(w, h)
            renderer.render(cam, t, mode)
            samples = []
            for _ in range(max(1, repeats // 2)):
                start = time.perf_counter()
                encode_jpeg(renderer.render(cam, t, mode).image, jpeg)
                samples.append(1000.0 * (time.perf_counter() - start))
            modes[mode][f"{name}_ms"] = float(np.median(samples))
    result["modes"] = modes
    return result
