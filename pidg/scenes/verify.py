"""``pidg make-scene --verify``: the ground truth checked independently, from the files as pidg reads them (no bpy).

* **Vertex flow**: every dynamic vertex at t and t + dt (``motion_gt/vertices.npz``) projected with pidg's camera of
  the frame (built by the dataset reader from the json); their displacement against the stored flow sampled
  bilinearly at the vertex's pixel position. A vertex counts as visible when the four pixels around it see a dynamic
  surface whose (bilinear) depth is within 0.5 % of the vertex's camera z. Residuals in pixels.
* **Vertex depth**: the same visible vertices' camera z against the stored depth (world units); bounded by the
  visibility test, so Blender's own ray cast (``blender`` checks, made at generation) is the independent depth check.
* **Velocities** against central differences of the stored positions, (x_{i+1} - x_{i-1}) / (t_{i+1} - t_{i-1}) at
  interior samples (world units per unit of dataset time; also relative to the median speed).
* **Exactness and consistency**: flow exactly 0 on static surfaces; motion masks equal to the flows' ``dynamic``;
  depth > 0 exactly where the flow is defined; the renders' alpha against that surface (pixels that disagree: only
  anti-aliased edges should).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from pidg.data import DataConfig, load_scene
from pidg.data.motion_gt import MOTION_GT_DIR, read_motion_gt
from pidg.data.scene import SPLIT_NAMES
from pidg.render.camera import Camera
from pidg.scenes.ground_truth import interior_finite_differences

VISIBLE_DEPTH_TOLERANCE = 0.005
"""A vertex is visible when the stored depth around it is within this fraction of its camera z."""
VERIFY_FILE = "verify.json"


def stats(values: np.ndarray) -> dict[str, float]:
    """Median, 95th percentile, max and count (NaN figures for no values)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan"), "n": 0}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max()), "n": int(v.size)}


