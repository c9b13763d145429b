"""A small dynamic scene the project generates itself: the default scene of ``pidg demo`` and a test fixture.

Why: real dynamic datasets are large downloads without ground-truth motion. This scene is made in 2-3 seconds,
needs no files, and everything about it is known exactly (geometry, motion, which pixels move), so training can be
shown and checked on a 2-core CPU.

Content (world z up, floor at z = -0.5):

* a "jelly ring": a textured torus of flat surface Gaussians that bends (taco fold), squashes and stretches
  (volume preserving), spins and hops along a figure-eight. Its deformation ``phi(X, t)`` is analytic and the
  identity at t = 0, so the t = 0 pose *is* the canonical shape;
* static content for static/dynamic decoupling: a checkered floor with a low-frequency tint and two striped balls.

Every Gaussian is carried through the deformation to first order: mean ``phi(mu, t)``, covariance
``J Sigma J^T`` with ``J`` the analytic Jacobian of ``phi`` at ``mu`` (factored into rotation and scales by an
eigendecomposition for the rasterizer). Colours are constant per Gaussian (shading is baked in canonical space),
as deformation models assume.

Capture, like D-NeRF: a monocular video, one camera per time, moving along a wavy orbit (one full turn over the
sequence by default, so consecutive training views differ by ~6 degrees and the object is seen from all sides).
Training times are t_i = i / (n - 1); test (and optional val) frames sit at held-out midpoint times, seen from
off-orbit views (azimuth offset, other elevation). Frames are numbered on the common time grid (``r_0000``,
``r_0001``, ...; training frames even, held-out frames odd), so time from the json and time from the frame
number agree and mask file names are unique across splits.

Images are RGBA renders (straight alpha); :func:`make_procedural_scene` composites them on the configured
background with exactly the arithmetic of the dataset loader, so the in-memory scene and the one read back from
:func:`write_procedural_dataset`'s folder are identical. Every frame also has its true depth (camera z, as an
RGB-D sensor would measure it), which a run may train against (``--optim.lambda_depth``): a monocular orbit leaves
the moving ring's depth under-determined, and that, not the model, is what limits its novel views
(docs/cpu-quality.md, "The train/test gap").
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from pidg.config_tools import validate_config
from pidg.data.io import composite_rgba_float
from pidg.data.motion_gt import (
    FrameFlow,
    MotionObject,
    VertexMotion,
    composited_flow,
    projected_displacement,
    write_frame_flow,
    write_motion_gt,
)
from pidg.data.ply import write_ply_points
from pidg.data.scene import Background, Frame, PointCloud, SceneData, compute_bounds
from pidg.render.api import rasterize
from pidg.render.camera import Camera, orbit_camera_to_world
from pidg.render.projection import rotmat_to_quat
from pidg.render.scenes import GaussianScene

InitPoints = Literal["surface", "random"]

FLOOR_Z = -0.5
FLOOR_HALF_SIZE = 2.0
TORUS_MAJOR, TORUS_MINOR = 0.55, 0.2
BALLS = (((1.15, 0.95), 0.22), ((-1.0, -1.15), 0.22))  # (x, y) on the floor, radius
CAMERA_TARGET = (0.0, 0.0, -0.1)
_LIGHT = torch.tensor([0.35, -0.45, 0.82], dtype=torch.float64)  # baked-shading light direction (normalised below)
# Share of the Gaussians per part; the torus gets the rest.
_FLOOR_SHARE, _BALL_SHARE = 0.35, 0.10
GT_VELOCITY_STEP = 1e-5  # dataset time: central differences of the analytic deformation (float64)


@dataclass(frozen=True)
class ProceduralFrame:
    """One rendered view of the scene: what a dataset frame stores, plus the ground truth that comes with it."""

    rgba: np.ndarray  # [H, W, 4] uint8, straight alpha
    mask: np.ndarray  # [H, W] bool, True where the moving ring is seen
    depth: np.ndarray  # [H, W] float32 expected camera z (world units) where alpha >= 0.5, else 0 (= unknown)
    flow: FrameFlow | None  # ground-truth motion flow, when asked for


@dataclass(frozen=True)
class ProceduralSceneConfig:
    """What to generate. Defaults: the ``pidg demo`` scene (60 + 20 frames of 128x128, 2-3 s to make on 2 cores)."""

    n_train: int = 60
    n_test: int = 20
    n_val: int = 0  # optional val split, at held-out times not used by test
    width: int = 128
    height: int = 128
    seed: int = 0
    background: Background = "black"  # as DataConfig: the PIDG paper trains on black
    n_gaussians: int = 8000  # ground-truth Gaussians: ~55 % ring, 35 % floor, 10 % balls
    motion: float = 1.0  # scales every motion term (bend, squash, spin, path), in [0, 1.5]; 0 = ring at rest
    fov_x_deg: float = 50.0
    camera_distance: float = 3.5
    orbit_turns: float = 1.0  # camera turns around the scene over the sequence
    init_points: InitPoints = "surface"  # see ProceduralScene.initial_points
    n_init_points: int = 2000

    def __post_init__(self) -> None:
        validate_config(self)
        if self.n_train < 2:
            raise ValueError(f"ProceduralSceneConfig.n_train must be >= 2, got {self.n_train}")
        if self.n_test < 1 or self.n_val < 0:
            raise ValueError(f"ProceduralSceneConfig: need n_test >= 1 and n_val >= 0, got {self.n_test}, {self.n_val}")
        if self.n_test + self.n_val > self.n_train - 1:
            raise ValueError(
                f"ProceduralSceneConfig: held-out frames sit between training frames, so n_test + n_val must be "
                f"<= n_train - 1 = {self.n_train - 1}, got {self.n_test + self.n_val}"
            )
        if self.width < 8 or self.height < 8:
            raise ValueError(f"ProceduralSceneConfig: image size must be >= 8x8, got {self.width}x{self.height}")
        if self.n_gaussians < 500:
            raise ValueError(f"ProceduralSceneConfig.n_gaussians must be >= 500, got {self.n_gaussians}")
        if not 0.0 <= self.motion <= 1.5:  # beyond 1.5 the ring would pass through the balls
            raise ValueError(f"ProceduralSceneConfig.motion must be in [0, 1.5], got {self.motion}")
        if not (0.0 < self.fov_x_deg < 170.0 and self.camera_distance > 0.0):
            raise ValueError("ProceduralSceneConfig: need 0 < fov_x_deg < 170 and camera_distance > 0")
        if self.n_init_points < 1:
            raise ValueError(f"ProceduralSceneConfig.n_init_points must be >= 1, got {self.n_init_points}")

    @property
    def background_rgb(self) -> tuple[float, float, float]:
        return (1.0, 1.0, 1.0) if self.background == "white" else (0.0, 0.0, 0.0)


# ---------------------------------------------------------------------------------------------------------------
# small geometry helpers
# ---------------------------------------------------------------------------------------------------------------
def _tangent_frame(normal: Tensor) -> Tensor:
    """Right-handed frames [N, 3, 3] with columns (t1, t2, n), for flat splats lying on a surface."""
    helper = torch.where(
        (normal[:, 2].abs() < 0.9).unsqueeze(-1),
        normal.new_tensor([0.0, 0.0, 1.0]).expand_as(normal),
        normal.new_tensor([1.0, 0.0, 0.0]).expand_as(normal),
    )
    t1 = torch.linalg.cross(helper, normal)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(normal, t1)
    return torch.stack([t1, t2, normal], dim=-1)


def _shade(normal: Tensor) -> Tensor:
    """Baked diffuse shading in [0.55, 1] [N, 1]: constant per Gaussian, gives the eye some 3D shape."""
    light = _LIGHT / _LIGHT.norm()
    return (0.55 + 0.45 * (normal @ light).clamp_min(0)).unsqueeze(-1)


def _hue(h: Tensor) -> Tensor:
    """Saturated RGB [N, 3] for hue h (period 1), a cosine palette."""
    return torch.stack([0.5 + 0.45 * torch.cos(2 * math.pi * (h - k / 3)) for k in range(3)], dim=-1)


def _golden_lattice(n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """n well-spread points in [0, 1)^2 (a Fibonacci lattice with a seeded shift): even coverage, no holes."""
    i = torch.arange(n, dtype=torch.float64)
    shift = torch.rand(2, generator=gen, dtype=torch.float64)
    a = torch.remainder(i / n + shift[0], 1.0)
    b = torch.remainder(i * (math.sqrt(5.0) - 1.0) / 2.0 + shift[1], 1.0)
    return a, b


# ---------------------------------------------------------------------------------------------------------------
# the scene
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Motion:
    """The ring's motion parameters at one time (all smooth in t, the identity at t = 0)."""

    bend: float  # curvature of the fold along the ring's x axis (1 / world units)
    squash: float  # vertical scale; horizontal scale is 1 / sqrt(squash) (volume preserving)
    spin: float  # rotation about the vertical axis (radians)
    offset: tuple[float, float, float]  # translation of the ring's centre


