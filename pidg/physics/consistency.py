"""Particle-velocity consistency: the material field's v at each particle against the particle's own motion.

PIDG treats every Gaussian as a Lagrangian particle, but only the flow loss ties the field's velocity to the
deformation, and only on the pixels it supervises. This optional term (``--physics.lambda_kinematic``, an extension,
not in the paper) compares them directly in 3D on sampled particles:

    L_kin = mean_i | v(x_i(t), t) - (x_i(t + h) - x_i(t - h)) / (2h) | * dt_frame / L

with v in world units per physics time unit, h half a training-frame interval, the difference quotient converted
to physics time (``TimeAxis.to_physics``), dt_frame one training-frame interval in physics time, and L the material
field's box half-extent per axis: the error in box half-extents per training frame, unitless and the same for any
``--physics.time_scale``. The deformation's velocity is a target (detached): the term teaches v, not the motion.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.models.time_axis import TimeAxis


def particle_velocity(before: Tensor, after: Tensor, t0: float, t1: float, time_axis: TimeAxis) -> Tensor:
    """The difference quotient (after - before) / (t1 - t0) of positions [N, 3] at dataset times t0 < t1, in world
    units per physics time unit."""
    if not t1 > t0:
        raise ValueError(f"particle_velocity: need t1 > t0, got t0={t0}, t1={t1}")
    return (after - before) / time_axis.to_physics(t1 - t0)


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
