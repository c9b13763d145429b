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
3. per interval and body, three candidate motions: the rigid motion of the flow pairs that start nearest the body's
   carried points (RANSAC on three pairs, then least squares on the inliers: :func:`ransac_rigid`), its last motion
   continued (constant velocity) and rest;
4. each candidate refined against the next frame's moving surface (its depth on the motion mask) and the flow pairs
   at once (:func:`refine_motion`, an iterative closest point fit, point to plane: :func:`point_plane_fit`): the
   surface corrects the flow's drift and carries a body through intervals where the flow fails (fast motion), the
   flow pins what the surface leaves free (a sphere's spin);
5. of the candidates that leave about the fewest of the body's points where the next frame sees through them
   (:func:`seen_through`: a right motion leaves none), the one most flow pairs agree with; when none is fitted to
   enough pairs, or even the best leaves more than ``max_seen_through``, the body stays where it is if the frame
   shows it off the motion mask (it came to rest), else it is carried at its last velocity for up to ``max_gap``
   intervals, then its tracks end;
6. the chosen motion refined by the body's look (``photometric``, :class:`Look`): the surface frame t shows of the
   body must look in frame t+1 as it does in frame t (:func:`photometric_refine`), kept only if it looks no less
   alike (:func:`look_agreement`) and leaves no more of the body seen through. The optical flow falls short of
   small, fast-turning bodies' motion (12 % on the generated rigid scene), the images do not; where the flow failed
   altogether (a fast motion), every candidate the surface allows is refined so and the best-looking one chosen;
7. the sides of a body the first frame does not see join from the later frames: points of each frame's moving
   surface connected to a tracked body, carried back to the first frame by the inverse of its motion, then along it;
8. the chain is chaotic (a small change in one interval reshuffles every later draw), so a body whose chain went
   wrong (its points look anti-correlated with themselves over some interval: :func:`chain_look`) is chained again
   with new RANSAC draws, up to ``attempts`` chains, and the one whose points look most alike is kept.

Against the true motion (``pidg bench rigid-tracks``; docs/motion.md, "Rigid-body tracks that hold", "Tracks fitted
point to plane", "Tracks fitted to the images" and "Chains that went wrong"): the rigid scene's tracks move 0.13-0.22
of the true moves off in ten of eleven seeds and 0.31 in one, whose box goes wrong without its look telling (0.13-0.44
with one chain, where boxes went wrong in a fast phase; 0.25-0.29 without the look; 0.27-0.36 with a Kabsch fit), the
kinematic head's 0.004 through all 44 intervals (with the flow alone lost at interval 16).

Positions are world units, times the dataset's [0, 1]; everything runs on the CPU in float64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.flow.decomposition import backproject, unproject_points
from pidg.flow.optical_flow import pixel_centers, sample_bilinear, sample_mask
from pidg.flow.preprocess import FlowCache, FlowPair

_MIN_INLIERS = 6  # a motion fitted to fewer pairs than this is not trusted
_SEEN_THROUGH_MARGIN = 0.05  # motions leaving up to this share more of a body seen through than the best are equals
_MIN_LOOK_POINTS = 20  # fewest seen surface points a photometric fit or a look comparison is made on
_LOOK_BLUR = 1.0  # px: the blur of the images the look is compared on (:func:`look_agreement`)
_PHOTOMETRIC_BLURS = (2.0, 1.0, 0.0)  # px: the photometric fit coarse to fine (a wider basin first, then the detail)
_PHOTOMETRIC_STEPS = 4  # Gauss-Newton steps per blur
_PHOTOMETRIC_HUBER = 0.05  # colour residuals (image units) beyond this count linearly: occlusions, highlights
_PHOTOMETRIC_NOISE = 0.03  # the colour residual (image units) that weighs as one footprint along a surface's normal
_PHOTOMETRIC_DAMPING = 1e-2  # Levenberg-Marquardt: this share of the normal matrix's diagonal added to it


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
    later_points: int = 100
    """Points added per later training frame from the surface it shows on a tracked body (its sides the first frame
    does not see), carried back to the first frame and along the body's tracked motion."""
    max_seen_through: float = 0.2
    """A motion that leaves more than this share of a body's points in view where the next frame sees through them
    (no surface there, or a farther one) is not trusted."""
    photometric: bool = True
    """Refine each fitted motion by the body's look as well (:func:`photometric_refine`): the optical flow falls
    short of small, fast-turning bodies' motion (12 % on the rigid scene), the images themselves do not."""
    high_pass: float = 3.0
    """The photometric fit compares images less their blur of this width (px, the Gaussian's sigma): shading, which
    does not turn with a body, varies slowly across it; its texture does not."""
    max_look_drop: float = 0.05
    """A photometric refinement is kept only if the body looks at most this much less alike in the two frames
    (:func:`look_agreement`: a correlation times the share of the body still seen, at most 1) than with the motion
    it started from: a fit that slid into a wrong minimum shows there."""
    attempts: int = 3
    """Chains made at most for a body whose chain went wrong (its points look anti-correlated with themselves over
    some interval: :func:`chain_look`), each drawing its RANSAC samples anew; of them the one whose points look most
    alike from each frame to the next is kept. The chain is chaotic (a small change in one interval reshuffles every
    later draw), so a body tracked wrong in one chain is often right in another: on the generated rigid scene, over
    eleven tracker seeds, three boxes that went wrong so (move error 0.54, 0.34, 0.92) came to 0.06-0.07
    (docs/motion.md, "Chains that went wrong"). 1: one chain (the tracker before 2026-12-01); bodies whose chain did
    not go wrong cost nothing more."""


@dataclass
class RigidTracks:
    """What :func:`track_rigid_bodies` found."""

    times: Tensor  # [T] the training frames' times (dataset time)
    positions: Tensor  # [T, P, 3] world units
    known: Tensor  # [T, P] bool: False once a point's body is lost
    body: Tensor  # [P] long: the body of each point
    static: Tensor  # [S, 3] the first frame's lifted still surface
    found: Tensor  # [T - 1, B] bool: a motion was fitted for body b over interval k (not extrapolated)
    chains: Tensor  # [B] long: chains made for body b (more than 1 where its first went wrong: RigidTrackConfig.attempts)
    look: Tensor  # [B] float64: how alike its kept chain's points look from frame to frame (chain_look's mean)


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
    """The rotation R [..., 3, 3] and translation t [..., 3] that carry ``a`` [..., N, 3] onto ``b`` in least squares
    (Kabsch, no reflection): b ~ a @ R.T + t; leading dimensions are independent fits (one batched SVD)."""
    ca, cb = a.mean(-2, keepdim=True), b.mean(-2, keepdim=True)
    u, _, vh = torch.linalg.svd((a - ca).transpose(-1, -2) @ (b - cb))
    v, ut = vh.transpose(-1, -2), u.transpose(-1, -2)
    sign = torch.sign(torch.linalg.det(v @ ut))
    flip = torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], dim=-1)
    rotation = (v * flip[..., None, :]) @ ut
    return rotation, (cb - ca @ rotation.transpose(-1, -2)).squeeze(-2)


