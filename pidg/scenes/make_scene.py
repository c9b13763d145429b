"""``pidg make-scene KIND --out DIR``: a PIDG-style dynamic dataset from Blender's solvers, with its ground truth.

Writes (``DIR`` must not exist, or ``overwrite``)::

    transforms_{train,val,test}.json   camera_angle_x; frames: file_path, time (t in [0, 1]), transform_matrix
                                       (OpenGL camera-to-world), one common time grid (see pidg.scenes.capture)
    {split}/r_NNNN.png                 RGBA renders (Cycles, transparent background)
    mask/r_NNNN.png                    motion masks (255 = a dynamic object is seen at the pixel centre)
    depth/r_NNNN.npy                   float32 camera z (world units) at the pixel centre, 0 = background
    points3d.ply                       points sampled on the surfaces at t = 0, coloured from the training renders
    motion_gt/                         the ground truth (pidg.data.motion_gt): every dynamic vertex's position and
                                       velocity at every image time, faces, and per image the object-motion flow
    scene.json                         provenance: options, bpy version, render engine, timings

Velocities (world units per unit of dataset time) are central differences of Blender's own sub-frame evaluations,
x(f + h) and x(f - h) with h = ``VELOCITY_SUBFRAME`` of a frame, times the frames per unit of dataset time. Keyframed
motion is evaluated exactly at sub-frames (F-curves), so this is the derivative up to O(h^2). Simulations are read
from their caches, which Blender interpolates between frames (rigid bodies linearly, with quaternion slerp for
rotations; cloth and soft bodies with cubic Hermite curves through the solver's stored positions and velocities):
the velocity is then that interpolant's derivative at the frame, i.e. (x(f+1) - x(f-1)) / 2 per frame for rigid
bodies and the solver's own vertex velocity for cloth and soft bodies. ``meta.json`` records a check that sub-frames
really interpolate (a sub-frame position lies strictly between the frames').
"""
from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from pidg.data.motion_gt import FrameFlow, MotionObject, VertexMotion, write_frame_flow, write_motion_gt
from pidg.data.scene import parse_downscale
from pidg.data.ply import write_ply_points
from pidg.render.camera import Camera
from pidg.scenes import blender_build as bb
from pidg.scenes.capture import Shot, pidg_camera, shot_list
from pidg.scenes.ground_truth import Triangles, central_difference, object_motion_flow, sample_surface
from pidg.scenes.verify import verify_dataset, write_verify_report

logger = logging.getLogger(__name__)

VELOCITY_SUBFRAME = 0.05
"""h of the sub-frame central differences, in frames."""
SCENE_FILE = "scene.json"
MIN_SIDE, MAX_SIDE = 16, 4096


@dataclass(frozen=True)
class SceneOptions:
    """What to generate (defaults: 60 images of 200 x 200, 16 Cycles samples + denoising)."""

    kind: str
    frames: int = 60  # images, one per simulation frame
    width: int = 200
    height: int = 200
    samples: int = 16  # Cycles samples per pixel
    static_camera: bool = False
    held_out_on_orbit: bool = False  # held-out views on the training camera's path (novel times only; capture.Orbit)
    texture: str = "cells"  # surface pattern: bb.TEXTURES (cells; checker: the earlier scenes)
    seed: int = 0
    fps: int = 24
    denoise: bool = True
    points: int = 10_000  # points of points3d.ply
    verify: bool = False

    def __post_init__(self) -> None:
        if self.kind not in bb.KINDS:
            raise ValueError(f"scene kind {self.kind!r}: choose one of {', '.join(bb.KINDS)}")
        bb.check_texture(self.texture)
        if not 4 <= self.frames <= 2000:
            raise ValueError(f"--frames {self.frames}: give 4 to 2000 images")
        if not (MIN_SIDE <= self.width <= MAX_SIDE and MIN_SIDE <= self.height <= MAX_SIDE):
            raise ValueError(f"--resolution {self.width}x{self.height}: each side must be {MIN_SIDE}-{MAX_SIDE} px")
        if not 1 <= self.samples <= 4096:
            raise ValueError(f"--samples {self.samples}: give 1 to 4096")
        if not (1 <= self.fps <= 240 and self.points >= 1):
            raise ValueError(f"fps {self.fps} must be 1-240 and points {self.points} at least 1")


