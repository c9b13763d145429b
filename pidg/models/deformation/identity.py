"""No deformation: the canonical Gaussians at every time (static scenes, and a baseline)."""
from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from pidg.models.deformation.base import Bounds, DeformationModel, DeformedGaussians


@dataclass
class IdentityDeformationConfig:
    """No settings: there is nothing to configure."""


class IdentityDeformation(DeformationModel):
    """Returns its inputs; has no parameters and no regulariser."""

    def __init__(self, config: IdentityDeformationConfig | None = None, bounds: Bounds | None = None) -> None:
        super().__init__()
        self.config = config or IdentityDeformationConfig()

    def deform(self, means: Tensor, quats: Tensor, log_scales: Tensor, times: Tensor, regularize: bool = False) -> DeformedGaussians:
        return DeformedGaussians(means, quats, log_scales)
