"""3D trajectories of rigid bodies from the cached optical flow and the dataset's depth (an extension, not in the
paper): a start for the deformation field on scenes of rigid bodies.

Why: both image losses supervise whatever Gaussian is at a place, not the one carried there, so training from rest
hands a moving body from Gaussian to Gaussian (a relay) and learns neither its path nor its turn; started from the
right motion, training keeps it (docs/motion.md, "What the field can represent"). Single flow tracks die within a
few frames on tumbling bodies, but a rigid body's motion over one interval needs only a few right correspondences,
and motions chain without limit. So:

1. each training interval's consistent forward flow on the moving pixels, both ends lifted with the frames' depth,
   gives 3D pairs (:func:`lifted_pairs`);
2. the first frame's lifted moving surface splits into bodies by 3D connectivity (:func:`connected_labels`);
3. per interval and body, the rigid motion of the pairs that start nearest that body's carried points (RANSAC on
   three pairs, then least squares on the inliers: :func:`ransac_rigid`); a body without one stays where it is when
   the frame shows it off the motion mask (it came to rest), else it is carried at its last velocity for up to
   ``max_gap`` intervals, then its tracks end.

Positions are world units, times the dataset's [0, 1]; everything runs on the CPU in float64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.flow.decomposition import unproject_points
from pidg.flow.optical_flow import pixel_centers
from pidg.flow.preprocess import FlowCache, FlowPair

_MIN_INLIERS = 6  # a motion fitted to fewer pairs than this is not trusted


@dataclass(frozen=True)
class RigidTrackConfig:
    """Settings of :func:`track_rigid_bodies`. Distances are in pixels of the first training frame at the median
    depth of its moving surface (one such pixel spans median depth / fx world units), so that they hold at any scene
    scale and image size."""

    points: int = 2000
    """Surface points tracked, sampled on the first training frame's moving pixels."""
    static_points: int = 4000
    """Points of the first frame's still surface returned as anchors (held still by a fit)."""
    link: float = 2.5
    """Two lifted moving points closer than this (px) belong to one body."""
    inlier: float = 1.5
    """A pair is an inlier of a motion that carries its start within this (px) of its end."""
    reach: float = 4.5
    """A body's motion is fitted to the pairs starting within this (px) of its carried points (3x, 10x when too few)."""
    iterations: int = 300
    """RANSAC draws per body and interval."""
    min_pairs: int = 10
    """Fewest pairs a body's motion is fitted to."""
    max_gap: int = 1
    """Intervals a body without a fitted motion is carried at its last velocity before its tracks end."""
    min_body_points: int = 20
    """Connected pieces with fewer tracked points join the nearest larger body."""


@dataclass
class RigidTracks:
    """What :func:`track_rigid_bodies` found."""

    times: Tensor  # [T] the training frames' times (dataset time)
    positions: Tensor  # [T, P, 3] world units
    known: Tensor  # [T, P] bool: False once a point's body is lost
    body: Tensor  # [P] long: the body of each point
    static: Tensor  # [S, 3] the first frame's lifted still surface
    found: Tensor  # [T - 1, B] bool: a motion was fitted for body b over interval k (not extrapolated)


def lifted_pairs(pair: FlowPair, moving: bool = True) -> tuple[Tensor, Tensor]:
    """3D correspondences [N, 3] x2 (world, float64) of one pair: frame t's pixels with a consistent forward flow and
    depth (and on the motion mask when ``moving``), lifted with their depth, and where the flow lands in frame t+1
    (inside it, on a pixel with depth, on its motion mask when ``moving``), lifted with that pixel's depth."""
    f0, f1 = pair.frame0, pair.frame1
    d0, d1 = f0.depth.double(), f1.depth.double()
    h, w = d0.shape
    use = pair.valid_forward & (d0 > 0)
    if moving:
        use &= f0.mask
    p = pixel_centers(h, w, torch.float64)[use]
    q = p + pair.forward.double()[use]
    j, i = q[:, 0].floor().long(), q[:, 1].floor().long()
    inside = (j >= 0) & (j < w) & (i >= 0) & (i < h)
    i, j = i.clamp(0, h - 1), j.clamp(0, w - 1)
    z1 = d1[i, j]
    keep = inside & (z1 > 0) & (f1.mask[i, j] if moving else True)
    a = unproject_points(p[keep], d0[use][keep], f0.camera)
    b = unproject_points(q[keep], z1[keep], f1.camera)
    return a, b