def bilinear(image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Values [N, C] of ``image`` [H, W, C] at pixel positions ``uv`` [N, 2] (centres at +0.5), the four taps' flat
    pixel indices [N, 4] (row * W + column), and whether all four lie inside the image [N] (outside: clamped)."""
    h, w = image.shape[:2]
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    cols = np.clip(np.stack([x0, x0 + 1, x0, x0 + 1], axis=1), 0, w - 1)
    rows = np.clip(np.stack([y0, y0, y0 + 1, y0 + 1], axis=1), 0, h - 1)
    weights = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)[..., None]
    inside = (x0 >= 0) & (x0 + 1 < w) & (y0 >= 0) & (y0 + 1 < h)
    return (weights * image[rows, cols]).sum(axis=1), rows * w + cols, inside


def vertex_residuals(camera: Camera, flow: np.ndarray, dynamic: np.ndarray, depth: np.ndarray,
                     x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flow residuals [M] in px, depth residuals [M] in world units) of the visible vertices (module docstring)."""
    uv0, z0 = (a.numpy() for a in camera.project_points(torch.from_numpy(x0.astype(np.float64))))
    uv1, _ = camera.project_points(torch.from_numpy(x1.astype(np.float64)))
    disp = uv1.numpy() - uv0
    d, taps, inside = bilinear(depth[..., None].astype(np.float64), uv0)
    f, _, _ = bilinear(np.nan_to_num(flow.astype(np.float64)), uv0)
    on_dynamic = inside & (z0 > camera.near) & dynamic.ravel()[taps].all(axis=1)
    visible = on_dynamic & (np.abs(d[:, 0] - z0) <= VISIBLE_DEPTH_TOLERANCE * z0)
    return np.linalg.norm(f[visible] - disp[visible], axis=-1), np.abs(d[visible, 0] - z0[visible])


def velocity_residuals(times: np.ndarray, positions: np.ndarray, velocities: np.ndarray, frame_interval: float) -> dict[str, Any]:
    """Stored velocities against central differences of the stored positions (interior samples)."""
    if len(times) < 3:
        return {"n": 0}
    fd = interior_finite_differences(times, positions)
    err = np.linalg.norm(velocities[1:-1].astype(np.float64) - fd, axis=-1)
    speed = np.linalg.norm(fd, axis=-1)
    scale = float(np.median(speed[speed > 0])) if (speed > 0).any() else 1.0
    return {"abs": stats(err), "abs_per_frame": stats(err * frame_interval), "relative_to_median_speed": stats(err / scale),
            "median_speed": scale, "median_speed_per_frame": scale * frame_interval}


def verify_dataset(root: Path | str, blender: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every check of the module docstring on the dataset in ``root`` (plus Blender's own checks when given)."""
    root = Path(root)
    splits = tuple(s for s in SPLIT_NAMES if (root / f"transforms_{s}.json").is_file())
    scene = load_scene(DataConfig(path=root, splits=splits, progress=False))
    gt = read_motion_gt(root)
    v = gt.vertices
    flow_err, depth_err = [], []
    counts = {"images": 0, "images_without_vertex_check": 0, "static_nonzero_flow_px": 0, "mask_mismatch_px": 0,
              "depth_surface_mismatch_px": 0, "alpha_surface_mismatch_px": 0, "pixels": 0, "dynamic_px": 0}
    for frames in scene.splits.values():
        for frame in frames:
            ff = gt.frame_flow(frame.name)
            surface = ff.surface
            counts["images"] += 1
            counts["pixels"] += surface.size
            counts["dynamic_px"] += int(ff.dynamic.sum())
            counts["static_nonzero_flow_px"] += int((surface & ~ff.dynamic & (ff.flow != 0).any(-1)).sum())
            if frame.mask is not None:
                counts["mask_mismatch_px"] += int((frame.mask.numpy() != ff.dynamic).sum())
            depth = frame.depth.numpy() if frame.depth is not None else np.zeros(surface.shape, np.float32)
            counts["depth_surface_mismatch_px"] += int(((depth > 0) != surface).sum())
            if frame.path is not None:
                alpha = np.asarray(Image.open(frame.path).convert("RGBA"))[..., 3]
                counts["alpha_surface_mismatch_px"] += int(((alpha >= 128) != surface).sum())
            try:
                i0, i1 = v.index_of(ff.time), v.index_of(ff.next_time)
            except KeyError:  # the last image's t + dt lies after the recording
                counts["images_without_vertex_check"] += 1
                continue
            f, d = vertex_residuals(frame.camera, ff.flow, ff.dynamic, depth, v.positions[i0], v.positions[i1])
            flow_err.append(f)
            depth_err.append(d)
    counts["alpha_surface_mismatch_fraction"] = counts["alpha_surface_mismatch_px"] / max(1, counts["pixels"])
    report = {
        "dataset": str(root),
        "vertex_flow_px": stats(np.concatenate(flow_err) if flow_err else np.zeros(0)),
        "vertex_depth": stats(np.concatenate(depth_err) if depth_err else np.zeros(0)),
        "velocity": velocity_residuals(v.times, v.positions, v.velocities, gt.frame_interval),
        "counts": counts,
        "units": {"vertex_flow_px": "pixels", "vertex_depth": "world units", "velocity.abs": "world units per unit of dataset time",
                  "velocity.abs_per_frame": "world units per frame interval"},
    }
    if blender is not None:
        report["blender"] = blender
    return report


def write_verify_report(root: Path | str, report: dict[str, Any]) -> Path:
    path = Path(root) / MOTION_GT_DIR / VERIFY_FILE
    path.write_text(json.dumps(report, indent=2))
    return path


def summary_lines(report: dict[str, Any]) -> list[str]:
    """The residuals in a few printable lines."""
    fl, dp, vel, c = report["vertex_flow_px"], report["vertex_depth"], report["velocity"], report["counts"]
    lines = [
        f"vertex flow vs stored flow: median {fl['median']:.4f} px, p95 {fl['p95']:.4f} px ({fl['n']} visible vertex samples)",
        f"vertex depth vs stored depth: median {dp['median']:.2e}, p95 {dp['p95']:.2e} world units",
    ]
    if vel.get("n", 1):
        lines.append(f"velocity vs finite differences: median {vel['abs']['median']:.3g}, p95 {vel['abs']['p95']:.3g} world units "
                     f"per unit time (p95 {vel['relative_to_median_speed']['p95']:.3g} of the median speed {vel['median_speed']:.3g})")
    lines.append(f"static surfaces with nonzero flow: {c['static_nonzero_flow_px']} px; masks != dynamic: {c['mask_mismatch_px']} px; "
                 f"depth>0 != surface: {c['depth_surface_mismatch_px']} px; render alpha != surface: "
                 f"{100 * c['alpha_surface_mismatch_fraction']:.2f} % of pixels")
    if "blender" in report:
        b = report["blender"]
        rc = b["ray_cast"]
        lines.append(f"Blender camera vs pidg camera: max {b['camera_projection_max_px']:.2e} px; Blender ray cast vs stored depth: "
                     f"median {rc['depth_median']:.2e}, p95 {rc['depth_p95']:.2e} world units, hit mismatches "
                     f"{rc['hit_mismatch']}/{rc['rays']}, dynamic mismatches {rc['dynamic_mismatch']}")
    return lines