def parse_resolution(text: str) -> tuple[int, int]:
    """'200x200' -> (200, 200); ValueError naming the option otherwise."""
    try:
        size = parse_downscale(text)  # the parser of --data.downscale's WIDTHxHEIGHT form
    except ValueError:
        size = None
    if not isinstance(size, tuple):
        raise ValueError(f"--resolution {text!r}: give WIDTHxHEIGHT in pixels, e.g. 200x200")
    return size


def check_output(out: Path, overwrite: bool) -> None:
    """Refuse an existing ``out`` unless ``overwrite``; even then replace only an empty folder or an earlier
    make-scene output (it has scene.json), never any other folder."""
    if not out.exists():
        return
    if not overwrite:
        raise FileExistsError(f"{out}: already exists; give --overwrite to replace it, or another --out")
    if not out.is_dir() or (any(out.iterdir()) and not (out / SCENE_FILE).is_file()):
        raise FileExistsError(f"{out}: --overwrite replaces only an empty folder or an earlier make-scene output (with {SCENE_FILE})")


# ---- geometry over time -----------------------------------------------------------------------------------------
@dataclass
class SceneGeometry:
    """All surfaces over the sequence: static triangles once, dynamic vertices per time sample."""

    static_vertices: np.ndarray  # [Vs, 3]
    static_faces: np.ndarray  # [Fs, 3]
    dynamic_faces: np.ndarray  # [Fd, 3] into the dynamic vertices
    positions: np.ndarray  # [n + 1, Vd, 3]: image times, then one frame past the last
    velocities: np.ndarray  # [n, Vd, 3] world units per unit of dataset time
    objects: list[MotionObject]
    face_object: np.ndarray  # [Fs + Fd] index into static names + dynamic objects
    static_names: list[str]

    def triangles(self, sample: int) -> Triangles:
        """The whole scene at time sample ``sample`` (static faces first)."""
        vertices = np.concatenate([self.static_vertices, self.positions[sample]])
        faces = np.concatenate([self.static_faces, self.dynamic_faces + len(self.static_vertices)])
        dynamic = np.arange(len(faces)) >= len(self.static_faces)
        return Triangles(vertices, faces, dynamic)


