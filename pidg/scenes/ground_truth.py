"""The ground truth of a generated scene, computed from its triangles (numpy + numba, no bpy, so it is tested alone).

Why here and not in Blender: the same few lines make depth, motion masks and flow for every image, with pidg's own
camera model (:class:`pidg.render.camera.Camera`: OpenCV axes, pixel centres at integer + 0.5), so nothing is
converted twice; Blender's own ray caster checks it independently at generation (``--verify``).

* **Ray casting**: for each pixel, the ray from the camera centre through the pixel centre meets the nearest triangle
  (Moller-Trumbore, both sides, in camera coordinates where a ray is s * ((u - cx) / fx, (v - cy) / fy, 1), so the
  ray parameter s *is* the camera z). Result: face index, barycentric weights, depth (camera z, world units).
* **Flow** from t to t + dt in the camera of frame t held fixed: the surface point seen at t, P_t = sum b_k V_k(t),
  moves with its face to P_t1 = sum b_k V_k(t + dt) (same face, same barycentric weights: exact for rigid motion,
  the piecewise-linear surface's motion for deforming meshes); flow = project(P_t1) - project(P_t) in pixels
  (dx right, dy down), :func:`pidg.data.motion_gt.projected_displacement`, the function the evaluation uses too.
  Static faces keep their vertices, so their flow is exactly 0; background (no hit) is NaN.
* **Velocities**: central differences (units: world units per unit of dataset time); see :func:`central_difference`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from pidg.data.motion_gt import projected_displacement
from pidg.render.camera import Camera

_PARALLEL_EPS = 1e-14  # |det| below this: the ray runs in the triangle's plane (no single hit)


@dataclass(frozen=True)
class Triangles:
    """Every surface of the scene at one time: vertices [V, 3] float64 (world units), faces [F, 3] int64 (vertex
    indices), dynamic [F] bool (the face belongs to a moving object)."""

    vertices: np.ndarray
    faces: np.ndarray
    dynamic: np.ndarray

    def __post_init__(self) -> None:
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"Triangles: vertices [V, 3] and faces [F, 3], got {self.vertices.shape}, {self.faces.shape}")
        if self.dynamic.shape != (len(self.faces),):
            raise ValueError(f"Triangles: dynamic must be [F] = [{len(self.faces)}], got {self.dynamic.shape}")

    def moved(self, vertices: np.ndarray) -> "Triangles":
        """The same faces on other vertex positions (the scene at another time)."""
        if vertices.shape != self.vertices.shape:
            raise ValueError(f"Triangles.moved: vertices {vertices.shape}, expected {self.vertices.shape}")
        return Triangles(vertices, self.faces, self.dynamic)


@dataclass(frozen=True)
class SurfaceHits:
    """What each pixel's centre ray hits: face [H, W] int64 (-1: nothing), bary [H, W, 3] float64 (weights of the
    face's three vertices), depth [H, W] float64 (camera z in world units, 0 where nothing is hit)."""

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray

    @property
    def surface(self) -> np.ndarray:
        return self.face >= 0


