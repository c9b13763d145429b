"""Settings of Lagrangian particle flow matching (LPFM): optical-flow preprocessing, motion decomposition, loss.

Plain field types only, so the project's dataclass <-> command-line tool exposes every field as ``--flow.NAME``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

FlowKind = Literal["none", "lpfm"]
EstimatorName = Literal["dis", "deepflow", "tvl1", "raft"]
DisPreset = Literal["ultrafast", "fast", "medium"]


@dataclass
class FlowConfig:
    """Optical-flow supervision (paper Sec. 4.3 and supp. B; NOTES.md sections 6-8).

    Loss: ``lambda_lpfm * (lambda_gaussian * L1(flow_g, flow_gt) + lambda_velocity * L1(flow_v, flow_gt))``,
    applied on every step from ``start`` on (the reference code's 1%-of-steps schedule is a defect).
    """

    kind: FlowKind = "none"
    lambda_lpfm: float = 0.01  # weight of L_LPFM in the total loss (paper)
    lambda_gaussian: float = 0.5  # lambda_g (paper)
    lambda_velocity: float = 0.5  # lambda_v (paper)
    start: int = 0  # first training step that uses LPFM

    # optical flow estimation (preprocessing)
    estimator: EstimatorName = "dis"  # OpenCV DIS (fast), DeepFlow, Dual TV-L1, or RAFT with local weights
    dis_preset: DisPreset = "medium"
    raft_weights: Path | None = None  # local RAFT (.pt2 export, TorchScript, or torchvision state dict)
    # forward-backward check |f(p) + b(p + f(p))|^2 < alpha (|f(p)|^2 + |b(p + f(p))|^2) + beta (pixels^2)
    consistency_alpha: float = 0.01
    consistency_beta: float = 0.5
    cache_dir: str = "flow_cache"  # relative to the dataset folder, or an absolute path

    # ground-truth motion flow
    mask_dilation: int = 3  # pixels the motion mask of frame t is dilated by (square structuring element)
    motion_threshold: float = 1.0  # pixels of camera-compensated flow above which a pixel counts as moving
    min_alpha: float = 0.05  # rendered alpha below which a pixel's rendered flow is not supervised
    # flow_gt needs frame t+1's depth, rendered by the model (a no-grad render + the decomposition, ~100-250 ms per
    # step on a CPU at 400x400). A pair's target is rebuilt when it is older than this many steps (1 = every step);
    # the depth of a converging model changes slowly, and each pair is visited once per epoch anyway.
    target_refresh_steps: int = 300

    def __post_init__(self) -> None:
        if isinstance(self.raft_weights, str):
            self.raft_weights = Path(self.raft_weights) if self.raft_weights else None
        if self.kind not in ("none", "lpfm"):
            raise ValueError(f"FlowConfig.kind must be 'none' or 'lpfm', got {self.kind!r}")
        if self.estimator not in ("dis", "deepflow", "tvl1", "raft"):
            raise ValueError(f"FlowConfig.estimator must be dis, deepflow, tvl1 or raft, got {self.estimator!r}")
        if self.dis_preset not in ("ultrafast", "fast", "medium"):
            raise ValueError(f"FlowConfig.dis_preset must be ultrafast, fast or medium, got {self.dis_preset!r}")
        for name in ("lambda_lpfm", "lambda_gaussian", "lambda_velocity", "consistency_alpha", "consistency_beta",
                     "motion_threshold", "min_alpha"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"FlowConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.target_refresh_steps < 1:
            raise ValueError(f"FlowConfig.target_refresh_steps must be >= 1, got {self.target_refresh_steps}")
        if self.start < 0 or self.mask_dilation < 0:
            raise ValueError(f"FlowConfig: start and mask_dilation must be >= 0, got {self.start}, {self.mask_dilation}")
        if not self.cache_dir:
            raise ValueError("FlowConfig.cache_dir must not be empty")

    @property
    def enabled(self) -> bool:
        return self.kind == "lpfm"

    def active(self, step: int) -> bool:
        """Whether LPFM applies at training step ``step``."""
        return self.enabled and step >= self.start