def _concat_meshes(meshes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """(vertices, faces with offsets, owner index per face, vertex count per mesh)."""
    vertices, faces, owner, counts, offset = [], [], [], [], 0
    for k, (v, f) in enumerate(meshes):
        vertices.append(v)
        faces.append(f + offset)
        owner.append(np.full(len(f), k))
        counts.append(len(v))
        offset += len(v)
    empty = np.zeros((0, 3))
    return (np.concatenate(vertices) if vertices else empty, np.concatenate(faces) if faces else empty.astype(np.int64),
            np.concatenate(owner) if owner else np.zeros(0, np.int64), counts)


def _dynamic_vertices(built: bb.BuiltScene, frame: int, subframe: float = 0.0) -> np.ndarray:
    dg = bb.set_time(frame, subframe)
    return np.concatenate([bb.evaluated_mesh(name, dg, with_faces=False)[0] for name, _ in built.dynamic])


def collect_geometry(built: bb.BuiltScene, n_images: int) -> tuple[SceneGeometry, dict[str, float]]:
    """Positions at every image frame (and one past), sub-frame velocities, topology; and the sub-frame check."""
    first = built.image_frame(0)
    dg = bb.set_time(first)
    static = [bb.evaluated_mesh(name, dg) for name in built.static]
    dynamic = [bb.evaluated_mesh(name, dg) for name, _ in built.dynamic]
    static_v, static_f, static_owner, _ = _concat_meshes(static)  # type: ignore[arg-type]
    _, dynamic_f, dynamic_owner, counts = _concat_meshes(dynamic)  # type: ignore[arg-type]
    objects, start = [], 0
    for (name, kind), count in zip(built.dynamic, counts):
        objects.append(MotionObject(name, kind, start, count))
        start += count
    positions = np.stack([_dynamic_vertices(built, first + i) for i in range(n_images + 1)])
    frames_per_time = n_images - 1  # Blender frames per unit of dataset time
    h = VELOCITY_SUBFRAME
    velocities = np.stack([
        central_difference(_dynamic_vertices(built, first + i - 1, 1.0 - h), _dynamic_vertices(built, first + i, h), h)
        * frames_per_time for i in range(n_images)
    ])
    check = _subframe_check(built, positions, n_images // 2)
    geometry = SceneGeometry(static_v, static_f, dynamic_f, positions, velocities, objects,
                             np.concatenate([static_owner, dynamic_owner + len(built.static)]), list(built.static))
    return geometry, check


def _subframe_check(built: bb.BuiltScene, positions: np.ndarray, i: int) -> dict[str, float]:
    """Does a sub-frame interpolate? At image i: the largest step between the frames, and how far the half-frame
    position lies from either frame and from their midpoint (world units)."""
    half = _dynamic_vertices(built, built.image_frame(i), 0.5)
    a, b = positions[i], positions[i + 1]
    norm = lambda x: float(np.linalg.norm(x, axis=-1).max())  # noqa: E731
    return {"image": i, "frame_step": norm(b - a), "half_vs_frame": min(norm(half - a), norm(half - b)),
            "half_vs_linear_midpoint": norm(half - 0.5 * (a + b))}


# ---- writing ----------------------------------------------------------------------------------------------------------
def _write_frame_truth(root: Path, shot: Shot, camera: Camera, geometry: SceneGeometry, dt: float) -> np.ndarray:
    """Flow, mask and depth of one image; returns its depth map (float32)."""
    flow, dynamic, hits = object_motion_flow(camera, geometry.triangles(shot.index),
                                             geometry.triangles(shot.index + 1).vertices)
    write_frame_flow(root, shot.key, FrameFlow(flow, dynamic, shot.time, shot.time + dt))
    Image.fromarray(dynamic.astype(np.uint8) * 255, "L").save(root / "mask" / f"{shot.file_name}.png")
    depth = hits.depth.astype(np.float32)
    np.save(root / "depth" / f"{shot.file_name}.npy", depth)
    return depth


def _write_transforms(root: Path, shots: list[Shot], c2ws: dict[int, np.ndarray], fov_x: float) -> None:
    for split in ("train", "val", "test"):
        frames = [{"file_path": f"./{s.key}", "time": s.time, "transform_matrix": c2ws[s.index].tolist()}
                  for s in shots if s.split == split]
        if frames:
            (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}, indent=2))


def colour_points(points: np.ndarray, moving: np.ndarray, views: list[tuple[Camera, np.ndarray, np.ndarray, bool]]) -> np.ndarray:
    """Colours [P, 3] in [0, 1] of surface points at t = 0 from the renders that see them, NaN where none does.
    ``views`` are (camera, RGBA uint8, depth, taken at t = 0); points on moving objects (``moving``) are coloured
    from t = 0 views only. A view sees a point that projects inside the image onto an opaque pixel whose depth is
    within 2 % of the point's own."""
    rgb = np.full((len(points), 3), np.nan)
    for camera, rgba, depth, at_start in views:
        todo = np.isnan(rgb[:, 0]) & (at_start | ~moving)
        if not todo.any():
            continue
        uv, z = (a.numpy() for a in camera.project_points(torch.from_numpy(points[todo])))
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > camera.near) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        col, row = np.where(inside, col, 0), np.where(inside, row, 0)
        seen = inside & (rgba[row, col, 3] >= 128) & (np.abs(depth[row, col] - z) <= 0.02 * z)
        rgb[np.flatnonzero(todo)[seen]] = rgba[row[seen], col[seen], :3] / 255.0
    return rgb