def camera_arrays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(world-to-camera rotation [3, 3], translation [3]) as float64 from the camera's own matrix, so rays and
    :meth:`Camera.project_points` use the identical transform."""
    w2c = camera.world_to_camera.detach().cpu().to(torch.float64).numpy()
    return w2c[:3, :3].copy(), w2c[:3, 3].copy()


def cast_rays(camera: Camera, triangles: Triangles) -> SurfaceHits:
    """The nearest surface along each pixel-centre ray of ``camera`` (see the module docstring)."""
    rot, trans = camera_arrays(camera)
    cam_vertices = triangles.vertices @ rot.T + trans
    corners = np.ascontiguousarray(cam_vertices[triangles.faces], dtype=np.float64)  # [F, 3, 3]
    face, u, v, depth = _cast(corners, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near)
    bary = np.stack([1.0 - u - v, u, v], axis=-1)
    hit = face >= 0
    bary[~hit] = 0.0
    depth[~hit] = 0.0
    return SurfaceHits(face, bary, depth)


@njit(cache=True, nogil=True)
def _cast(corners, fx, fy, cx, cy, width, height, near):  # noqa: ANN001, ANN202 - numba kernel
    """Per triangle, test the pixels of its screen bounding box (the whole image when a corner is not in front of
    the camera); keep the nearest hit per pixel. Returns face, u, v (weights of corners 1 and 2), depth."""
    face = np.full((height, width), -1, dtype=np.int64)
    best = np.full((height, width), np.inf)
    out_u = np.zeros((height, width))
    out_v = np.zeros((height, width))
    for k in range(corners.shape[0]):
        a, b, c = corners[k, 0], corners[k, 1], corners[k, 2]
        i0, i1, j0, j1 = 0, height - 1, 0, width - 1
        if a[2] > near and b[2] > near and c[2] > near:
            us = np.array([fx * a[0] / a[2], fx * b[0] / b[2], fx * c[0] / c[2]]) + cx
            vs = np.array([fy * a[1] / a[2], fy * b[1] / b[2], fy * c[1] / c[2]]) + cy
            j0 = max(j0, int(np.floor(us.min() - 0.5)) - 1)
            j1 = min(j1, int(np.ceil(us.max() - 0.5)) + 1)
            i0 = max(i0, int(np.floor(vs.min() - 0.5)) - 1)
            i1 = min(i1, int(np.ceil(vs.max() - 0.5)) + 1)
        e1 = b - a
        e2 = c - a
        for i in range(i0, i1 + 1):
            dy = (i + 0.5 - cy) / fy
            for j in range(j0, j1 + 1):
                dx = (j + 0.5 - cx) / fx
                # Moller-Trumbore with ray origin 0 and direction (dx, dy, 1)
                px = dy * e2[2] - e2[1]
                py = e2[0] - dx * e2[2]
                pz = dx * e2[1] - dy * e2[0]
                det = e1[0] * px + e1[1] * py + e1[2] * pz
                if abs(det) < _PARALLEL_EPS:
                    continue
                inv = 1.0 / det
                sx, sy, sz = -a[0], -a[1], -a[2]
                u = (sx * px + sy * py + sz * pz) * inv
                if u < 0.0 or u > 1.0:
                    continue
                qx = sy * e1[2] - sz * e1[1]
                qy = sz * e1[0] - sx * e1[2]
                qz = sx * e1[1] - sy * e1[0]
                v = (dx * qx + dy * qy + qz) * inv
                if v < 0.0 or u + v > 1.0:
                    continue
                s = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
                if s <= near or s >= best[i, j]:
                    continue
                best[i, j] = s
                face[i, j] = k
                out_u[i, j] = u
                out_v[i, j] = v
    return face, out_u, out_v, best


def surface_points(vertices: np.ndarray, faces: np.ndarray, hits: SurfaceHits) -> np.ndarray:
    """[H, W, 3] world points sum_k b_k V_k of the hit faces on ``vertices`` (any time); NaN where nothing is hit."""
    corners = vertices[faces[np.maximum(hits.face, 0)]]  # [H, W, 3, 3]
    points = np.einsum("hwk,hwkc->hwc", hits.bary, corners)
    points[~hits.surface] = np.nan
    return points


def object_motion_flow(camera: Camera, scene_t: Triangles, vertices_t1: np.ndarray) -> tuple[np.ndarray, np.ndarray, SurfaceHits]:
    """(flow [H, W, 2] float32 in pixels, dynamic [H, W] bool, hits) of ``camera`` held fixed from the scene at t
    to its vertices at t + dt (module docstring). Flow is exactly 0 on static faces and NaN on the background."""
    hits = cast_rays(camera, scene_t)
    surface = hits.surface
    p0 = surface_points(scene_t.vertices, scene_t.faces, hits)[surface]
    p1 = surface_points(vertices_t1, scene_t.faces, hits)[surface]
    shift = projected_displacement(camera, torch.from_numpy(p0), torch.from_numpy(p1)).numpy()
    dynamic = np.zeros(surface.shape, dtype=bool)
    dynamic[surface] = scene_t.dynamic[hits.face[surface]]
    flow = np.full((*surface.shape, 2), np.nan, dtype=np.float32)
    flow[surface] = shift
    flow[surface & ~dynamic] = 0.0  # static vertices never move: exactly 0 (already so; stated, not trusted)
    return flow, dynamic, hits


def central_difference(before: np.ndarray, after: np.ndarray, step: float) -> np.ndarray:
    """d/dt at the midpoint of samples ``step`` before and after it: (after - before) / (2 step), float64. Its error
    is O(step^2) times the third derivative for smooth motion."""
    return (np.asarray(after, np.float64) - np.asarray(before, np.float64)) / (2.0 * step)


def interior_finite_differences(times: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Central differences [T - 2, V, 3] of positions [T, V, 3] sampled at ``times`` [T], at the interior samples
    (x_{i+1} - x_{i-1}) / (t_{i+1} - t_{i-1}): second-order accurate on a uniform grid."""
    p = np.asarray(positions, np.float64)
    span = (np.asarray(times, np.float64)[2:] - np.asarray(times, np.float64)[:-2]).reshape(-1, 1, 1)
    return (p[2:] - p[:-2]) / span


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n points [n, 3] uniformly distributed over the triangles' area, and the face [n] each lies on."""
    corners = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=-1)
    if not area.sum() > 0:
        raise ValueError("sample_surface: the triangles have no area")
    face = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)  # uniform on a triangle: (1 - sqrt r1, sqrt r1 (1 - r2), sqrt r1 r2)
    w = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=-1)
    return np.einsum("nk,nkc->nc", w, corners[face]), face
