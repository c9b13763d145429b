"""Ground-truth motion a dataset may carry beside its images (generated scenes: ``pidg make-scene``, the embedded
procedural scene), so that the learned motion can be scored against the truth and not only against pixels.

Layout (``DIR`` is the dataset folder, beside ``transforms_*.json``)::

    DIR/motion_gt/meta.json      {"format": "pidg-motion-gt-1", "frame_interval": dt, "duration_s": ..., "units": {...},
                                  "objects": [{"name": ..., "kind": ..., "first_vertex": i0, "n_vertices": n}, ...]}
    DIR/motion_gt/vertices.npz   times [T] float64          dataset time t in [0, 1] of each sample
                                 positions [T, V, 3] float32  world position of every dynamic vertex (world units)
                                 velocities [T, V, 3] float32 dx/dt, world units per unit of dataset time
                                 faces [F, 3] int64            triangles (vertex indices; topology is constant)
    DIR/motion_gt/flow/<frame key>.npz, one per image; the key is the frame's ``file_path`` without extension
                                 (``Frame.name``, e.g. ``train/r_0002``):
                                 flow [H, W, 2] float32   object motion in pixels (dx right, dy down) from the frame's
                                                          time t to t + frame_interval, seen by the frame's camera held
                                                          fixed (camera motion excluded); NaN where no surface is seen
                                 dynamic [H, W] bool      the pixel sees a dynamic (moving) object
                                 time, next_time          float64 scalars: t and t + frame_interval

Units. Times are dataset time (the recording spans [0, 1]); velocities are world units per unit of dataset time,
so a particle moves about ``velocity * frame_interval`` world units between consecutive frames; dividing by
``duration_s`` (the recording's length in seconds, when the generator knows it) gives world units per second.
Flow is in pixels of the image at the dataset's full resolution (:func:`resize_flow` rescales it with the image).
Static surfaces have flow exactly 0; background pixels are NaN.
"""
from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pidg.data.scene import DatasetError
from pidg.render.camera import Camera

MOTION_GT_DIR = "motion_gt"
MOTION_GT_FORMAT = "pidg-motion-gt-1"
UNITS = {
    "time": "dataset time t in [0, 1] (the whole recording)",
    "positions": "world units",
    "velocities": "world units per unit of dataset time (x frame_interval: world units per frame)",
    "flow": "pixels at the dataset's full image resolution, dx right, dy down",
}


@dataclass(frozen=True)
class MotionObject:
    """One dynamic object's slice of the vertex arrays."""

    name: str
    kind: str  # "rigid", "cloth", "soft", "kinematic", "analytic", ...
    first_vertex: int
    n_vertices: int


@dataclass
class VertexMotion:
    """Every dynamic vertex's trajectory, sampled at ``times`` (see the module docstring for units)."""

    times: np.ndarray  # [T] float64
    positions: np.ndarray  # [T, V, 3] float32
    velocities: np.ndarray  # [T, V, 3] float32
    faces: np.ndarray  # [F, 3] int64

    def index_of(self, t: float, tol: float = 1e-6) -> int:
        """The sample at dataset time ``t``; KeyError when none lies within ``tol``."""
        i = int(np.argmin(np.abs(self.times - t)))
        if abs(float(self.times[i]) - t) > tol:
            raise KeyError(f"no ground-truth vertex sample at t = {t:.6f} (nearest {float(self.times[i]):.6f})")
        return i


@dataclass
class FrameFlow:
    """Ground-truth object-motion flow of one image (see the module docstring)."""

    flow: np.ndarray  # [H, W, 2] float32, NaN on background
    dynamic: np.ndarray  # [H, W] bool
    time: float
    next_time: float

    @property
    def surface(self) -> np.ndarray:
        """[H, W] bool: a surface is seen (the flow is defined)."""
        return np.isfinite(self.flow).all(axis=-1)


