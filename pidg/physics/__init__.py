"""Physics core of PIDG: the Cauchy momentum residual (CMR) on a time-evolving material field.

``PhysicsConfig`` holds every setting (``--physics.*``). The field itself is
``pidg.models.material_field.MaterialField`` (built with ``build_material_field``); ``cmr_loss`` is the
block-sampled L_CMR the trainer adds every step; ``momentum_residual`` works on any ``FieldJet``, and
``jet_from_function`` makes one from an arbitrary differentiable function by forward-mode AD.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from torch import Tensor

from pidg.physics.cmr import (
    STAT_NAMES,
    CMRResult,
    JetField,
    cmr_loss,
    convective_acceleration,
    material_acceleration,
    momentum_residual,
    sample_rows,
    stress_divergence,
)
from pidg.physics.config import PhysicsConfig
from pidg.physics.jet import (
    STRESS_COMPONENTS,
    SYMMETRIC_INDEX,
    FieldJet,
    jet_from_function,
    stress_matrix,
)

if TYPE_CHECKING:
    from pidg.models.material_field import MaterialField


def build_material_field(config: PhysicsConfig, bounds: object, num_particles: int) -> MaterialField:
    """The material field for ``GaussianModel.num_particles`` particles, normalised by ``bounds`` (a ``Bounds``,
    or points [P, 3]; use the same box as the deformation). Imported lazily: pidg.models imports this package."""
    from pidg.models.material_field import MaterialField

    return MaterialField(bounds if not isinstance(bounds, Tensor) else bounds.detach(), num_particles, config)


__all__ = [
    "STAT_NAMES", "STRESS_COMPONENTS", "SYMMETRIC_INDEX", "CMRResult", "FieldJet", "JetField", "PhysicsConfig",
    "build_material_field", "cmr_loss", "convective_acceleration", "jet_from_function", "material_acceleration",
    "momentum_residual", "sample_rows", "stress_divergence", "stress_matrix",
]
