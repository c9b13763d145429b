"""Settings of the physics term: when and how the Cauchy momentum residual enters the loss, and the unit of time.

The material field it constrains has its own section (``--material.*``, ``MaterialFieldConfig``) and learning
rates (``--optim.material_*``). Defaults: the paper where it says something (lambda 0.1, rho 1); the rest is
chosen and explained per field.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, validate_config

PhysicsKind = Literal["none", "cmr"]
KinematicTarget = Literal["central", "forward"]
KinematicTimes = Literal["frame", "recording"]


@dataclass
class PhysicsConfig:
    """Cauchy momentum residual (CMR) on the time-evolving material field (NOTES.md section 5)."""

    kind: PhysicsKind = "none"
    """cmr adds lambda_cmr * L_CMR to the training loss (the paper's "w/o LPFM" row); none leaves it out."""
    lambda_cmr: Annotated[float, NON_NEGATIVE] = 0.1
    """Weight of L_CMR in the total loss (paper: 0.1)."""
    # The paper names no warm-up. At step 0 the stress is exactly 0 and the velocity is tiny, so the residual and
    # its gradient into the positions are negligible until the field has learnt something: no warm-up needed.
    start: Annotated[int, NON_NEGATIVE] = 0
    """First training step at which L_CMR is applied (then on every step)."""
    # Budget: CMR may add ~30% to a ~250 ms CPU step at 20k Gaussians. At width 256, forward + backward measured
    # 53-58 ms at M = 1024 and 114-143 ms at M = 2048 on 2 shared cores (pidg bench cmr), so M = 1024, about 5%
    # of 20k Gaussians per step.
    samples: Annotated[int, AT_LEAST_ONE] = 1024
    """M: random particles per step that enter the residual (time and memory do not grow with the Gaussians)."""
    block_size: Annotated[int, AT_LEAST_ONE] = 1024
    """Particles per block of network evaluation."""
    # Measured at M = 4096 in blocks of 1024: peak 155 -> 60 MiB for +15-30% time. Off by default: at M = 1024
    # (one block) the peak is ~40 MiB and checkpointing a single block saves nothing.
    checkpoint_blocks: bool = False
    """Recompute each block's activations in backward instead of storing them (less memory, more time)."""
    # Off by default: not in the paper. Measured on generated scenes with ground-truth motion (docs/motion.md).
    lambda_kinematic: Annotated[float, NON_NEGATIVE] = 0.0
    """Weight of the particle-velocity consistency L_kin (pidg.physics.consistency): the material field's v at
    ``samples`` random particles against the deformation's own velocity there (detached), in box half-extents per
    training frame. An extension, not in the paper; applied with L_CMR (same start)."""
    kinematic_target: KinematicTarget = "central"
    """What L_kin teaches v: central, the deformation's velocity at t (its difference over half a training-frame
    interval either side: the particles' velocity, which the midpoint velocity flow integrates); forward, its move over
    the next training-frame interval (x(t + dt) - x(t)) / dt, what the paper's first-order (euler) velocity flow
    x + v dt must match where a body turns or accelerates."""
    kinematic_time_jitter: Annotated[float, NON_NEGATIVE] = 0.0
    """Where in time L_kin teaches v: at the step frame's time moved by a uniform offset of up to half this many
    training-frame intervals either way (clamped to [0, 1]; the particles deformed to that time), so v learns the
    particles' velocity between the training times too, which L_kin and L_CMR at the frame's time do not reach (2
    reaches a held-out image between two training frames); 0: at the frame's time. An extension, off by default."""
    kinematic_times: KinematicTimes = "frame"
    """When L_kin teaches v: frame, at the step frame's time (with ``kinematic_time_jitter``, near it), on the
    particles as the step renders them; recording, each sampled particle at a time of its own drawn uniformly over the
    recording [0, 1] (the particles deformed there). At one time a step v learns one slice of the motion at a time:
    on the generated rigid scene it ended 0.33-0.37 of the particles' speed off them after 1000 steps, and a fit of v
    to a trained deformation alone reaches 0.20 in 1000 steps at one time a step, 0.13 at sixteen (docs/motion.md,
    "The material field's v lags the motion"). With a time per particle every step teaches all of it, between the
    training times too, where the midpoint velocity flow reads v. An extension, off by default."""
    density: Annotated[float, POSITIVE] = 1.0
    """rho, in mass per world volume (paper: 1)."""
    detach_positions: bool = False
    """True: L_CMR's gradient does not flow into the deformed positions (only into the material field)."""
    # In units of the dataset's t (the whole video), velocities are ~N_frames times those per frame and the
    # residual's terms ~N^2 larger: measured on the demo scene (CMR + LPFM, 400 steps), that residual dominated the
    # flow loss and kept v at 0 (velocity-flow EPE 1.43 px = the target's size); per frame, v follows the flow
    # (EPE 0.48 px). See pidg.models.time_axis.
    time_scale: Annotated[float, NON_NEGATIVE] = 0.0
    """Physics time units per unit of dataset time t in [0, 1]; 0 = one unit per training-frame interval. Sets the
    unit of the material field's velocity (world units per physics time unit) and of the residual."""

    def __post_init__(self) -> None:
        validate_config(self)
        if self.kinematic_time_jitter > 0 and self.kinematic_times != "frame":
            raise ValueError(f"--physics.kinematic_time_jitter {self.kinematic_time_jitter} moves the step frame's time: it "
                             f"needs --physics.kinematic_times frame, not {self.kinematic_times}")

    @property
    def enabled(self) -> bool:
        return self.kind == "cmr"

    def active(self, step: int) -> bool:
        """Whether the trainer adds L_CMR at this step (every step from ``start`` on)."""
        return self.enabled and step >= self.start