def ransac_rigid(a: Tensor, b: Tensor, inlier: float, iterations: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor] | None:
    """The rigid motion most pairs of ``a`` -> ``b`` agree with: the best of ``iterations`` three-pair draws (the first
    of the most inliers; all draws fitted and counted at once), refitted to its inliers until they settle;
    (R, t, inlier mask), or None with fewer than three pairs."""
    if len(a) < 3:
        return None
    draws = torch.stack([torch.randperm(len(a), generator=generator)[:3] for _ in range(iterations)])
    rotations, shifts = rigid_fit(a[draws], b[draws])  # [K, 3, 3], [K, 3]
    counts = ((a @ rotations.transpose(-1, -2) + shifts[:, None] - b).norm(dim=-1) < inlier).sum(1)
    k = int(counts.argmax())  # the first draw with the most inliers
    best = (a @ rotations[k].T + shifts[k] - b).norm(dim=1) < inlier
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


def cross_matrix(v: Tensor) -> Tensor:
    """[..., 3, 3] matrices [v]x with [v]x u = v x u for ``v`` [..., 3]."""
    zero = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([zero, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], zero, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], zero], -1)], -2)


def axis_angle_rotation(axis: Tensor, angle: float) -> Tensor:
    """The rotation [3, 3] by ``angle`` (radians) about the unit vector ``axis`` [3] (Rodrigues)."""
    k = cross_matrix(axis)
    return torch.eye(3, dtype=axis.dtype) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _rotation_power(rotation: Tensor, s: float) -> Tensor:
    """R^s: the same axis, s times the angle."""
    angle = rotation_angle(rotation)
    if angle < 1e-9:
        return torch.eye(3, dtype=rotation.dtype)
    axis = torch.stack([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    return axis_angle_rotation(axis / axis.norm().clamp_min(1e-12), s * angle)


def point_plane_fit(
    rotation: Tensor, shift: Tensor, a: Tensor, b: Tensor, x: Tensor, target: Tensor, normal: Tensor,
    iterations: int = 3,
) -> tuple[Tensor, Tensor]:
    """The rigid motion (R, t), refined from (``rotation``, ``shift``) by Gauss-Newton steps, that carries the pairs'
    ``a`` [N, 3] onto ``b`` (point to point) and the points ``x`` [M, 3] onto the planes through ``target`` [M, 3]
    with unit normals ``normal`` [M, 3] (point to plane: only the distance along the normal counts), or onto
    ``target`` itself where the normal is zero (point to point). Each step linearises the update dR = exp([w]x) about
    the current motion and solves the 6-unknown least squares for (w, dt) in one go. Why not Kabsch to the points
    moved onto the planes: those targets keep the current motion along each plane, so every round the surface pulls
    the turn back toward where it started, and a sphere's spin or a face's slide, which only the pairs can tell,
    stays biased toward the start (the rigid scene's tracks were 0.16 of the travel off with it over five seeds, 0.12
    with this: docs/motion.md, "Tracks fitted point to plane")."""
    eye = torch.eye(3, dtype=x.dtype)
    point = (normal == 0).all(-1)
    for _ in range(iterations):
        ya, yx = a @ rotation.T + shift, x @ rotation.T + shift
        both = torch.cat([ya, yx[point]])  # point-to-point rows: d(R y + t) = -[y]x w + dt
        rows = [torch.cat([-cross_matrix(both), eye.expand(len(both), 3, 3)], -1).reshape(-1, 6),
                torch.cat([torch.linalg.cross(yx[~point], normal[~point]), normal[~point]], -1)]  # n . (w x y + dt)
        residuals = [torch.cat([b - ya, target[point] - yx[point]]).reshape(-1),
                     ((target[~point] - yx[~point]) * normal[~point]).sum(-1)]
        jacobian, residual = torch.cat(rows), torch.cat(residuals)
        if len(residual) < 6:
            break
        step = torch.linalg.lstsq(jacobian, residual[:, None]).solution[:, 0]
        w, angle = step[:3], float(step[:3].norm())
        turn = axis_angle_rotation(w / angle, angle) if angle > 1e-12 else eye
        rotation, shift = turn @ rotation, shift @ turn.T + step[3:]
    return rotation, shift


def blurred(image: Tensor, sigma: float) -> Tensor:
    """``image`` [H, W, C] blurred by a Gaussian of ``sigma`` px (separable, edges repeated; itself at sigma 0)."""
    if sigma <= 0:
        return image
    radius = int(3 * sigma + 0.5)
    kernel = torch.exp(-0.5 * (torch.arange(-radius, radius + 1, dtype=image.dtype) / sigma) ** 2)
    kernel = kernel / kernel.sum()
    x = image.permute(2, 0, 1)[:, None]  # [C, 1, H, W]
    pad, conv = torch.nn.functional.pad, torch.nn.functional.conv2d
    x = conv(pad(x, (radius, radius, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))  # along rows
    x = conv(pad(x, (0, 0, radius, radius), mode="replicate"), kernel.view(1, 1, -1, 1))  # along columns
    return x[:, 0].permute(1, 2, 0)


def masked_blur(image: Tensor, mask: Tensor, sigma: float) -> Tensor:
    """``image`` [H, W, C] blurred by a Gaussian of ``sigma`` px within ``mask`` [H, W] only (the blur of the masked
    image over the blur of the mask; 0 off it): a moving body's colours do not mix with the still background's."""
    weight = mask.to(image.dtype)[..., None]
    return blurred(image * weight, sigma) / blurred(weight, sigma).clamp_min(1e-6) * weight


def _seen(points: Tensor, frame: Frame, tolerance: float) -> Tensor:
    """[N] whether ``frame`` sees ``points`` [N, 3]: inside its view, within ``tolerance`` (world units) of the depth
    it measures at their pixel."""
    inside, z, i, j = _pixels_of(points, frame)
    measured = frame.depth.double()[i, j]
    return inside & (measured > 0) & ((measured - z).abs() < tolerance)


@dataclass(frozen=True)
class PairImages:
    """A frame pair's images as the look reads them (:func:`pair_images`): made once per interval and read by every
    body and candidate motion (blurring both images anew for each of them made the tracker 1.3x slower)."""

    levels: tuple[tuple[Tensor, Tensor], ...]  # per ``_PHOTOMETRIC_BLURS``: frame t's and t+1's [H, W, 3]
    plain: tuple[Tensor, Tensor]  # both images blurred by ``_LOOK_BLUR`` px


def pair_images(frame0: Frame, frame1: Frame, high_pass: float) -> PairImages:
    """The two frames' images (float64, [0, 1]) as :func:`photometric_refine` fits on them, coarse to fine: each less
    its blur of ``high_pass`` px within its motion mask (shading does not turn with a body; 0: none), then blurred
    within the mask by each of ``_PHOTOMETRIC_BLURS``; and as :func:`look_agreement` compares them: blurred by
    ``_LOOK_BLUR`` px. Blurs within the mask keep a moving body's colours from the still background's."""
    images = [frame.image.double() for frame in (frame0, frame1)]
    masks = [frame.mask for frame in (frame0, frame1)]
    passed = images
    if high_pass > 0:
        passed = [(image - masked_blur(image, mask, high_pass)) * mask[..., None] for image, mask in zip(images, masks)]
    levels = tuple((masked_blur(passed[0], masks[0], sigma), masked_blur(passed[1], masks[1], sigma))
                   for sigma in _PHOTOMETRIC_BLURS)
    return PairImages(levels, (blurred(images[0], _LOOK_BLUR), blurred(images[1], _LOOK_BLUR)))


def photometric_rows(
    y: Tensor, colours: Tensor, image: Tensor, frame: Frame, centre: Tensor,
) -> tuple[Tensor, Tensor]:
    """The colour residuals [N * C] of points ``y`` [N, 3] (world) in ``image`` [H, W, C] as ``frame``'s camera sees
    them, against ``colours`` [N, C], and their Jacobian [N * C, 6] in the motion update (w, dt) that moves each point
    to exp([w]x) (y - ``centre``) + ``centre`` + dt, at zero: d r / d w = (y - centre) x g, d r / d dt = g, with g
    = dI/dy (the bilinear lookup's own gradient through the projection, by autograd: each residual depends on its own
    point only, so one backward pass per channel gives every point's)."""
    with torch.enable_grad():
        at = y.detach().requires_grad_(True)
        values, _ = sample_bilinear(image, frame.camera.project_points(at)[0])
        gradients = [torch.autograd.grad(values[:, c].sum(), at, retain_graph=c + 1 < values.shape[1])[0]
                     for c in range(values.shape[1])]
    g = torch.stack(gradients, 1)  # [N, C, 3]
    arm = (y - centre)[:, None].expand_as(g)
    jacobian = torch.cat([torch.linalg.cross(arm, g, dim=-1), g], -1).reshape(-1, 6)
    return (values.detach() - colours).reshape(-1), jacobian


def photometric_refine(
    x: Tensor, rotation: Tensor, shift: Tensor, frame0: Frame, frame1: Frame, images: PairImages,
    surface: tuple[Tensor, Tensor], tolerance: float, footprint: float,
) -> tuple[Tensor, Tensor]:
    """The motion (R, t) of a body, refined from (``rotation``, ``shift``), under which its surface points ``x``
    [N, 3] (world, lifted from ``frame0``'s depth) look in ``frame1`` as they look in ``frame0``: a direct,
    photometric fit (Gauss-Newton with Levenberg-Marquardt damping, Huber-weighted colour residuals), coarse to fine
    over ``images.levels`` (:func:`pair_images`: the two frames' images high-passed and blurred within their motion
    masks). Only the points ``frame1`` sees at their moved place (within ``tolerance``, world units) count. The
    body's points also pull point to plane toward ``surface`` (frame1's moving surface near them, points and normals:
    :func:`moving_surface`) in the same solve, one footprint (world units a pixel spans) weighing as
    ``_PHOTOMETRIC_NOISE`` of colour, so the look cannot take the body off the surface the depth shows. Why: the
    optical flow's pairs fall short of small, fast-turning bodies' motion (12 % on the generated rigid scene), while
    their texture in the images moves with them (docs/motion.md, "Tracks fitted to the images"). Both frames need
    depth maps and motion masks (:func:`track_rigid_bodies` checks)."""
    uv0, _ = frame0.camera.project_points(x)
    clear = _seen(x, frame0, tolerance) & sample_mask(frame0.mask, uv0)  # not mixed with the background by the lookup
    x, uv0 = x[clear], uv0[clear]
    if len(x) < _MIN_LOOK_POINTS:
        return rotation, shift
    eye = torch.eye(3, dtype=x.dtype)
    points, normals = surface
    for image0, image1 in images.levels:
        colours0 = sample_bilinear(image0, uv0)[0]
        for _ in range(_PHOTOMETRIC_STEPS):
            y = x @ rotation.T + shift
            use = _seen(y, frame1, tolerance) & sample_mask(frame1.mask, frame1.camera.project_points(y)[0])
            if int(use.sum()) < _MIN_LOOK_POINTS:
                return rotation, shift
            centre = y[use].mean(0)
            residual, jacobian = photometric_rows(y[use], colours0[use], image1, frame1, centre)
            size = residual.abs()
            weight = (_PHOTOMETRIC_HUBER / size.clamp_min(1e-12)).clamp_max(1.0)  # Huber's weights
            residual, jacobian = residual / _PHOTOMETRIC_NOISE, jacobian / _PHOTOMETRIC_NOISE
            if len(points):
                distance, nearest = _nearest(y, points)
                normal = normals[nearest]
                near = (distance < 3 * tolerance) & (normal != 0).any(-1)
                plane = torch.cat([torch.linalg.cross(y[near] - centre, normal[near], dim=-1), normal[near]], -1)
                residual = torch.cat([residual, ((y[near] - points[nearest[near]]) * normal[near]).sum(-1) / footprint])
                jacobian = torch.cat([jacobian, plane / footprint])
                weight = torch.cat([weight, torch.ones(int(near.sum()), dtype=x.dtype)])
            normal_matrix = jacobian.T @ (weight[:, None] * jacobian)
            damped = normal_matrix + _PHOTOMETRIC_DAMPING * torch.diag(torch.diagonal(normal_matrix))
            gradient = (jacobian.T @ (weight * residual))[:, None]
            step = -torch.linalg.lstsq(damped, gradient).solution[:, 0]  # least squares: no step where no texture
            w, angle = step[:3], float(step[:3].norm())
            turn = axis_angle_rotation(w / angle, angle) if angle > 1e-12 else eye
            rotation, shift = turn @ rotation, (shift - centre) @ turn.T + centre + step[3:]
    return rotation, shift


def look_agreement(
    x: Tensor, rotation: Tensor, shift: Tensor, frame0: Frame, frame1: Frame, images: PairImages, tolerance: float,
) -> float:
    """How alike a body's surface points ``x`` [N, 3] (world, lifted from ``frame0``) look in ``frame0`` and,
    carried by (``rotation``, ``shift``), in ``frame1``: the zero-mean normalised cross-correlation of their colours
    in both images blurred by ``_LOOK_BLUR`` px (``images.plain``: :func:`pair_images`), over the points both frames
    see (within ``tolerance``, world units), times the share of ``x`` those are (a wrong motion that leaves few of
    them in view can match by chance); at most 1, for a right motion of a body whose look does not change and which
    stays in view; NaN when fewer than ``_MIN_LOOK_POINTS`` are seen. Unlike the photometric fit's cost it is blind
    to a change of brightness and contrast, so it can judge that fit."""
    correlation, seen = look_correlation(x, x @ rotation.T + shift, frame0, frame1, images.plain, tolerance)
    return correlation * seen


def look_correlation(
    x: Tensor, y: Tensor, frame0: Frame, frame1: Frame, plain: tuple[Tensor, Tensor], tolerance: float,
) -> tuple[float, float]:
    """The zero-mean normalised cross-correlation of surface points' colours at ``x`` [N, 3] in ``frame0`` and at
    ``y`` [N, 3] in ``frame1``, on the images ``plain`` (both blurred by ``_LOOK_BLUR`` px), over the points both
    frames see (within ``tolerance``, world units), and the share of the points those are; NaN for the correlation
    when fewer than ``_MIN_LOOK_POINTS`` are seen."""
    both = _seen(x, frame0, tolerance) & _seen(y, frame1, tolerance)
    seen = float(both.double().mean()) if len(both) else 0.0
    if int(both.sum()) < _MIN_LOOK_POINTS:
        return math.nan, seen
    looks = []
    for frame, image, points in ((frame0, plain[0], x[both]), (frame1, plain[1], y[both])):
        colours = sample_bilinear(image, frame.camera.project_points(points)[0])[0]
        looks.append(colours - colours.mean(0))
    return float((looks[0] * looks[1]).sum() / (looks[0].norm() * looks[1].norm()).clamp_min(1e-12)), seen


def _constant_velocity(x: Tensor, rotation: Tensor, shift: Tensor, s: float) -> tuple[Tensor, Tensor]:
    """The motion (R', t') that carries ``x`` by s times the motion (R, t) about the points' centroid: s intervals at
    the same velocities (s times the turn about the moving centroid, s times its drift)."""
    centre = x.mean(0)
    turn = _rotation_power(rotation, s)
    return turn, centre - centre @ turn.T + s * (centre @ rotation.T + shift - centre)


def _pixels_of(points: Tensor, frame: Frame) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Where ``frame`` sees ``points`` [N, 3]: inside [N] (in front of the camera and inside the image), their depth z
    [N], and the row and column [N] of their pixel (clamped into the image)."""
    uv, z = frame.camera.project_points(points)
    h, w = frame.depth.shape
    j, i = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (j >= 0) & (j < w) & (i >= 0) & (i < h) & (z > 0)
    return inside, z, i.clamp(0, h - 1), j.clamp(0, w - 1)


def _came_to_rest(points: Tensor, frame: Frame, min_visible: int, depth_tolerance: float = 0.03) -> bool:
    """Whether a body without flow pairs has stopped: most of its ``points`` that ``frame`` sees (projected inside it,
    at the depth it measures there within ``depth_tolerance`` of it) lie off the motion mask (a still body leaves it)."""
    inside, z, i, j = _pixels_of(points, frame)
    measured = frame.depth.double()[i, j]
    seen = inside & (measured > 0) & ((measured - z).abs() < depth_tolerance * z)
    return int(seen.sum()) >= min_visible and float(frame.mask[i, j][seen].float().mean()) < 0.5


def seen_through(points: Tensor, frame: Frame, tolerance: float) -> float:
    """The share of ``points`` [N, 3] inside ``frame``'s view that it sees through: at their pixel and its eight
    neighbours it measures no surface, or only farther ones than their depth + ``tolerance`` (world units). Points on
    an opaque surface are never seen through, so a wrong motion of a body shows here (the neighbours forgive a point
    on a silhouette a pixel's rounding); 0 when none is in view."""
    inside, z, i, j = _pixels_of(points, frame)
    depth = frame.depth.double()
    nearest = -torch.nn.functional.max_pool2d(-torch.where(depth > 0, depth, math.inf)[None, None], 3, 1, 1)[0, 0]
    through = inside & (nearest[i, j] > z + tolerance)
    return float(through.sum()) / max(int(inside.sum()), 1)


def moving_surface(frame: Frame) -> tuple[Tensor, Tensor]:
    """The surface ``frame`` shows on its motion mask, lifted with its depth: points [M, 3] and unit normals [M, 3]
    (world, float64; a normal from the lifted neighbours' differences, zero on the surface's outline, where a
    neighbour is off it)."""
    depth = frame.depth.double()
    points = backproject(depth, frame.camera)  # [H, W, 3]
    use = frame.mask & (depth > 0)
    inner = torch.zeros_like(use)
    inner[1:-1, 1:-1] = use[1:-1, 1:-1] & use[:-2, 1:-1] & use[2:, 1:-1] & use[1:-1, :-2] & use[1:-1, 2:]
    normals = torch.zeros_like(points)
    normals[1:-1, 1:-1] = torch.linalg.cross(points[1:-1, 2:] - points[1:-1, :-2], points[2:, 1:-1] - points[:-2, 1:-1])
    normals = torch.where(inner[..., None], normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12), 0.0)
    return points[use], normals[use]


def refine_motion(
    x: Tensor, rotation: Tensor, shift: Tensor, a: Tensor, b: Tensor, surface: tuple[Tensor, Tensor], frame: Frame,
    reach: float, inlier: float, rounds: int = 8,
) -> tuple[Tensor, Tensor, int, int]:
    """The motion (R, t) of a body's points ``x`` [N, 3] fitted, from (``rotation``, ``shift``), to the flow pairs
    ``a`` -> ``b`` and to the surface ``frame`` shows (``surface``: points and normals, :func:`moving_surface`) at
    once: each round one fit (:func:`point_plane_fit`) to the pairs within ``inlier`` of the current motion and to the
    carried points ``frame`` does not see hidden (behind its surface), each paired with its nearest surface point
    within ``reach`` (3x on the first rounds): an iterative closest point fit. Inside the surface only the distance
    along the surface's normal counts (point to plane: where the samples lie on it must not pull the body along it);
    on its outline point to point. The flow pins what the surface leaves free (a sphere's spin, a plane's slide), the
    surface corrects the flow's drift and its failures. Returns (R, t, flow pairs used, surface pairs used)."""
    n_flow = n_surface = 0
    for round_ in range(rounds):
        flow = (a @ rotation.T + shift - b).norm(dim=1) < inlier
        moved = x @ rotation.T + shift
        inside, z, i, j = _pixels_of(moved, frame)
        measured = frame.depth.double()[i, j]
        cut = 3 * reach if round_ < rounds // 2 else reach
        pairs = inside & ((measured <= 0) | (z < measured + inlier))  # not hidden
        target, normal = moved, torch.zeros_like(moved)
        points, normals = surface
        if len(points) and bool(pairs.any()):
            distance, nearest = _nearest(moved, points)
            pairs &= distance < cut
            target, normal = points[nearest], normals[nearest]  # a zero normal: the outline
        else:
            pairs = torch.zeros_like(pairs)
        n_flow, n_surface = int(flow.sum()), int(pairs.sum())
        if n_flow + n_surface < 3:
            break
        rotation, shift = point_plane_fit(rotation, shift, a[flow], b[flow], x[pairs], target[pairs], normal[pairs])
    return rotation, shift, n_flow, n_surface


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


def _flow_motion(
    a: Tensor, b: Tensor, owned: Tensor, distance: Tensor, reach: float, inlier: float, config: RigidTrackConfig,
    generator: torch.Generator,
) -> tuple[tuple[Tensor, Tensor] | None, Tensor]:
    """A body's motion from the flow pairs it ``owned`` (their start nearest its points) within ``reach`` of its
    points (3x, 10x when too few agree): RANSAC (:func:`ransac_rigid`). Returns (motion or None, the pairs it was
    fitted to, else those within 3x ``reach``)."""
    for within in (reach, 3 * reach, 10 * reach):
        near = owned & (distance < within)
        if int(near.sum()) >= config.min_pairs:
            fit = ransac_rigid(a[near], b[near], inlier, config.iterations, generator)
            if fit is not None and int(fit[2].sum()) >= _MIN_INLIERS:
                return fit[:2], near
    return None, owned & (distance < 3 * reach)


def _surface_owners(
    x: Tensor, body: Tensor, alive: Tensor, continued: dict[int, tuple[Tensor, Tensor]], surface: Tensor,
) -> Tensor:
    """The body each point of frame t+1's moving surface ``surface`` [M, 3] is nearest to [M] once every tracked body
    is carried by its motion in ``continued`` (its last velocity; -1 when none is tracked; colliding bodies: a body's
    surface fit must not take its neighbour's surface)."""
    guess = x.clone()
    for bi, (turn, drift) in continued.items():
        rows = body == bi
        guess[rows] = x[rows] @ turn.T + drift
    tracked = alive[body]
    if not len(surface) or not bool(tracked.any()):
        return torch.full((len(surface),), -1, dtype=torch.long)
    return body[tracked][_nearest(surface, guess[tracked])[1]]


def _best_motion(
    x: Tensor, starts: list[tuple[Tensor, Tensor]], a: Tensor, b: Tensor, surface: tuple[Tensor, Tensor], frame: Frame,
    reach: float, inlier: float, min_pairs: int, look: Look | None = None,
) -> tuple[tuple[Tensor, Tensor] | None, float]:
    """Of the motions refined (:func:`refine_motion`) from each of ``starts`` and fitted to at least ``_MIN_INLIERS``
    flow pairs or ``min_pairs`` surface points, the one most flow pairs agree with among those that leave at most
    ``_SEEN_THROUGH_MARGIN`` more of the body's points ``x`` seen through in ``frame`` than the best
    (:func:`seen_through`): the surface rules out motions it contradicts, the flow chooses among those it allows
    (a turn in the image plane, a slide along a face, leave the surface where it was). With a ``look``, the chosen
    motion is refined by the images too (:class:`Look`); where no motion the surface allows has ``_MIN_INLIERS`` flow
    pairs (the flow failed: a fast motion), each fitted motion that leaves no more than ``max_seen_through`` seen
    through is, and the one the body looks most alike under is chosen (the surface alone picked wrong motions there).
    Returns (motion or None, its share seen through)."""
    fits = []
    for rotation, shift in starts:
        rotation, shift, n_flow, n_surface = refine_motion(x, rotation, shift, a, b, surface, frame, reach, inlier)
        if n_flow >= _MIN_INLIERS or n_surface >= min_pairs:
            fits.append((seen_through(x @ rotation.T + shift, frame, inlier), n_flow, (rotation, shift)))
    if not fits:
        return None, math.inf
    lowest = min(f[0] for f in fits)
    allowed = [f for f in fits if f[0] <= lowest + _SEEN_THROUGH_MARGIN]
    through, n_flow, motion = max(allowed, key=lambda f: (f[1], -f[0]))
    if look is None:
        return motion, through
    if n_flow >= _MIN_INLIERS:
        return look.refined(motion, through)[:2]
    looked = [look.refined(m, t) for t, _, m in fits if t <= max(through, look.config.max_seen_through)]
    return max(looked, key=lambda f: f[2] if not math.isnan(f[2]) else -math.inf)[:2]


@dataclass
class Look:
    """What refines one body's motion over one interval by its look (:func:`photometric_refine`)."""

    x: Tensor  # [N, 3] the body's tracked points at frame t
    shown: Tensor  # [M, 3] the surface frame t shows of it (its depth lifted on the motion mask)
    pair: FlowPair
    surface: tuple[Tensor, Tensor]  # frame t+1's moving surface near the body: points and normals
    images: PairImages  # the pair's images, prepared once per interval (:func:`pair_images`)
    inlier: float  # world units
    footprint: float  # world units a pixel spans at the moving surface's median depth
    config: RigidTrackConfig

    def refined(self, motion: tuple[Tensor, Tensor], through: float) -> tuple[tuple[Tensor, Tensor], float, float]:
        """``motion`` refined by the body's look, or kept as it is when the refined one leaves more than
        ``_SEEN_THROUGH_MARGIN`` more of the body's points seen through in frame t+1 than ``through`` (``motion``'s
        own share), or looks more than ``config.max_look_drop`` less alike (:func:`look_agreement`). Returns (the
        motion, its share seen through, how alike the body looks under it)."""
        frame0, frame1, tolerance = self.pair.frame0, self.pair.frame1, 3 * self.inlier
        before = look_agreement(self.shown, *motion, frame0, frame1, self.images, tolerance)
        rotation, shift = photometric_refine(self.shown, *motion, frame0, frame1, self.images, self.surface, tolerance,
                                             self.footprint)
        after = look_agreement(self.shown, rotation, shift, frame0, frame1, self.images, tolerance)
        moved_through = seen_through(self.x @ rotation.T + shift, frame1, self.inlier)
        if moved_through > through + _SEEN_THROUGH_MARGIN or not after >= before - self.config.max_look_drop:
            return motion, through, before
        return (rotation, shift), moved_through, after


def _later_surfaces(
    positions: Tensor, known: Tensor, body: Tensor, surfaces: list[Tensor], link: float, per_frame: int,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor]:
    """Points of the later frames' moving surfaces ``surfaces`` (frame k's [M_k, 3], :func:`moving_surface`; the
    first frame's unused) on tracked bodies, with their tracks: a surface point of frame k
    belongs to the body of its nearest tracked point when it is connected to tracked points (within ``link``, through
    other surface points); it is carried back to the first frame by the inverse of that body's motion to frame k, then
    along the body's motion to every frame. Returns (positions [T, Q, 3], known [T, Q], body [Q])."""
    n_bodies, n_frames = int(body.max()) + 1, len(positions)
    poses = {}  # (frame, body) -> the body's motion from the first frame (Kabsch of its tracked points: exact)
    for k in range(n_frames):
        for bi in range(n_bodies):
            rows = (body == bi) & known[k]
            if int(rows.sum()) >= 3:
                poses[k, bi] = rigid_fit(positions[0, rows], positions[k, rows])
    added, owners = [], []
    for k in range(1, n_frames):
        tracked, surface = known[k], surfaces[k]
        if not bool(tracked.any()) or not len(surface):
            continue
        surface = surface[torch.randperm(len(surface), generator=generator)[:4 * per_frame]]
        n_tracked = int(tracked.sum())
        labels = connected_labels(torch.cat([positions[k, tracked], surface]), link)
        attached = torch.isin(labels[n_tracked:], labels[:n_tracked])
        owner = body[tracked][_nearest(surface, positions[k, tracked])[1]]
        keep = torch.nonzero(attached).flatten()[:per_frame]
        for q in keep.tolist():
            if (k, int(owner[q])) in poses:
                rotation, shift = poses[k, int(owner[q])]
                added.append((surface[q] - shift) @ rotation)  # R^T (y - t): where it was at the first frame
                owners.append(int(owner[q]))
    if not added:
        return positions[:, :0], known[:, :0], body[:0]
    canonical, owner = torch.stack(added), torch.tensor(owners, dtype=torch.long)
    out = canonical.expand(n_frames, -1, -1).clone()
    out_known = torch.zeros(n_frames, len(owner), dtype=torch.bool)
    for k in range(n_frames):
        for bi in torch.unique(owner).tolist():
            if (k, bi) in poses:
                rows = owner == bi
                out[k, rows] = canonical[rows] @ poses[k, bi][0].T + poses[k, bi][1]
                out_known[k, rows] = True
    return out, out_known, owner


@dataclass(frozen=True)
class _Interval:
    """What every chain reads of one training interval, made once: its flow pair, the pair's lifted moving flow
    (:func:`lifted_pairs`) and frame t+1's moving surface (:func:`moving_surface`)."""

    pair: FlowPair
    a: Tensor  # [K, 3] the lifted pairs' starts (world units)
    b: Tensor  # [K, 3] their ends
    surface: tuple[Tensor, Tensor]  # frame t+1's moving surface: points [M, 3] and normals [M, 3]


@dataclass
class _Chain:
    """One chain of the bodies' motions through the recording (:func:`_chain`)."""

    positions: Tensor  # [T, N, 3] the first frame's tracked points, carried (world units)
    known: Tensor  # [T, N] bool
    found: Tensor  # [T - 1, B] bool: a motion was fitted for body b over interval k


def _chain(
    intervals: list[_Interval], first_surface: Tensor, start: Tensor, body: Tensor, footprint: float,
    config: RigidTrackConfig, generator: torch.Generator,
) -> _Chain:
    """Chain every body's motion through ``intervals`` from its points ``start`` [N, 3] (steps 3-6 of the module
    docstring); ``first_surface`` is the first frame's moving surface, ``footprint`` the world units a pixel spans."""
    link, inlier, reach = config.link * footprint, config.inlier * footprint, config.reach * footprint
    n_bodies = int(body.max()) + 1
    x, alive = start.clone(), torch.ones(n_bodies, dtype=torch.bool)
    rest = (torch.eye(3, dtype=x.dtype), torch.zeros(3, dtype=x.dtype))
    gaps = [0] * n_bodies
    last: dict[int, tuple[Tensor, Tensor, float]] = {}  # each body's last motion and its interval's length
    positions, known, found = [x], [alive[body]], []
    previous = first_surface  # frame k's moving surface, each body's part of it fitted photometrically
    for interval in intervals:
        pair, a, b, surface = interval.pair, interval.a, interval.b, interval.surface
        distance, owner = torch.zeros(0, dtype=x.dtype), torch.zeros(0, dtype=torch.long)
        if len(a):
            distance, nearest = _nearest(a, x)
            owner = body[nearest]
        continued = {bi: _constant_velocity(x[body == bi], rotation, shift, pair.dt / dt_last)  # the last velocity
                     for bi, (rotation, shift, dt_last) in last.items() if alive[bi]}
        claimed = _surface_owners(x, body, alive, continued, surface[0])
        shown = torch.full((len(previous),), -1)  # the body frame k shows at each point of its moving surface
        if config.photometric and len(previous):
            distance_to, nearest_to = _nearest(previous, x)
            shown = torch.where(distance_to < 2 * link, body[nearest_to], shown)
        images = pair_images(pair.frame0, pair.frame1, config.high_pass) if config.photometric else None
        moved = x.clone()
        found_k = torch.zeros(n_bodies, dtype=torch.bool)
        for bi in range(n_bodies):
            if not alive[bi]:
                continue
            rows = body == bi
            flow_motion, mine = _flow_motion(a, b, (owner == bi), distance, reach, inlier, config, generator)
            starts = [] if flow_motion is None else [flow_motion]  # motions to refine from: the flow's, ...
            if bi in continued:  # ... constant velocity, ...
                starts.append(continued[bi])
            starts.append(rest)  # ... and rest
            own_surface = (surface[0][claimed == bi], surface[1][claimed == bi])
            look = None if images is None else Look(x[rows], previous[shown == bi], pair, own_surface, images, inlier,
                                                    footprint, config)
            motion, through = _best_motion(x[rows], starts, a[mine], b[mine], own_surface, pair.frame1, reach, inlier,
                                           config.min_pairs, look)
            if motion is not None and through <= config.max_seen_through:
                gaps[bi], last[bi], found_k[bi] = 0, (*motion, pair.dt), True
                moved[rows] = x[rows] @ motion[0].T + motion[1]
            elif _came_to_rest(x[rows], pair.frame0, config.min_pairs):
                gaps[bi], last[bi] = 0, (*rest, pair.dt)
            elif bi in continued and gaps[bi] < config.max_gap:
                gaps[bi] += 1
                turn, drift = continued[bi]
                moved[rows] = x[rows] @ turn.T + drift
            else:
                alive[bi] = False
        x, previous = moved, surface[0]
        positions.append(x)
        known.append(alive[body])
        found.append(found_k)
    return _Chain(torch.stack(positions), torch.stack(known), torch.stack(found))


def chain_look(
    positions: Tensor, known: Tensor, body: Tensor, frames: list[Frame], tolerance: float,
) -> tuple[Tensor, Tensor]:
    """How alike each body's tracked points look from each frame to the next: per interval the correlation of their
    colours (:func:`look_correlation`) over its points known at both ends and seen in both frames, and of those
    correlations per body their mean and their lowest ([B] each; NaN for a body never seen so). A body tracked right
    looks alike all along (the generated rigid scene: means 0.87-0.95, lowest 0.17-0.85); a chain that went wrong
    puts its points on other parts of the texture, and over some interval they look anti-correlated with themselves
    (lowest -0.20 and -0.30 for the boxes that went wrong). The correlation, not :func:`look_agreement`'s product
    with the share seen: that share, which turning and occlusion change, outweighed it. ``positions`` [T, N, 3] and
    ``known`` [T, N] are the points at ``frames``' times, ``tolerance`` world units."""
    n_bodies = int(body.max()) + 1
    looks: list[list[float]] = [[] for _ in range(n_bodies)]
    plain = [blurred(frame.image.double(), _LOOK_BLUR) for frame in frames]
    for k in range(len(frames) - 1):
        for bi in range(n_bodies):
            rows = (body == bi) & known[k] & known[k + 1]
            if int(rows.sum()) >= _MIN_LOOK_POINTS:
                correlation, _ = look_correlation(positions[k, rows], positions[k + 1, rows], frames[k], frames[k + 1],
                                                  (plain[k], plain[k + 1]), tolerance)
                if not math.isnan(correlation):
                    looks[bi].append(correlation)
    mean = torch.tensor([sum(c) / len(c) if c else math.nan for c in looks], dtype=torch.float64)
    lowest = torch.tensor([min(c) if c else math.nan for c in looks], dtype=torch.float64)
    return mean, lowest


def track_rigid_bodies(cache: FlowCache, config: RigidTrackConfig, generator: torch.Generator) -> RigidTracks:
    """Track the first training frame's moving surface through every training interval as rigid bodies (module
    docstring; a body whose chain went wrong is chained again, up to ``config.attempts`` times in all, and the chain
    that looks most alike kept: :func:`chain_look`).
    ValueError naming the frame when a frame has no depth or motion mask, or the first frame shows no moving surface
    with depth."""
    frames = cache.frames
    for frame in frames:
        if frame.depth is None or frame.mask is None:
            raise ValueError(f"rigid-body tracks need depth maps and motion masks: {frame.name or frame.path} has no "
                             f"{'depth' if frame.depth is None else 'motion mask'}")
    if config.attempts < 1:
        raise ValueError(f"rigid-body tracks: attempts must be at least 1, got {config.attempts}")
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
    start = first[torch.randperm(len(first), generator=generator)[:config.points]]
    body = _bodies(start, first, config.link * footprint, config.min_body_points)
    still = (~f0.mask) & (f0.depth > 0)
    h, w = still.shape
    pixels = pixel_centers(h, w, torch.float64)[still]
    pick = torch.randperm(len(pixels), generator=generator)[:config.static_points]
    static = unproject_points(pixels[pick], f0.depth.double()[still][pick], f0.camera)

    intervals = []
    for k in range(len(cache)):
        pair = cache.pair(k)
        intervals.append(_Interval(pair, *lifted_pairs(pair), moving_surface(pair.frame1)))
    first_surface = moving_surface(f0)[0]
    chain = _chain(intervals, first_surface, start, body, footprint, config, generator)
    tolerance = 3 * config.inlier * footprint  # as the look judges a photometric fit (Look.refined)
    mean, lowest = chain_look(chain.positions, chain.known, body, frames, tolerance)
    chains = torch.ones(len(mean), dtype=torch.long)
    for _ in range(config.attempts - 1):
        wrong = torch.nonzero(lowest < 0).flatten().tolist()  # chains gone wrong (NaN, never seen: not wrong)
        if not wrong:
            break
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        other = _chain(intervals, first_surface, start, body, footprint, config, torch.Generator().manual_seed(seed))
        other_mean, other_lowest = chain_look(other.positions, other.known, body, frames, tolerance)
        for bi in wrong:
            chains[bi] += 1
            if bool(other_mean[bi] > mean[bi]):
                rows = body == bi
                chain.positions[:, rows], chain.known[:, rows] = other.positions[:, rows], other.known[:, rows]
                chain.found[:, bi], mean[bi], lowest[bi] = other.found[:, bi], other_mean[bi], other_lowest[bi]
    surfaces = [first] + [interval.surface[0] for interval in intervals]  # the first's unused by the later points
    later = _later_surfaces(chain.positions, chain.known, body, surfaces, config.link * footprint, config.later_points,
                            generator)
    times = torch.tensor([f.time for f in frames], dtype=torch.float64)
    return RigidTracks(times, torch.cat([chain.positions, later[0]], 1), torch.cat([chain.known, later[1]], 1),
                       torch.cat([body, later[2]]), static, chain.found, chains, mean)