@dataclass
class MotionGroundTruth:
    """A dataset's ground-truth motion: metadata, vertex trajectories and the per-image flows (read lazily)."""

    root: Path  # the motion_gt folder
    frame_interval: float
    objects: list[MotionObject]
    vertices: VertexMotion
    duration_s: float | None = None
    meta: dict = field(default_factory=dict)

    def flow_path(self, key: str) -> Path:
        return self.root / "flow" / f"{key}.npz"

    def vertex_objects(self, unowned: int = -1) -> Tensor:
        """[V] long: the index in ``objects`` of each vertex's object (``unowned`` for a vertex in none)."""
        owner = torch.full((self.vertices.positions.shape[1],), unowned, dtype=torch.long)
        for index, obj in enumerate(self.objects):
            owner[obj.first_vertex:obj.first_vertex + obj.n_vertices] = index
        return owner

    def frame_flow(self, key: str) -> FrameFlow:
        """The flow of the image whose ``Frame.name`` is ``key``; DatasetError naming the file when it is missing
        or malformed."""
        return read_frame_flow(self.flow_path(key))


def has_motion_gt(dataset_dir: Path | str) -> bool:
    return (Path(dataset_dir) / MOTION_GT_DIR / "meta.json").is_file()


def write_motion_gt(
    dataset_dir: Path | str,
    frame_interval: float,
    objects: list[MotionObject],
    vertices: VertexMotion,
    duration_s: float | None = None,
    extra: dict | None = None,
) -> Path:
    """Write ``meta.json`` and ``vertices.npz`` (flows are written per image with :func:`write_frame_flow`)."""
    root = Path(dataset_dir) / MOTION_GT_DIR
    root.mkdir(parents=True, exist_ok=True)
    v = vertices
    if v.positions.shape != v.velocities.shape or v.positions.ndim != 3 or v.positions.shape[0] != len(v.times):
        raise ValueError(f"write_motion_gt: positions {v.positions.shape} / velocities {v.velocities.shape} / times {len(v.times)} disagree")
    np.savez_compressed(
        root / "vertices.npz",
        times=np.asarray(v.times, np.float64),
        positions=np.asarray(v.positions, np.float32),
        velocities=np.asarray(v.velocities, np.float32),
        faces=np.asarray(v.faces, np.int64).reshape(-1, 3),
    )
    meta = {
        "format": MOTION_GT_FORMAT,
        "frame_interval": float(frame_interval),
        "duration_s": duration_s,
        "units": UNITS,
        "objects": [o.__dict__ for o in objects],
        **(extra or {}),
    }
    (root / "meta.json").write_text(json.dumps(meta, indent=2))
    return root


def write_frame_flow(dataset_dir: Path | str, key: str, frame: FrameFlow) -> Path:
    """Write one image's flow; ``key`` is the frame's file_path without extension (e.g. ``train/r_0002``)."""
    path = Path(dataset_dir) / MOTION_GT_DIR / "flow" / f"{key}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        flow=np.asarray(frame.flow, np.float32),
        dynamic=np.asarray(frame.dynamic, bool),
        time=np.float64(frame.time),
        next_time=np.float64(frame.next_time),
    )
    return path


def read_frame_flow(path: Path) -> FrameFlow:
    if not path.is_file():
        raise DatasetError(path, "ground-truth flow file not found")
    try:
        with np.load(path) as z:
            flow, dynamic = z["flow"].astype(np.float32), z["dynamic"].astype(bool)
            time, next_time = float(z["time"]), float(z["next_time"])
    except (KeyError, ValueError, OSError, zipfile.BadZipFile) as err:
        raise DatasetError(path, f"not a ground-truth flow file (needs flow, dynamic, time, next_time): {err}") from None
    if flow.ndim != 3 or flow.shape[-1] != 2 or dynamic.shape != flow.shape[:2]:
        raise DatasetError(path, f"flow must be [H, W, 2] with dynamic [H, W], got {flow.shape} and {dynamic.shape}")
    return FrameFlow(flow, dynamic, time, next_time)