DYNAMIC_POINT_SHARE = 0.3
"""Share of points3d.ply sampled on the moving objects (the rest on static surfaces), whatever their areas: the
floor would otherwise take nearly all of them."""


def _write_points(root: Path, geometry: SceneGeometry, views: list[tuple[Camera, np.ndarray, np.ndarray, bool]],
                  n: int, seed: int) -> int:
    """points3d.ply: ``n`` points on the surfaces at t = 0 (``DYNAMIC_POINT_SHARE`` of them on moving objects), coloured
    from the training renders. Like structure from motion, static points no training view sees are left out; moving
    ones the first view does not see take their object's mean colour. Returns the number written."""
    rng = np.random.default_rng(seed + 1)
    scene0 = geometry.triangles(0)
    parts = []
    for moving, count in ((True, round(n * DYNAMIC_POINT_SHARE)), (False, n - round(n * DYNAMIC_POINT_SHARE))):
        faces = np.flatnonzero(scene0.dynamic == moving)
        if count and len(faces):
            points, face = sample_surface(scene0.vertices, scene0.faces[faces], count, rng)
            parts.append((points, geometry.face_object[faces[face]], np.full(count, moving)))
    points, owner, moving = (np.concatenate(p) for p in zip(*parts))
    rgb = colour_points(points, moving, views)
    for k in np.unique(owner[moving]):
        mine, seen = owner == k, ~np.isnan(rgb[:, 0])
        rgb[mine & ~seen] = rgb[mine & seen].mean(axis=0) if (mine & seen).any() else 0.5
    keep = ~np.isnan(rgb[:, 0])
    write_ply_points(root / "points3d.ply", points[keep], rgb[keep])
    return int(keep.sum())


