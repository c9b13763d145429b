"""The run configuration: one dataclass per concern, composed into ``TrainConfig`` (saved with every run)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pidg.data.scene import DataConfig
from pidg.models.deformation import DeformationConfig
from pidg.models.gaussians import GaussianModelConfig
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
    deformation_lr_decay_every: int = 20_000  # x0.1 per this many steps, applied smoothly (exponential)
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
    optim: OptimConfig = field(default_factory=OptimConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto"