def read_motion_gt(dataset_dir: Path | str) -> MotionGroundTruth:
    """The ground truth in ``DIR/motion_gt``; DatasetError naming the file for anything missing or malformed."""
    root = Path(dataset_dir) / MOTION_GT_DIR
    meta_path, vert_path = root / "meta.json", root / "vertices.npz"
    if not meta_path.is_file():
        raise DatasetError(meta_path, "no ground-truth motion here (generated scenes carry it: pidg make-scene)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as err:
        raise DatasetError(meta_path, f"malformed json: {err}") from None
    if meta.get("format") != MOTION_GT_FORMAT:
        raise DatasetError(meta_path, f"format {meta.get('format')!r}, expected {MOTION_GT_FORMAT!r}")
    try:
        interval = float(meta["frame_interval"])
        objects = [MotionObject(**o) for o in meta["objects"]]
    except (KeyError, TypeError, ValueError) as err:
        raise DatasetError(meta_path, f"needs frame_interval and objects (name, kind, first_vertex, n_vertices): {err}") from None
    if not interval > 0:
        raise DatasetError(meta_path, f"frame_interval must be positive, got {interval}")
    if not vert_path.is_file():
        raise DatasetError(vert_path, "ground-truth vertex file not found")
    try:
        with np.load(vert_path) as z:
            vertices = VertexMotion(z["times"].astype(np.float64), z["positions"].astype(np.float32),
                                    z["velocities"].astype(np.float32), z["faces"].astype(np.int64))
    except (KeyError, ValueError, OSError, zipfile.BadZipFile) as err:
        raise DatasetError(vert_path, f"needs times, positions, velocities, faces: {err}") from None
    p = vertices.positions
    if p.ndim != 3 or p.shape[-1] != 3 or p.shape != vertices.velocities.shape or p.shape[0] != len(vertices.times):
        raise DatasetError(vert_path, f"positions {p.shape} / velocities {vertices.velocities.shape} / times "
                                      f"{vertices.times.shape} must be [T, V, 3], [T, V, 3], [T]")
    if not (np.isfinite(p).all() and np.isfinite(vertices.velocities).all()):
        raise DatasetError(vert_path, "positions or velocities hold NaN or infinite values")
    duration = meta.get("duration_s")
    return MotionGroundTruth(root, interval, objects, vertices, None if duration is None else float(duration), meta)


def resize_flow(flow: Tensor, dynamic: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Flow [H, W, 2] (NaN = background) and mask [H, W] at image size (width, height): nearest-neighbour samples
    (no blending across object edges), vectors scaled by the size ratio so they stay in pixels of the new image."""
    h, w = flow.shape[:2]
    new_w, new_h = size
    if (new_w, new_h) == (w, h):
        return flow, dynamic
    ys = ((torch.arange(new_h, dtype=torch.float64) + 0.5) * h / new_h).floor().long().clamp_max(h - 1)
    xs = ((torch.arange(new_w, dtype=torch.float64) + 0.5) * w / new_w).floor().long().clamp_max(w - 1)
    out = flow[ys][:, xs].clone()
    out[..., 0] *= new_w / w
    out[..., 1] *= new_h / h
    return out, dynamic[ys][:, xs]


# ---- flows as composited displacements (the generator's ground truth and the evaluation's model flow alike) ----------
SURFACE_MIN_ALPHA = 0.5
"""A pixel sees a surface (its flow is defined) where the composited alpha is at least this."""


def projected_displacement(camera: Camera, points_t: Tensor, points_t1: Tensor) -> Tensor:
    """Pixels [N, 2] that each point moves in ``camera`` (held fixed) from ``points_t`` [N, 3] to ``points_t1``;
    rows are 0 where either end is not in front of the camera. Identical points give exactly 0."""
    uv0, z0 = camera.project_points(points_t)
    uv1, z1 = camera.project_points(points_t1)
    ahead = ((z0 > camera.near) & (z1 > camera.near)).unsqueeze(-1)
    return torch.where(ahead, uv1 - uv0, torch.zeros_like(uv0))


def composited_flow(features: Tensor, alpha: Tensor, min_alpha: float = SURFACE_MIN_ALPHA) -> Tensor:
    """Per-pixel flow [H, W, C] from displacement channels [H, W, C] composited with the colour weights (as
    ``rasterize(..., features=)`` does): their weighted mean ``features / alpha``, so a pixel's flow is the
    colour-weighted motion of what it sees; NaN where ``alpha < min_alpha`` (no surface)."""
    seen = (alpha >= min_alpha).unsqueeze(-1)
    return torch.where(seen, features / alpha.clamp_min(min_alpha).unsqueeze(-1), torch.full_like(features, float("nan")))