# ---- the whole job ------------------------------------------------------------------------------------------------------
def make_scene(options: SceneOptions, out: Path | str, overwrite: bool = False) -> dict[str, Any]:
    """Build, simulate, render and write the dataset in ``out`` (module docstring); with ``options.verify`` also check
    the ground truth (``out/motion_gt/verify.json``). Returns the summary written to ``out/scene.json``."""
    root = Path(out)
    check_output(root, overwrite)  # before bpy: a wrong --out fails at once
    bpy = bb.import_bpy()
    if root.exists():
        shutil.rmtree(root)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    n = options.frames
    built = bb.build_scene(options.kind, n, options.seed, options.fps, options.static_camera, options.texture,
                           options.held_out_on_orbit)
    geometry, subframe = collect_geometry(built, n)
    timings["simulate_s"] = time.perf_counter() - start

    for sub in ("mask", "depth", "train", "val", "test"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    setup = bb.configure_render(options.width, options.height, options.samples, options.seed, options.denoise)
    if setup.note:
        logger.warning("make-scene: %s", setup.note)
    shots = shot_list(n)
    dt = 1.0 / (n - 1)
    fov_x = math.radians(bb.FOV_X_DEG)
    c2ws = {s.index: built.orbit.camera_to_world(s) for s in shots}
    cameras = {s.index: pidg_camera(c2ws[s.index], options.width, options.height, fov_x) for s in shots}
    truth_s = render_s = 0.0
    views = []
    for shot in shots:
        t0 = time.perf_counter()
        depth = _write_frame_truth(root, shot, cameras[shot.index], geometry, dt)
        t1 = time.perf_counter()
        bb.set_time(built.image_frame(shot.index))
        image_path = root / f"{shot.key}.png"
        bb.render_image(built.camera, c2ws[shot.index], image_path)
        t2 = time.perf_counter()
        truth_s, render_s = truth_s + t1 - t0, render_s + t2 - t1
        if shot.split == "train":
            views.append((cameras[shot.index], np.asarray(Image.open(image_path).convert("RGBA")), depth, shot.index == 0))
        if (shot.index + 1) % 10 == 0 or shot.index == n - 1:
            logger.info("make-scene %s: %d/%d images (%.2f s a render)", options.kind, shot.index + 1, n, render_s / (shot.index + 1))
    timings.update(ground_truth_s=truth_s, render_s=render_s, render_s_per_image=render_s / n)

    _write_transforms(root, shots, c2ws, fov_x)
    n_points = _write_points(root, geometry, views, options.points, options.seed)
    dynamic_faces = geometry.dynamic_faces
    write_motion_gt(root, dt, geometry.objects, VertexMotion(np.array([s.time for s in shots]), geometry.positions[:n].astype(np.float32),
                    geometry.velocities.astype(np.float32), dynamic_faces), duration_s=(n - 1) / options.fps,
                    extra=_motion_meta(built, subframe))
    timings["total_s"] = time.perf_counter() - start
    summary = {
        "generator": "pidg make-scene", "options": asdict(options), "bpy": bpy.app.version_string,
        "render": asdict(setup), "objects": {"dynamic": [o.__dict__ for o in geometry.objects], "static": geometry.static_names},
        "images": {split: sum(s.split == split for s in shots) for split in ("train", "val", "test")},
        "points3d": n_points, "blender_frame_of_image_0": built.image_frame(0), "fps": options.fps, "timings": timings,
    }
    (root / SCENE_FILE).write_text(json.dumps(summary, indent=2))
    if options.verify:
        checks = blender_checks(built, geometry, shots, c2ws, cameras, root)
        report = verify_dataset(root, checks)
        write_verify_report(root, report)
        summary["verify"] = report
    return summary


def _motion_meta(built: bb.BuiltScene, subframe: dict[str, float]) -> dict[str, Any]:
    return {
        "generator": "pidg make-scene (Blender)",
        "vertices": "every vertex of each dynamic object's evaluated mesh (after modifiers and physics), world units",
        "velocity_method": f"central differences of Blender sub-frame evaluations at +-{VELOCITY_SUBFRAME} frame, x frames "
                           "per unit of dataset time (simulations: derivative of Blender's cache interpolation)",
        "subframe_check": subframe,
        "image_i_is_blender_frame": f"{built.image_frame(0)} + i at {built.fps} fps",
        "last_image_flow": "uses the simulated frame after the last image (next_time = 1 + frame_interval)",
    }


def blender_checks(built: bb.BuiltScene, geometry: SceneGeometry, shots: list[Shot], c2ws: dict[int, np.ndarray],
                   cameras: dict[int, Camera], root: Path) -> dict[str, Any]:
    """Blender's own view of three images (first, middle, last): its camera projection against pidg's camera, and its
    ray cast (Scene.ray_cast, ~1000 rays an image) against the stored depth and masks."""
    names = {name for name, _ in built.dynamic}
    camera_px, depth_err = [], []
    totals = {"rays": 0, "hit_mismatch": 0, "dynamic_mismatch": 0}
    for shot in (shots[0], shots[len(shots) // 2], shots[-1]):
        camera = cameras[shot.index]
        dg = bb.set_time(built.image_frame(shot.index))
        vertices = geometry.triangles(shot.index).vertices
        sample = vertices[:: max(1, len(vertices) // 500)]
        camera_px.append(bb.camera_agreement(built.camera, c2ws[shot.index], camera, sample))
        depth = np.load(root / "depth" / f"{shot.file_name}.npy")
        dynamic = np.asarray(Image.open(root / "mask" / f"{shot.file_name}.png")) > 0
        stride = max(1, round(math.sqrt(camera.width * camera.height / 1000)))
        found = bb.ray_cast_agreement(dg, camera, depth, dynamic, names, stride)
        depth_err += found.pop("depth_abs_error")
        for key in totals:
            totals[key] += found[key]
    err = np.asarray(depth_err) if depth_err else np.zeros(1)
    return {
        "camera_projection_max_px": float(max(camera_px)),
        "ray_cast": {**totals, "depth_median": float(np.median(err)), "depth_p95": float(np.percentile(err, 95)),
                     "depth_max": float(err.max())},
    }