def rigid_fit(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """The rotation R [3, 3] and translation t [3] that carry ``a`` [N, 3] onto ``b`` in least squares (Kabsch, no
    reflection): b ~ a @ R.T + t."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vh = torch.linalg.svd((a - ca).T @ (b - cb))
    sign = torch.sign(torch.linalg.det(vh.T @ u.T))
    rotation = vh.T @ torch.diag(torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign])) @ u.T
    return rotation, cb - ca @ rotation.T


def ransac_rigid(a: Tensor, b: Tensor, inlier: float, iterations: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor] | None:
    """The rigid motion most pairs of ``a`` -> ``b`` agree with: the best of ``iterations`` three-pair draws, refitted to
    its inliers until they settle; (R, t, inlier mask), or None with fewer than three pairs."""
    if len(a) < 3:
        return None
    draws = torch.stack([torch.randperm(len(a), generator=generator)[:3] for _ in range(iterations)])
    best = None
    for rows in draws:
        rotation, shift = rigid_fit(a[rows], b[rows])
        inliers = (a @ rotation.T + shift - b).norm(dim=1) < inlier
        if best is None or int(inliers.sum()) > int(best.sum()):
            best = inliers
    if int(best.sum()) < 3:
        return None
    for _ in range(3):
        rotation, shift = rigid_fit(a[best], b[best])
        refined = (a @ rotation.T + shift - b).norm(dim=1) < inlier
        if int(refined.sum()) < 3 or torch.equal(refined, best):
            break
        best = refined
    return rotation, shift, best


def connected_labels(points: Tensor, link: float, chunk: int = 2048) -> Tensor:
    """[N] component labels 0..C-1 of ``points`` [N, 3], two points joined when closer than ``link`` (single linkage;
    union-find over the close pairs, found a block of rows at a time)."""
    parent = list(range(len(points)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for start in range(0, len(points), chunk):
        close = (torch.cdist(points[start:start + chunk], points) < link).nonzero().tolist()
        for i, j in close:
            ri, rj = root(start + i), root(j)
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
    roots = torch.tensor([root(i) for i in range(len(points))], dtype=torch.long)
    return torch.unique(roots, return_inverse=True)[1]


def rotation_angle(rotation: Tensor) -> float:
    """The angle of a rotation matrix [3, 3], radians in [0, pi]."""
    return math.acos(max(-1.0, min(1.0, (float(torch.trace(rotation)) - 1.0) / 2.0)))


def _rotation_power(rotation: Tensor, s: float) -> Tensor:
    """R^s: the same axis, s times the angle (Rodrigues)."""
    angle = rotation_angle(rotation)
    if angle < 1e-9:
        return torch.eye(3, dtype=rotation.dtype)
    axis = torch.stack([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    axis = axis / axis.norm().clamp_min(1e-12)
    k = torch.zeros(3, 3, dtype=rotation.dtype)
    k[0, 1], k[0, 2], k[1, 2] = -axis[2], axis[1], -axis[0]
    k = k - k.T
    theta = s * angle
    return torch.eye(3, dtype=rotation.dtype) + math.sin(theta) * k + (1.0 - math.cos(theta)) * (k @ k)


def _carried(x: Tensor, rotation: Tensor, shift: Tensor, s: float = 1.0) -> Tensor:
    """``x`` moved by the motion (R, t) or, for s != 1, by s times it about the points' centroid (constant velocity)."""
    if s == 1.0:
        return x @ rotation.T + shift
    centre = x.mean(0)
    return (x - centre) @ _rotation_power(rotation, s).T + centre + s * (centre @ rotation.T + shift - centre)


def _came_to_rest(points: Tensor, frame: Frame, min_visible: int, depth_tolerance: float = 0.03) -> bool:
    """Whether a body without flow pairs has stopped: most of its ``points`` that ``frame`` sees (projected inside it,
    at the depth it measures there within ``depth_tolerance`` of it) lie off the motion mask (a still body leaves it)."""
    uv, z = frame.camera.project_points(points)
    h, w = frame.depth.shape
    j, i = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (j >= 0) & (j < w) & (i >= 0) & (i < h) & (z > 0)
    i, j = i.clamp(0, h - 1), j.clamp(0, w - 1)
    measured = frame.depth.double()[i, j]
    seen = inside & (measured > 0) & ((measured - z).abs() < depth_tolerance * z)
    return int(seen.sum()) >= min_visible and float(frame.mask[i, j][seen].float().mean()) < 0.5


def _nearest(points: Tensor, to: Tensor, chunk: int = 4096) -> tuple[Tensor, Tensor]:
    """The distance [N] from each of ``points`` [N, 3] to the nearest of ``to`` [M, 3], and its index [N] (a block of
    rows at a time: N x M distances at once would be large on large images)."""
    blocks = [torch.cdist(rows, to).min(1) for rows in points.split(chunk)]
    return torch.cat([b.values for b in blocks]), torch.cat([b.indices for b in blocks])


def _bodies(start: Tensor, moving: Tensor, link: float, min_points: int) -> Tensor:
    """The body of each tracked point: its connected piece of the first frame's moving surface ``moving``; pieces
    with fewer than ``min_points`` tracked points join the nearest larger one."""
    labels = connected_labels(moving, link)[_nearest(start, moving)[1]]
    sizes = torch.bincount(labels)
    large = sizes[labels] >= min_points
    if large.any() and not large.all():
        labels[~large] = labels[large][_nearest(start[~large], start[large])[1]]
    return torch.unique(labels, return_inverse=True)[1]


def track_rigid_bodies(cache: FlowCache, config: RigidTrackConfig, generator: torch.Generator) -> RigidTracks:
    """Track the first training frame's moving surface through every training interval as rigid bodies (module
    docstring). ValueError naming the frame when a frame has no depth or motion mask, or the first frame shows no
    moving surface with depth."""
    frames = cache.frames
    for frame in frames:
        if frame.depth is None or frame.mask is None:
            raise ValueError(f"rigid-body tracks need depth maps and motion masks: {frame.name or frame.path} has no "
                             f"{'depth' if frame.depth is None else 'motion mask'}")
    cache = cache.to("cpu", [f.to("cpu") for f in frames])
    frames = cache.frames
    if len(cache) == 0:
        raise ValueError("rigid-body tracks need at least two training frames")
    first, _ = lifted_pairs(cache.pair(0))
    if len(first) < config.min_body_points:
        raise ValueError(f"rigid-body tracks: the first training frame ({frames[0].name}) shows {len(first)} moving "
                         "pixels with depth and a consistent flow; too few to track")
    f0 = frames[0]
    footprint = float(f0.depth[f0.mask & (f0.depth > 0)].double().median()) / f0.camera.fx  # world units a pixel
    link, inlier, reach = config.link * footprint, config.inlier * footprint, config.reach * footprint
    start = first[torch.randperm(len(first), generator=generator)[:config.points]]
    body = _bodies(start, first, link, config.min_body_points)
    n_bodies = int(body.max()) + 1
    still = (~f0.mask) & (f0.depth > 0)
    h, w = still.shape
    pixels = pixel_centers(h, w, torch.float64)[still]
    pick = torch.randperm(len(pixels), generator=generator)[:config.static_points]
    static = unproject_points(pixels[pick], f0.depth.double()[still][pick], f0.camera)

    x, alive = start.clone(), torch.ones(n_bodies, dtype=torch.bool)
    gaps = [0] * n_bodies
    last: dict[int, tuple[Tensor, Tensor, float]] = {}
    positions, known, found = [x], [alive[body]], []
    for k in range(len(cache)):
        pair = cache.pair(k)
        a, b = lifted_pairs(pair)
        dt = pair.dt
        if len(a):
            distance, nearest = _nearest(a, x)
            owner = body[nearest]
        moved = x.clone()
        found_k = torch.zeros(n_bodies, dtype=torch.bool)
        for bi in range(n_bodies):
            if not alive[bi]:
                continue
            rows = body == bi
            motion = None
            for within in (reach, 3 * reach, 10 * reach):
                if not len(a):
                    break
                mine = (owner == bi) & (distance < within)
                if int(mine.sum()) >= config.min_pairs:
                    fit = ransac_rigid(a[mine], b[mine], inlier, config.iterations, generator)
                    if fit is not None and int(fit[2].sum()) >= _MIN_INLIERS:
                        motion = fit[:2]
                        break
            if motion is not None:
                gaps[bi], last[bi], found_k[bi] = 0, (*motion, dt), True
                moved[rows] = _carried(x[rows], *motion)
            elif _came_to_rest(x[rows], pair.frame0, config.min_pairs):
                gaps[bi], last[bi] = 0, (torch.eye(3, dtype=x.dtype), torch.zeros(3, dtype=x.dtype), dt)
            elif bi in last and gaps[bi] < config.max_gap:
                gaps[bi] += 1
                rotation, shift, dt_last = last[bi]
                moved[rows] = _carried(x[rows], rotation, shift, dt / dt_last)
            else:
                alive[bi] = False
        x = moved
        positions.append(x)
        known.append(alive[body])
        found.append(found_k)
    times = torch.tensor([f.time for f in frames], dtype=torch.float64)
    return RigidTracks(times, torch.stack(positions), torch.stack(known), body, static, torch.stack(found))
