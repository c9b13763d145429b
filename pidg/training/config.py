"""The run configuration: one dataclass per concern, composed into ``TrainConfig`` (saved with every run)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from pidg.data.scene import DataConfig
from pidg.flow.config import FlowConfig
from pidg.models.deformation import DeformationConfig
from pidg.models.gaussians import GaussianModelConfig
from pidg.physics.config import PhysicsConfig
from pidg.training.densification import DensificationConfig
from pidg.training.optim import GaussianOptimConfig


@dataclass
class OptimConfig:
    """Run length, loss weights and the deformation network's learning rates (Gaussians: GaussianOptimConfig)."""

    iterations: int = 20_000
    seed: int = 42
    lambda_dssim: float = 0.2
    deformation_lr: float = 2e-3  # MLPs; hash grids get `grid_lr_factor` times this
    grid_lr_factor: float = 10.0  # NOTES.md: hash grids 10-50x the MLP learning rate
    deformation_lr_decay_every: int = 0  # x0.1 per this many steps, applied smoothly (exponential); 0: the run's iterations
    static_warmup: int = 0  # steps that train the canonical Gaussians only, before deformation starts
    time_budget_minutes: float | None = None  # stop early (with a checkpoint) when training time runs out
    dynamic_vote: float = 0.4  # decoupling: dynamic if inside the motion mask in > this share of visible views


@dataclass
class OutputConfig:
    dir: Path = Path("outputs/run")
    checkpoint_every: int = 1000
    log_every: int = 25  # TensorBoard scalars
    preview_every: int = 1000  # TensorBoard image previews (a training view)
    progress: bool = True  # tqdm bar


@dataclass
class TrainConfig:
    data: DataConfig = field(default_factory=lambda: DataConfig(path=""))
    gaussians: GaussianModelConfig = field(default_factory=GaussianModelConfig)
    gaussian_optim: GaussianOptimConfig = field(default_factory=GaussianOptimConfig)
    densify: DensificationConfig = field(default_factory=DensificationConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto"


Preset = Literal["auto", "paper", "cpu"]


def apply_preset(config: TrainConfig, preset: Preset = "auto") -> TrainConfig:
    """Model sizes for the hardware: "paper" keeps the paper's Grid4D (2^19 / 2^17-entry hash tables, width 256);
    "cpu" shrinks what a CPU step pays for without measurable quality loss on D-NeRF at 400x400: hash tables of
    2^16 / 2^15 entries (Adam touches every entry every step), spatial resolution up to 1024, 64-wide layers, and
    16 instead of 32 levels on the temporal grids. Their resolutions only grow from 8 to 32 (16 along t), so 32
    levels sit 4.6% apart; 16 levels (9% apart) cover the same range at half the lookups, and the temporal grids
    were the largest item of a CPU step (63 of ~260 ms at 23k Gaussians, 400x400).
    "auto" picks "paper" when CUDA is available and "cpu" otherwise. Explicit overrides are applied after this.
    """
    import torch

    from pidg.models.deformation import HashGridConfig

    if preset == "auto":
        preset = "paper" if torch.cuda.is_available() else "cpu"
    if preset == "paper":
        return config
    if preset != "cpu":
        raise ValueError(f"unknown preset {preset!r}: expected auto, paper or cpu")
    grid4d = replace(
        config.deformation.grid4d,
        spatial_grid=HashGridConfig(16, 2, 16, 16, 1024),
        temporal_grid=HashGridConfig(16, 2, 15, (8, 8, 8), (32, 32, 16)),
        width=64,
    )
    return replace(config, deformation=replace(config.deformation, grid4d=grid4d))
