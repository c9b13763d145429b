"""Moving particles with the material field's velocity: the physics-side way to extrapolate a scene in time.

The deformation field answers "where is each Gaussian at time t" for any t, including times it never saw in
training (its extrapolation is whatever the hash grid and the decoder do outside the trained range). The material
field answers a different question, "how fast does the particle at x move at time t". Integrating that velocity
from the last trained positions is a second, physically motivated predictor of the future:

    dx/dt = k * v(x, t),   x(t_start) = deformation(t_start),

with t dataset time, v in world units per physics time unit and k = ``TimeAxis.physics_per_dataset`` (physics time
units per unit of dataset time), so that x stays in world units. Rotations and scales keep their values at
``t_start``: the field predicts positions only.
"""
from __future__ import annotations

import math
from typing import Callable, Literal

import torch
from torch import Tensor

from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians

Integrator = Literal["midpoint", "rk4"]
VelocityFn = Callable[[Tensor, float], Tensor]
"""(positions [N, 3], dataset time t) -> dx/dt [N, 3] in world units per unit of dataset time."""


def integrate(velocity: VelocityFn, x0: Tensor, t0: float, t1: float, substeps: int, method: Integrator = "rk4") -> Tensor:
    """x(t1) for dx/dt = velocity(x, t), x(t0) = x0, with ``substeps`` equal steps of explicit midpoint (2nd
    order) or classical Runge-Kutta (4th order). ``t1 < t0`` integrates backwards."""
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    h = (t1 - t0) / substeps
    x = x0
    for i in range(substeps):
        t = t0 + i * h
        if method == "midpoint":
            k1 = velocity(x, t)
            x = x + h * velocity(x + 0.5 * h * k1, t + 0.5 * h)
        elif method == "rk4":
            k1 = velocity(x, t)
            k2 = velocity(x + 0.5 * h * k1, t + 0.5 * h)
            k3 = velocity(x + 0.5 * h * k2, t + 0.5 * h)
            k4 = velocity(x + h * k3, t + h)
            x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        else:
            raise ValueError(f"method must be 'midpoint' or 'rk4', got {method!r}")
    return x


def model_velocity(model: DynamicGaussians) -> VelocityFn:
    """The scene model's material-field velocity as dx/dt in world units per unit of dataset time (static
    Gaussians, after decoupling, do not move)."""
    scale = model.time_axis.physics_per_dataset  # physics time units per unit of dataset time
    return lambda x, t: model.velocities(t, means=x) * scale


class Advection:
    """Gaussians advected by the material field from their deformed state at ``t_start``.

    ``at(t)`` for t >= t_start continues from the latest time it reached when times come in increasing order (a
    test split sorted by time costs one pass over the interval), with at most ``max_step`` dataset time per
    substep (default: a quarter of a training-frame interval).
    """

    def __init__(
        self, model: DynamicGaussians, t_start: float, method: Integrator = "rk4", max_step: float | None = None
    ) -> None:
        if model.material_field is None:
            raise ValueError("advection needs a material field (train with --physics cmr or --flow lpfm)")
        self.model = model
        self.method: Integrator = method
        self.max_step = max_step if max_step is not None else 0.25 * model.time_axis.frame_interval
        with torch.no_grad():
            self.start = model.at(t_start)
        self.t_start = t_start
        self._t, self._means = t_start, self.start.means

    @torch.no_grad()
    def at(self, t: float) -> DeformedGaussians:
        if t < self.t_start:
            raise ValueError(f"advection runs forward from t={self.t_start}; asked for t={t}")
        if t < self._t:  # an earlier time than the last one: start again
            self._t, self._means = self.t_start, self.start.means
        span = t - self._t
        if span > 0:
            substeps = max(1, math.ceil(span / self.max_step - 1e-9))
            self._means = integrate(model_velocity(self.model), self._means, self._t, t, substeps, self.method)
            self._t = t
        return DeformedGaussians(self._means, self.start.quats, self.start.log_scales)