def motion_at(t: float, amplitude: float = 1.0) -> Motion:
    """Over t in [0, 1]: one fold cycle (up, then down), two squash cycles and two hops, a quarter turn and one
    figure-eight. Amplitudes are moderate so that ~60 frames sample the motion smoothly (a few pixels a frame)."""
    a, w = amplitude, 2.0 * math.pi * t
    return Motion(
        bend=0.9 * a * math.sin(w),
        squash=1.0 + 0.22 * a * math.sin(2 * w),
        spin=0.5 * math.pi * a * t,
        offset=(0.3 * a * math.sin(w), 0.2 * a * math.sin(2 * w), 0.15 * a * 0.5 * (1.0 - math.cos(2 * w))),
    )


def deform_local(x: Tensor, mo: Motion) -> tuple[Tensor, Tensor]:
    """Bend, squash and spin points [P, 3] given in the ring's frame: (positions [P, 3], Jacobians [P, 3, 3]).

    The bend maps the ring's x axis onto an arc of curvature k: its Jacobian is a rotation by k x in the x-z
    plane times a stretch (1 - k z) along x; squash and spin are linear. Hence everything is closed-form.
    """
    px, py, pz = x.unbind(-1)
    k = mo.bend
    ang = k * px
    c, s = torch.cos(ang), torch.sin(ang)
    # sin(kx)/k and (1 - cos kx)/k written with sinc so that k = 0 (no bend) is exact.
    x1 = px * torch.sinc(ang / math.pi) - pz * s
    z1 = px * torch.sin(0.5 * ang) * torch.sinc(0.5 * ang / math.pi) + pz * c
    h = 1.0 / math.sqrt(mo.squash)
    cp, sp = math.cos(mo.spin), math.sin(mo.spin)
    x2, y2, z2 = h * x1, h * py, mo.squash * z1
    pos = torch.stack([cp * x2 - sp * y2, sp * x2 + cp * y2, z2], dim=-1)
    zero, one = torch.zeros_like(px), torch.ones_like(px)
    stretch = 1.0 - k * pz
    j_bend = torch.stack(
        [
            torch.stack([c * stretch, zero, -s], dim=-1),
            torch.stack([zero, one, zero], dim=-1),
            torch.stack([s * stretch, zero, c], dim=-1),
        ],
        dim=-2,
    )
    j_rest = x.new_tensor([[cp * h, -sp * h, 0.0], [sp * h, cp * h, 0.0], [0.0, 0.0, mo.squash]])
    return pos, j_rest @ j_bend


