"""The capture of a generated scene: which image is taken when, by which camera, into which split (no bpy).

Time grid. ``n`` images sit on one grid t_i = i / (n - 1), one image per simulation frame, so consecutive images are
one ``frame_interval`` = 1 / (n - 1) of dataset time apart (and 1 / fps seconds). Every ``HOLDOUT_EVERY``-th image
(i = 2, 6, 10, ...) is held out, alternately for test and val; the first and the last image always train, so the
training frames span the whole recording and their median spacing is one frame interval (as ``TimeAxis`` reads it).

Cameras, like a D-NeRF capture: one moving camera, one view per time. Training views orbit the scene once over the
sequence (azimuth linear in t, elevation waving gently); held-out views sit off the orbit (test +30 degrees of
azimuth, val -30, elevation 6 degrees higher and waving in opposite phase), so they are novel views as well as novel times. ``static`` keeps
every training view at the start of the orbit (a tripod); held-out views keep their offsets from it.
``held_out_on_orbit`` puts the held-out views where the training camera is at their time instead (novel times only, as
a video's own frames are), so that a run's held-out error can be split into what the time and what the view cost.
Matrices are OpenGL/Blender camera-to-world (x right, y up, looking down -z), world z up, world units.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pidg.render.camera import Camera, orbit_camera_to_world

HOLDOUT_EVERY = 4
"""Image i is held out when i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2 (alternately test and val)."""
HELD_OUT_AZIMUTH_DEG = {"test": 30.0, "val": -30.0}


@dataclass(frozen=True)
class Shot:
    """One image of the sequence."""

    index: int  # position on the common time grid (also the file number: r_0007)
    time: float  # dataset time in [0, 1]
    split: str  # "train", "val" or "test"

    @property
    def file_name(self) -> str:
        return f"r_{self.index:04d}"

    @property
    def key(self) -> str:
        """The frame's ``file_path`` without extension, as ``Frame.name`` and the motion ground truth name it."""
        return f"{self.split}/{self.file_name}"


def shot_list(n_images: int) -> list[Shot]:
    """Every image in time order with its split (see the module docstring); needs at least 4 images."""
    if n_images < 4:
        raise ValueError(f"need at least 4 images (2 to train, 1 to test), got {n_images}")
    half = HOLDOUT_EVERY // 2
    held = [i for i in range(1, n_images - 1) if i % HOLDOUT_EVERY == half]
    split_of = {i: ("test" if k % 2 == 0 else "val") for k, i in enumerate(held)}
    return [Shot(i, i / (n_images - 1), split_of.get(i, "train")) for i in range(n_images)]


@dataclass(frozen=True)
class Orbit:
    """Where the camera looks from: a circle around ``target`` (world units, degrees)."""

    target: tuple[float, float, float]
    radius: float
    elevation_deg: float = 24.0
    elevation_wave_deg: float = 6.0  # training elevation = elevation_deg + wave * sin(4 pi t)
    azimuth0_deg: float = 0.0
    turns: float = 1.0
    static: bool = False
    held_out_on_orbit: bool = False  # held-out views where the training camera is at their time (module docstring)

    def camera_to_world(self, shot: Shot) -> np.ndarray:
        """OpenGL camera-to-world [4, 4] float64 of ``shot``."""
        progress = 0.0 if self.static else shot.time
        wave = 0.0 if self.static else math.sin(4.0 * math.pi * shot.time)
        off_orbit = shot.split != "train" and not self.held_out_on_orbit
        azimuth = self.azimuth0_deg + 360.0 * self.turns * progress + (HELD_OUT_AZIMUTH_DEG[shot.split] if off_orbit else 0.0)
        sign = -1.0 if off_orbit else 1.0
        elevation = self.elevation_deg + sign * self.elevation_wave_deg * wave + (6.0 if off_orbit else 0.0)
        return look_at_gl(self.target, self.radius, math.radians(azimuth), math.radians(elevation))


def look_at_gl(target: tuple[float, float, float], radius: float, azimuth: float, elevation: float) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenGL: columns right, up, backward, eye) on a sphere around ``target``, upright
    (world z up), looking at ``target``; angles in radians (``pidg.render.camera.orbit_camera_to_world``)."""
    return orbit_camera_to_world(target, radius, azimuth, elevation).numpy()


def pidg_camera(c2w: np.ndarray, width: int, height: int, fov_x: float) -> Camera:
    """The camera exactly as the dataset reader builds it from ``transform_matrix`` and ``camera_angle_x``
    (radians): every ray, projection and flow of the ground truth goes through it."""
    return Camera.from_fov(torch.as_tensor(c2w, dtype=torch.float64), width, height, fov_x)
