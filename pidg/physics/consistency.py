"""Particle-velocity consistency: the material field's v at each particle against the particle's own motion.

PIDG treats every Gaussian as a Lagrangian particle, but only the flow loss ties the field's velocity to the
deformation, and only on the pixels it supervises. This optional term (``--physics.lambda_kinematic``, an extension,
not in the paper) compares them directly in 3D on sampled particles:

    L_kin = mean_i | v(x_i(t), t) - (x_i(t + h) - x_i(t - h)) / (2h) | * dt_frame / L

with v in world units per physics time unit, h half a training-frame interval, the difference quotient
(``DynamicGaussians.motion_velocity``, the one the motion metrics score) converted to physics time, dt_frame one
training-frame interval in physics time, and L the material
field's box half-extent per axis: the error in box half-extents per training frame, unitless and the same for any
``--physics.time_scale``. The deformation's velocity is a target (detached): the term teaches v, not the motion.
``--physics.kinematic_target forward`` replaces the central difference by the move over the next training-frame
interval, (x_i(t + dt) - x_i(t)) / dt, the velocity the paper's first-order velocity flow x + v dt needs where a body
turns or accelerates.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.time_axis import TimeAxis


def particle_velocity(model: DynamicGaussians, t: float | Tensor, rows: Tensor | None = None) -> Tensor:
    """The deformation's velocity [N, 3] of the particles ``rows`` (all: None) at dataset time ``t`` (a float, or
    [N]: a time per particle), over half a training-frame interval either side, in world units per physics time unit
    (tau = t * S: dx/dtau = dx/dt / S)."""
    time_axis = model.time_axis
    return model.motion_velocity(t, 0.5 * time_axis.frame_interval, rows) / time_axis.physics_per_dataset


def particle_step_velocity(model: DynamicGaussians, t: float | Tensor, means: Tensor, rows: Tensor | None = None) -> Tensor:
    """The deformation's move [N, 3] of the particles ``rows`` (all: None), at ``means`` at dataset time ``t`` (a
    float, or [N]: a time per particle), over the next training-frame interval, as a velocity in world units per
    physics time unit: (x(t + dt) - x(t)) / dt.
    Where that interval leaves the recording (t + dt > 1: the last training frame) the interval is the one that ends
    at t = 1, as :meth:`DynamicGaussians.motion_velocity` stays in [0, 1]: past the end no image supervises the
    deformation, and its move there taught v at the last frame about half the true speed on the generated kinematic
    scene (docs/motion.md, "Holding the tracks")."""
    time_axis = model.time_axis
    dt = time_axis.frame_interval
    if isinstance(t, Tensor):
        end = (t + dt).clamp_max(1.0)
        inside = (end == t + dt).reshape(-1, 1)
        start = means if bool(inside.all()) else torch.where(inside, means, model.at(end - dt, rows=rows).means)
    else:
        end = min(t + dt, 1.0)
        start = means if end == t + dt else model.at(end - dt, rows=rows).means
    return (model.at(end, rows=rows).means - start) / time_axis.to_physics(dt)


def velocity_mismatch(v: Tensor, target: Tensor, time_axis: TimeAxis, half_extent: Tensor) -> Tensor:
    """mean_i |(v_i - target_i) * dt_frame / half_extent| (Euclidean norm per row): velocities [N, 3] in world
    units per physics time unit, ``half_extent`` [3] or scalar in world units; the result in box half-extents per
    training-frame interval."""
    if v.shape != target.shape or v.dim() != 2 or v.shape[1] != 3:
        raise ValueError(f"velocity_mismatch: v and target must both be [N, 3], got {list(v.shape)} and {list(target.shape)}")
    if v.shape[0] == 0:
        return v.new_zeros(())
    step = (v - target) * time_axis.frame_dt / half_extent.to(v)
    return step.norm(dim=-1).mean()
