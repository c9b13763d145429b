"""Settings of the physics term: the material field's sizes and learning rates, and how the CMR loss is sampled.

Flat on purpose: every field is a plain type, so the run configuration's dataclass <-> CLI tool exposes each one
as ``--physics.<field>``. Defaults: the paper where it says something (lambda 0.1, rho 1, index embedding 64,
MLP depth 2 x width 256, MLP lr 2e-3, grids 10-50x the MLP lr); the rest is chosen and explained per field.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

PhysicsKind = Literal["none", "cmr"]
Activation = Literal["tanh", "silu", "softplus"]


def _help(text: str) -> dict[str, str]:
    return {"help": text}


@dataclass
class PhysicsConfig:
    """Cauchy momentum residual (CMR) on a time-evolving material field (NOTES.md sections 4-5)."""

    kind: PhysicsKind = field(default="none", metadata=_help("'cmr' adds lambda_cmr * L_CMR to the training loss"))
    lambda_cmr: float = field(default=0.1, metadata=_help("weight of L_CMR (paper: 0.1)"))
    # The paper names no warm-up. At step 0 the stress is exactly 0 and the velocity is tiny, so the residual and
    # its gradient into the positions are negligible until the field has learnt something: no warm-up needed.
    start: int = field(default=0, metadata=_help("first step at which CMR is applied (then on every step)"))
    # Budget: CMR may add ~30% to a ~250 ms CPU step at 20k Gaussians. At width 256, forward + backward measured
    # 53-58 ms at M = 1024 and 114-143 ms at M = 2048 on 2 shared cores (python -m pidg.physics.bench), so
    # M = 1024, about 5% of 20k Gaussians per step.
    samples: int = field(default=1024, metadata=_help("M: random particles per step that enter the residual"))
    block_size: int = field(default=1024, metadata=_help("particles per block of network evaluation"))
    # Measured at M = 4096 in blocks of 1024: peak 155 -> 60 MiB for +15-30% time. Off by default: at M = 1024
    # (one block) the peak is ~40 MiB and checkpointing a single block saves nothing.
    checkpoint_blocks: bool = field(
        default=False, metadata=_help("recompute each block's activations in backward instead of storing them")
    )
    density: float = field(default=1.0, metadata=_help("rho (paper: 1)"))
    stress: bool = field(default=True, metadata=_help("False: the paper's 'no stress' ablation, sigma == 0"))
    detach_positions: bool = field(
        default=False, metadata=_help("True: CMR gradients do not flow into the deformed positions")
    )
    # The unit of time of v and of the residual. The dataset's t in [0, 1] spans the whole video, so velocities in
    # scene units per unit t are ~N_frames times those per frame and the residual's terms (dv/dt, (v.grad)v) are
    # ~N^2 larger: measured on the demo scene (CMR + LPFM, 400 steps), that residual dominated the flow loss and kept
    # v at 0 (velocity-flow EPE 1.43 px = the target's size); per frame, v follows the flow (EPE 0.48 px).
    # time_scale = physics time units per unit of t; 0 = one unit per training-frame interval.
    time_scale: float = field(
        default=0.0, metadata=_help("physics time units per unit of dataset time (0: one per training-frame interval)")
    )
    # -- material field sizes -------------------------------------------------------------------------------
    # Coarse planes: a bilinear lookup's derivative is piecewise constant per cell, so fine planes make the
    # velocity gradient noisy; the index embedding carries per-particle detail instead.
    spatial_resolution: int = field(default=32, metadata=_help("cells per spatial axis of the six planes"))
    time_resolution: int = field(default=16, metadata=_help("cells along t of the XT, YT, ZT planes"))
    plane_channels: int = field(default=8, metadata=_help("feature channels per plane"))
    time_frequencies: int = field(default=6, metadata=_help("n: Fourier time encoding sin/cos(pi 2^k (2t - 1))"))
    embedding_dim: int = field(default=64, metadata=_help("H: index embedding size (paper: 64)"))
    width: int = field(default=256, metadata=_help("MLP width (paper: 256)"))
    depth: int = field(default=2, metadata=_help("hidden layers of the shared MLP trunk (paper: 2)"))
    activation: Activation = field(default="tanh", metadata=_help("smooth trunk activation (see material_field)"))
    init_std: float = field(default=0.1, metadata=_help("std of the initial plane and embedding values"))
    velocity_init_scale: float = field(default=0.01, metadata=_help("the velocity head's default init times this"))
    # -- learning rates ---------------------------------------------------------------------------------------
    mlp_lr: float = field(default=2e-3, metadata=_help("MLP trunk and heads (paper: 2e-3)"))
    plane_lr_factor: float = field(default=10.0, metadata=_help("planes get mlp_lr times this (paper: 10-50x)"))
    # Each embedding row only gets a gradient when its particle is sampled (about M / N of the steps), so it
    # gets a larger step than the shared weights.
    embedding_lr: float = field(default=1e-2, metadata=_help("index embedding learning rate"))

    def __post_init__(self) -> None:
        if self.kind not in ("none", "cmr"):
            raise ValueError(f"PhysicsConfig: kind must be 'none' or 'cmr', got {self.kind!r}")
        if self.activation not in ("tanh", "silu", "softplus"):
            raise ValueError(f"PhysicsConfig: activation must be tanh, silu or softplus, got {self.activation!r}")
        positive = {
            "samples": self.samples, "block_size": self.block_size, "width": self.width, "depth": self.depth,
            "plane_channels": self.plane_channels, "embedding_dim": self.embedding_dim,
        }  # fmt: skip
        bad = {k: v for k, v in positive.items() if v < 1}
        if bad:
            raise ValueError(f"PhysicsConfig: these must be >= 1: {bad}")
        if self.spatial_resolution < 2 or self.time_resolution < 2:
            raise ValueError(
                f"PhysicsConfig: plane resolutions must be >= 2, got {self.spatial_resolution}, {self.time_resolution}"
            )
        if self.time_scale < 0:
            raise ValueError(f"PhysicsConfig: time_scale must be >= 0 (0 = per training frame), got {self.time_scale}")
        if self.time_frequencies < 0 or self.start < 0:
            raise ValueError("PhysicsConfig: time_frequencies and start must be >= 0")
        if self.density <= 0 or self.lambda_cmr < 0:
            raise ValueError(f"PhysicsConfig: need density > 0 and lambda_cmr >= 0, got {self.density}, {self.lambda_cmr}")

    @property
    def enabled(self) -> bool:
        return self.kind == "cmr"

    def active(self, step: int) -> bool:
        """Whether the trainer adds L_CMR at this step (every step from ``start`` on)."""
        return self.enabled and step >= self.start
