"""The two clocks of a dynamic scene: dataset time and physics time.

Dataset time t in [0, 1] spans the whole video; the deformation, the material field and the flow pairs are
indexed by it. Physics time tau is the unit of velocities and of the momentum residual: tau = t * scale. In units of
t, a velocity is ~N_frames times its per-frame size and the residual's terms (dv/dt, (v.grad)v) ~N^2 larger, which
measured on the demo scene let the residual hold v at 0 against the flow loss; the default therefore counts
physics time in training-frame intervals (``PhysicsConfig.time_scale = 0``). Every caller that converts between
the two (the residual, the velocity flow, the renders of velocity) asks this one object.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass

import torch


@dataclass(frozen=True)
class TimeAxis:
    """Physics time units per unit of dataset time, and the dataset time of one training-frame interval."""

    physics_per_dataset: float
    """tau / t: physics time units per unit of dataset time."""
    frame_interval: float
    """Median gap between consecutive distinct training times, in dataset time (1 with fewer than two times)."""

    def __post_init__(self) -> None:
        if not (self.physics_per_dataset > 0 and self.frame_interval > 0):
            raise ValueError(f"TimeAxis: both scales must be > 0, got {self.physics_per_dataset}, {self.frame_interval}")

    @classmethod
    def from_times(cls, times: Iterable[float], time_scale: float = 0.0) -> "TimeAxis":
        """From the training frames' times: ``time_scale`` physics units per unit of t, or (0) one per interval."""
        if time_scale < 0:
            raise ValueError(f"TimeAxis: time_scale must be >= 0 (0 = one unit per training-frame interval), got {time_scale}")
        distinct = torch.tensor(sorted(set(times)), dtype=torch.float64)
        gaps = distinct.diff()
        gaps = gaps[gaps > 0]
        interval = float(gaps.median()) if len(gaps) else 1.0
        return cls(float(time_scale) if time_scale > 0 else 1.0 / interval, interval)

    def to_physics(self, dt: float) -> float:
        """A dataset-time span in physics time units."""
        return dt * self.physics_per_dataset

    @property
    def frame_dt(self) -> float:
        """One training-frame interval in physics time units (1 with the default scale)."""
        return self.to_physics(self.frame_interval)

    def state_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def from_state_dict(cls, state: dict[str, float]) -> "TimeAxis":
        return cls(float(state["physics_per_dataset"]), float(state["frame_interval"]))