def _lowest_point(ring: Tensor, amplitude: float) -> float:
    """Lowest z the ring (points in its own frame) reaches over the sequence, on a fine time grid.

    Why: the ring then rests as low as it can without ever entering the floor, whatever the amplitude.
    """
    sample = ring[:: max(1, len(ring) // 800)]
    lows = []
    for t in np.linspace(0.0, 1.0, 241):
        mo = motion_at(float(t), amplitude)
        lows.append(float(deform_local(sample, mo)[0][:, 2].min()) + mo.offset[2])
    return min(lows)


class ProceduralScene:
    """Ground-truth Gaussians (canonical, float64) and the capture schedule for one :class:`ProceduralSceneConfig`."""

    def __init__(self, config: ProceduralSceneConfig) -> None:
        self.config = config
        gen = torch.Generator().manual_seed(config.seed)
        n = config.n_gaussians
        n_floor, n_balls = int(n * _FLOOR_SHARE), int(n * _BALL_SHARE)
        parts = [self._torus(n - n_floor - n_balls, gen), self._floor(n_floor, gen), self._balls(n_balls, gen)]
        ring = parts[0]
        self.ring_origin = (0.0, 0.0, FLOOR_Z + 0.03 - _lowest_point(ring[0], config.motion))
        parts[0] = (ring[0] + torch.tensor(self.ring_origin, dtype=torch.float64), *ring[1:])
        self.means = torch.cat([p[0] for p in parts])  # [N, 3] canonical (= t = 0) positions
        self.rotations = torch.cat([p[1] for p in parts])  # [N, 3, 3] canonical rotations (columns: splat axes)
        self.scales = torch.cat([p[2] for p in parts])  # [N, 3]
        self.colors = torch.cat([p[3] for p in parts]).clamp(0, 1)  # [N, 3]
        opacity = (0.92, 0.98, 0.95)
        self.opacities = torch.cat([torch.full((len(p[0]),), o, dtype=torch.float64) for p, o in zip(parts, opacity)])
        self.is_dynamic = torch.zeros(len(self.means), dtype=torch.bool)
        self.is_dynamic[: len(ring[0])] = True
        self._quats = rotmat_to_quat(self.rotations)
        self.azimuth0 = 2.0 * math.pi * float(torch.rand(1, generator=gen, dtype=torch.float64))

    # ---- canonical parts: (means, rotation frames, scales, colours) ---------------------------------------
    @staticmethod
    def _torus(n: int, gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Flat splats evenly covering a torus (object frame, centred at 0); hue around it, 8x4 checker."""
        big, small = TORUS_MAJOR, TORUS_MINOR
        a, b = _golden_lattice(n, gen)
        u = 2 * math.pi * a
        # Area density on the torus is proportional to (R + r cos v): invert its CDF with Newton steps.
        v = 2 * math.pi * b
        for _ in range(8):
            f = (v + (small / big) * torch.sin(v)) / (2 * math.pi) - b
            v = v - f * (2 * math.pi) / (1 + (small / big) * torch.cos(v))
        ring = big + small * torch.cos(v)
        means = torch.stack([ring * torch.cos(u), ring * torch.sin(u), small * torch.sin(v)], dim=-1)
        normal = torch.stack([torch.cos(v) * torch.cos(u), torch.cos(v) * torch.sin(u), torch.sin(v)], dim=-1)
        t_u = torch.stack([-torch.sin(u), torch.cos(u), torch.zeros_like(u)], dim=-1)
        frames = torch.stack([t_u, torch.linalg.cross(normal, t_u), normal], dim=-1)
        spacing = math.sqrt(4 * math.pi**2 * big * small / n)
        scales = torch.tensor([0.65, 0.65, 0.15], dtype=torch.float64).mul(spacing).expand(n, 3).clone()
        checker = (torch.floor(8 * a) + torch.floor(4 * v / (2 * math.pi))) % 2
        colors = _hue(a) * (0.55 + 0.45 * checker).unsqueeze(-1) * _shade(normal)
        return means, frames, scales, colors

    @staticmethod
    def _floor(n: int, gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """A jittered grid of flat splats; 0.5-unit checker times a smooth tint, so no two places look alike."""
        side = max(2, int(math.sqrt(n)))
        cell = 2 * FLOOR_HALF_SIZE / side
        centres = (torch.arange(side, dtype=torch.float64) + 0.5) * cell - FLOOR_HALF_SIZE
        gx, gy = torch.meshgrid(centres, centres, indexing="ij")
        xy = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)
        xy = xy + 0.15 * cell * (torch.rand(xy.shape, generator=gen, dtype=torch.float64) * 2 - 1)
        m = len(xy)
        means = torch.cat([xy, torch.full((m, 1), FLOOR_Z, dtype=torch.float64)], dim=-1)
        frames = torch.eye(3, dtype=torch.float64).expand(m, 3, 3).clone()
        scales = torch.tensor([0.7 * cell, 0.7 * cell, 0.05 * cell], dtype=torch.float64).expand(m, 3).clone()
        x, y = xy.unbind(-1)
        checker = ((torch.floor(x / 0.5) + torch.floor(y / 0.5)) % 2).unsqueeze(-1)
        tint = torch.stack(
            [
                0.75 + 0.2 * torch.sin(1.3 * x + 0.4),
                0.72 + 0.2 * torch.sin(1.1 * y + 1.0),
                0.65 + 0.2 * torch.cos(0.9 * (x - y)),
            ],
            dim=-1,
        )
        noise = 0.04 * torch.randn(m, 3, generator=gen, dtype=torch.float64)
        colors = tint * (0.45 + 0.4 * checker) + noise
        return means, frames, scales, colors

    @staticmethod
    def _balls(n: int, gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Two static balls resting on the floor: a six-segment beach ball and a latitude-striped one."""
        out = []
        per = [n // len(BALLS)] * len(BALLS)
        per[0] += n - sum(per)
        for k, (((cx, cy), radius), m) in enumerate(zip(BALLS, per)):
            a, b = _golden_lattice(m, gen)
            z = 1 - 2 * b
            phi = 2 * math.pi * a
            rho = (1 - z**2).clamp_min(0).sqrt()
            normal = torch.stack([rho * torch.cos(phi), rho * torch.sin(phi), z], dim=-1)
            means = normal * radius + torch.tensor([cx, cy, FLOOR_Z + radius], dtype=torch.float64)
            spacing = math.sqrt(4 * math.pi * radius**2 / m)
            scales = torch.tensor([0.65, 0.65, 0.15], dtype=torch.float64).mul(spacing).expand(m, 3).clone()
            if k == 0:
                colors = _hue(torch.floor(6 * a) / 6 + 0.08)
            else:
                stripe = (torch.floor(5 * (z + 1)) % 2).unsqueeze(-1)
                colors = stripe * torch.tensor([0.95, 0.9, 0.8], dtype=torch.float64) + (1 - stripe) * torch.tensor(
                    [0.15, 0.35, 0.7], dtype=torch.float64
                )
            out.append((means, _tangent_frame(normal), scales, colors * _shade(normal)))
        return tuple(torch.cat([o[i] for o in out]) for i in range(4))  # type: ignore[return-value]

    # ---- deformation ----------------------------------------------------------------------------------------
    def deform(self, points: Tensor, t: float) -> tuple[Tensor, Tensor]:
        """The ring's deformation of canonical world points [P, 3]: (positions [P, 3], Jacobians [P, 3, 3])."""
        mo = motion_at(t, self.config.motion)
        origin = points.new_tensor(self.ring_origin)
        pos, jac = deform_local(points - origin, mo)
        return pos + origin + points.new_tensor(mo.offset), jac

    def gaussians(self, t: float) -> GaussianScene:
        """Rasterizer inputs (float32) at time t; ``features`` [N, 1] is 1 for the ring's Gaussians, 0 elsewhere.

        A ring Gaussian's covariance M M^T (M = J R S) is factored by an eigendecomposition into the rotation and
        scales the rasterizer takes; static Gaussians keep their canonical rotation and scales.
        """
        dyn = self.is_dynamic
        pos, jac = self.deform(self.means[dyn], t)
        m = jac @ (self.rotations[dyn] * self.scales[dyn].unsqueeze(-2))
        var, axes = torch.linalg.eigh(m @ m.transpose(-1, -2))
        axes = axes * torch.where(torch.linalg.det(axes) < 0, -1.0, 1.0).reshape(-1, 1, 1)  # a proper rotation
        means, quats, scales = self.means.clone(), self._quats.clone(), self.scales.clone()
        means[dyn], quats[dyn], scales[dyn] = pos, rotmat_to_quat(axes), var.clamp_min(0).sqrt()
        f32 = lambda v: v.to(torch.float32).contiguous()  # noqa: E731
        return GaussianScene(
            means=f32(means),
            quats=f32(quats),
            scales=f32(scales),
            opacities=f32(self.opacities),
            colors=f32(self.colors),
            features=f32(dyn.unsqueeze(-1)),
        )

    # ---- ground-truth motion (pidg.data.motion_gt) -------------------------------------------------------------
    @property
    def frame_interval(self) -> float:
        """Dataset time between consecutive training frames (two steps of the common time grid): the interval of
        the ground-truth flow, equal to a model's ``TimeAxis.frame_interval`` trained on this scene."""
        return 1.0 / (self.config.n_train - 1)

    def ring_positions(self, t: float) -> Tensor:
        """Centres [V, 3] float64 of the ring's ground-truth Gaussians at time t (the ground-truth "vertices")."""
        return self.deform(self.means[self.is_dynamic], t)[0]

    def ring_velocities(self, t: float, h: float = GT_VELOCITY_STEP) -> Tensor:
        """dx/dt [V, 3] float64 of the ring's Gaussian centres, world units per unit of dataset time: central
        differences of the analytic deformation at t +- h (in float64 the error is ~1e-8 of the speed)."""
        return (self.ring_positions(t + h) - self.ring_positions(t - h)) / (2.0 * h)

    def vertex_motion(self, times: Sequence[float]) -> VertexMotion:
        """The ring's centres and velocities at the given times (sorted, repeats dropped); no faces."""
        grid = np.asarray(sorted(set(times)), dtype=np.float64)
        positions = np.stack([self.ring_positions(float(t)).numpy() for t in grid]).astype(np.float32)
        velocities = np.stack([self.ring_velocities(float(t)).numpy() for t in grid]).astype(np.float32)
        return VertexMotion(grid, positions, velocities, np.zeros((0, 3), dtype=np.int64))

    def motion_flow(self, t: float, camera: Camera, dt: float | None = None) -> FrameFlow:
        """The ground-truth flow of the view at time t (see :meth:`render_frame`)."""
        flow = self.render_frame(t, camera, True, dt).flow
        assert flow is not None
        return flow

    # ---- capture --------------------------------------------------------------------------------------------
    def schedule(self) -> dict[str, list[tuple[int, float]]]:
        """(frame number, time) per split on the common grid t = k / (2 (n_train - 1)).

        Training frames are the even numbers; test frames are evenly spread odd numbers (midpoints), val frames
        are evenly spread among the midpoints test left over.
        """
        cfg = self.config
        steps = 2 * (cfg.n_train - 1)
        mids = cfg.n_train - 1

        def spread(n_items: int, n_pick: int) -> list[int]:
            return [int((i + 0.5) * n_items / n_pick) for i in range(n_pick)]

        test = spread(mids, cfg.n_test)
        rest = [j for j in range(mids) if j not in set(test)]
        val = [rest[i] for i in spread(len(rest), cfg.n_val)] if cfg.n_val else []
        out = {"train": [(2 * i, 2 * i / steps) for i in range(cfg.n_train)]}
        if val:
            out["val"] = [(2 * j + 1, (2 * j + 1) / steps) for j in val]
        out["test"] = [(2 * j + 1, (2 * j + 1) / steps) for j in test]
        return out

    def camera_to_world(self, split: str, t: float) -> Tensor:
        """OpenGL camera-to-world [4, 4] float64 of the frame at time t of ``split``.

        Training views follow the orbit (azimuth linear in t, elevation waving between 16 and 40 degrees);
        test and val views are off the orbit (azimuth +-35 degrees, elevation in opposite phase), so they are
        novel views as well as novel times.
        """
        cfg = self.config
        az = self.azimuth0 + 2 * math.pi * cfg.orbit_turns * t
        wave = math.sin(2 * math.pi * 2 * t)
        if split == "train":
            el = 28.0 + 12.0 * wave
        else:
            az += math.radians(35.0 if split == "test" else -35.0)
            el = 28.0 - 12.0 * wave
        return orbit_camera_to_world(CAMERA_TARGET, cfg.camera_distance, az, math.radians(el))

    def camera(self, c2w: Tensor) -> Camera:
        """The camera exactly as the D-NeRF reader builds it from ``transform_matrix`` and ``camera_angle_x``."""
        cfg = self.config
        return Camera.from_fov(c2w, cfg.width, cfg.height, math.radians(cfg.fov_x_deg))

    def render(self, t: float, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(RGBA uint8 [H, W, 4] with straight alpha, motion mask bool [H, W]) of the scene at time t.

        The mask is where the ring is visible: its composited "is dynamic" channel exceeds 0.5, i.e. the ring
        makes up most of the pixel.
        """
        frame = self.render_frame(t, camera, with_flow=False)
        return frame.rgba, frame.mask

    def render_frame(
        self, t: float, camera: Camera, with_flow: bool = True, dt: float | None = None
    ) -> ProceduralFrame:
        """:meth:`render` with the view's depth, and with ``with_flow`` its ground-truth flow, from one rasterizer
        pass.

        Depth is the composited camera z over the composited alpha (the expected depth of what is hit), kept where
        alpha >= 0.5 (:meth:`RenderOutput.opaque_depth`), as a model's rendered depth is kept for the flow
        target and the depth loss.

        The flow runs from t to t + dt (default: one training-frame interval) with ``camera`` held fixed: each
        Gaussian's projected centre displacement, composited with the colour weights beside the "is dynamic"
        channel (so ``dynamic`` is the motion mask); NaN where the composited alpha < 0.5, exactly 0 where only
        static Gaussians are seen.
        """
        g = self.gaussians(t)
        features = g.features
        dt = self.frame_interval if dt is None else dt
        if with_flow:
            dyn = self.is_dynamic
            start, end = self.means.clone(), self.means.clone()
            start[dyn], end[dyn] = self.ring_positions(t), self.ring_positions(t + dt)
            features = torch.cat([features, projected_displacement(camera, start, end).to(torch.float32)], dim=-1)
        with torch.no_grad():
            out = rasterize(
                g.means, g.quats, g.opacities, g.colors, camera, scales=g.scales, features=features, backend="cpu"
            )
        assert out.features is not None
        alpha = out.alpha.clamp(0, 1)
        straight = torch.where(alpha.unsqueeze(-1) > 1e-6, out.rgb / alpha.clamp_min(1e-6).unsqueeze(-1), 0.0)
        rgba = torch.cat([straight.clamp(0, 1), alpha.unsqueeze(-1)], dim=-1)
        rgba_u8 = torch.round(rgba * 255.0).to(torch.uint8).numpy()
        rgba_u8[rgba_u8[..., 3] == 0, :3] = 0  # fully transparent: no colour (keeps PNGs small and tidy)
        mask = (out.features[..., 0] > 0.5).numpy()
        flow = FrameFlow(composited_flow(out.features[..., 1:], out.alpha).numpy(), mask, t, t + dt) if with_flow else None
        depth = out.opaque_depth().to(torch.float32).numpy()
        return ProceduralFrame(rgba_u8, mask, depth, flow)

    def initial_points(self) -> PointCloud:
        """The initial point cloud, standing in for the SfM points of a real capture.

        "surface" (default): a random subset of the ground-truth Gaussian centres at t = 0 (the canonical pose),
        jittered by 1.5 cm, colours jittered by 0.05 -- roughly what SfM gives. "random": uniform points in the
        box above the floor with random colours, like the random initialisation 3DGS-family methods use on
        D-NeRF. Colours are quantised to 8 bits so the in-memory cloud equals the one read from points3d.ply.
        """
        cfg = self.config
        gen = torch.Generator().manual_seed(cfg.seed + 1)  # its own stream: the cloud does not shift the scene
        n = cfg.n_init_points
        if cfg.init_points == "surface":
            idx = torch.randperm(len(self.means), generator=gen)[:n]
            xyz = self.means[idx] + 0.015 * torch.randn(len(idx), 3, generator=gen, dtype=torch.float64)
            rgb = self.colors[idx] + 0.05 * torch.randn(len(idx), 3, generator=gen, dtype=torch.float64)
        else:
            lo = torch.tensor([-FLOOR_HALF_SIZE, -FLOOR_HALF_SIZE, FLOOR_Z], dtype=torch.float64)
            hi = torch.tensor([FLOOR_HALF_SIZE, FLOOR_HALF_SIZE, 0.8], dtype=torch.float64)
            xyz = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=torch.float64)
            rgb = torch.rand(n, 3, generator=gen, dtype=torch.float64)
        rgb = torch.round(rgb.clamp(0, 1) * 255.0) / 255.0
        return PointCloud(xyz.to(torch.float32), rgb.to(torch.float32))


# ---------------------------------------------------------------------------------------------------------------
# generation
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Rendered:
    """One rendered frame with everything both outputs need (in-memory frames and the dataset files)."""

    split: str
    number: int
    time: float
    c2w: Tensor  # [4, 4] float64, OpenGL camera-to-world
    camera: Camera
    view: ProceduralFrame

    @property
    def file_name(self) -> str:
        return f"r_{self.number:04d}"

    @property
    def name(self) -> str:
        return f"{self.split}/{self.file_name}"


def _render_all(scene: ProceduralScene, with_flow: bool = False) -> dict[str, list[_Rendered]]:
    out: dict[str, list[_Rendered]] = {}
    for split, items in scene.schedule().items():
        out[split] = []
        for number, t in items:
            c2w = scene.camera_to_world(split, t)
            camera = scene.camera(c2w)
            out[split].append(_Rendered(split, number, t, c2w, camera, scene.render_frame(t, camera, with_flow)))
    return out


def composite_rgba(rgba: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """uint8 RGB [H, W, 3] of an RGBA uint8 image on ``background``, with the loader's exact arithmetic
    (``pidg.data.io.decode_rgb`` then rounding), so in-memory and reloaded frames are bit-identical."""
    rgb = composite_rgba_float(rgba, background)
    np.clip(np.rint(rgb, out=rgb), 0, 255, out=rgb)
    return rgb.astype(np.uint8)


def _scene_data(
    config: ProceduralSceneConfig, rendered: dict[str, list[_Rendered]], points: PointCloud, root: Path
) -> SceneData:
    def frame(r: _Rendered) -> Frame:
        image = torch.from_numpy(composite_rgba(r.view.rgba, config.background_rgb))
        return Frame(r.camera, r.time, image, torch.from_numpy(r.view.mask), r.name, depth=torch.from_numpy(r.view.depth))

    splits = {split: [frame(r) for r in items] for split, items in rendered.items()}
    centers = torch.stack([r.c2w[:3, 3] for r in rendered["train"]])
    return SceneData(
        root=root,
        kind="procedural",
        splits=splits,
        background=torch.tensor(config.background_rgb, dtype=torch.float32),
        bounds=compute_bounds(centers, points),
        time_source="procedural",
        points3d=points,
        info={"layout": "procedural", "masks": True, "config": asdict(config)},
    )


def make_procedural_scene(config: ProceduralSceneConfig | None = None) -> SceneData:
    """Generate the scene in memory: frames per split (images composited on the background, motion masks),
    bounds from the training cameras and the initial point cloud, as a dataset reader would return them."""
    config = config or ProceduralSceneConfig()
    scene = ProceduralScene(config)
    return _scene_data(config, _render_all(scene), scene.initial_points(), Path(f"procedural-seed{config.seed}"))


def write_procedural_dataset(config: ProceduralSceneConfig | None, out_dir: Path | str) -> Path:
    """Write the scene as a D-NeRF/BlenderNeRF folder that ``pidg.data.load_scene`` reads back unchanged.

    Layout: ``transforms_{train,[val,]test}.json`` (``camera_angle_x``; frames with ``file_path``, ``time`` and
    an OpenGL camera-to-world ``transform_matrix``), RGBA frames ``{split}/r_NNNN.png``, motion masks
    ``mask/r_NNNN.png`` (0/255), depth maps ``depth/r_NNNN.npy`` (float32 camera z, 0 = unknown),
    ``points3d.ply`` and ``procedural.json`` (the config, for provenance).
    Load it with ``DataConfig(out_dir, background=config.background)`` to get the in-memory scene's images.
    """
    config = config or ProceduralSceneConfig()
    root = Path(out_dir)
    for folder in ("mask", "depth"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    scene = ProceduralScene(config)
    rendered = _render_all(scene, with_flow=True)
    for split, items in rendered.items():
        (root / split).mkdir(exist_ok=True)
        frames = []
        for r in items:
            Image.fromarray(r.view.rgba, "RGBA").save(root / f"{r.name}.png")
            Image.fromarray(r.view.mask.astype(np.uint8) * 255, "L").save(root / "mask" / f"{r.file_name}.png")
            np.save(root / "depth" / f"{r.file_name}.npy", r.view.depth)
            frames.append({"file_path": f"./{r.name}", "time": r.time, "transform_matrix": r.c2w.tolist()})
        meta = {"camera_angle_x": math.radians(config.fov_x_deg), "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))
    points = scene.initial_points()
    assert points.rgb is not None
    write_ply_points(root / "points3d.ply", points.xyz, points.rgb)
    (root / "procedural.json").write_text(json.dumps(asdict(config), indent=2))
    write_procedural_motion_gt(scene, rendered, root)
    return root


def write_procedural_motion_gt(scene: ProceduralScene, rendered: dict[str, list[_Rendered]], root: Path) -> Path:
    """The scene's ground-truth motion in ``root/motion_gt`` (:mod:`pidg.data.motion_gt`): the ring's Gaussian
    centres as vertices, sampled at every frame's time, and one flow per image over one training-frame interval."""
    frames = [r for items in rendered.values() for r in items]
    for r in frames:
        assert r.view.flow is not None  # rendered with_flow
        write_frame_flow(root, r.name, r.view.flow)
    vertices = scene.vertex_motion([r.time for r in frames])
    ring = MotionObject("ring", "analytic", 0, int(vertices.positions.shape[1]))
    extra = {
        "generator": "pidg.data.procedural",
        "vertices": "centres of the ring's ground-truth Gaussians (no faces)",
        "velocity_method": f"central differences of the analytic deformation, step {GT_VELOCITY_STEP:g} (dataset time)",
        "frame_interval_is": "one training-frame interval = two steps of the common time grid",
    }
    return write_motion_gt(root, scene.frame_interval, [ring], vertices, extra=extra)


def contact_sheet(frames: Sequence[Frame], columns: int = 5, show_masks: bool = True) -> Tensor:
    """A grid [H', W', 3] in [0, 1] of frames, each row of images followed by a row of their masks (white =
    dynamic), for a quick look at a scene."""
    if not frames:
        raise ValueError("contact_sheet: no frames")
    h, w, pad = frames[0].height, frames[0].width, 2
    tiles: list[list[Tensor]] = []
    for start in range(0, len(frames), columns):
        chunk = frames[start : start + columns]
        tiles.append([f.image for f in chunk])
        if show_masks:
            masks = [f.mask if f.mask is not None else torch.zeros(h, w, dtype=torch.bool) for f in chunk]
            tiles.append([m.float().unsqueeze(-1).expand(h, w, 3) for m in masks])
    sheet = torch.ones(len(tiles) * (h + pad) + pad, columns * (w + pad) + pad, 3)
    for r, row in enumerate(tiles):
        for c, tile in enumerate(row):
            y, x = pad + r * (h + pad), pad + c * (w + pad)
            sheet[y : y + h, x : x + w] = tile
    return sheet
