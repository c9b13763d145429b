"""Deformation models: canonical Gaussians + time -> Gaussians at that time, behind one small interface.

``DeformationConfig`` says which model to build (``kind``) and holds each model's settings; the run config
composes it. ``build_deformation(config, bounds)`` turns it (or a single model's config) into a
``DeformationModel``; ``bounds`` is the box positions are normalised by (see ``as_bounds``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

from torch import Tensor

from pidg.config_tools import validate_config
from pidg.models.deformation.base import (
    GROUP_GRID,
    GROUP_MLP,
    Bounds,
    DeformationModel,
    DeformedGaussians,
    as_bounds,
    quat_multiply,
    quat_rotate,
    unit_quat_from_delta,
)
from pidg.models.deformation.grid4d import Grid4D, Grid4DConfig
from pidg.models.deformation.hash_grid import (
    GRID4D_SPATIAL,
    GRID4D_TEMPORAL,
    HashGrid,
    HashGridConfig,
    HashGridBackend,
    hash_encode,
    hash_encode_reference,
)
from pidg.models.deformation.identity import IdentityDeformation, IdentityDeformationConfig
from pidg.models.deformation.mlp import MLPDeformation, MLPDeformationConfig

DeformationKind = Literal["grid4d", "mlp", "identity"]


@dataclass
class DeformationConfig:
    """Which deformation model to use (``kind``) and the settings of each; only the chosen one is read."""

    kind: DeformationKind = "grid4d"
    """The deformation field: grid4d (the paper's), mlp (Deformable-3DGS baseline) or identity (a static scene)."""
    grid4d: Grid4DConfig = field(default_factory=Grid4DConfig)
    """Settings of the Grid4D field (read when kind is grid4d)."""
    mlp: MLPDeformationConfig = field(default_factory=MLPDeformationConfig)
    """Settings of the MLP baseline (read when kind is mlp)."""

    def __post_init__(self) -> None:
        validate_config(self)

    @property
    def selected(self) -> Grid4DConfig | MLPDeformationConfig | IdentityDeformationConfig:
        return self.grid4d if self.kind == "grid4d" else self.mlp if self.kind == "mlp" else IdentityDeformationConfig()

    @classmethod
    def of(cls, model: DeformationModel) -> "DeformationConfig":
        """The config that builds a model like ``model`` (its kind and its settings; the others at default)."""
        for kind, (_, model_type) in _MODELS.items():
            if type(model) is model_type:
                return cls(kind=kind, **({kind: model.config} if kind in ("grid4d", "mlp") else {}))  # type: ignore[arg-type]
        raise TypeError(f"DeformationConfig.of: unknown deformation model {type(model).__name__}")


_MODELS: dict[str, tuple[type, type[DeformationModel]]] = {
    "grid4d": (Grid4DConfig, Grid4D),
    "mlp": (MLPDeformationConfig, MLPDeformation),
    "identity": (IdentityDeformationConfig, IdentityDeformation),
}
assert set(_MODELS) == set(get_args(DeformationKind)), "every DeformationKind needs a model, and no model is unnamed"


def build_deformation(
    config: DeformationConfig | Grid4DConfig | MLPDeformationConfig | IdentityDeformationConfig,
    bounds: Bounds | Tensor | object | None = None,
) -> DeformationModel:
    """The deformation model a config describes, normalising positions by ``bounds`` (see ``as_bounds``)."""
    chosen = config.selected if isinstance(config, DeformationConfig) else config
    for config_type, model_type in _MODELS.values():
        if type(chosen) is config_type:
            return model_type(chosen, as_bounds(bounds))
    raise TypeError(f"build_deformation: unknown config type {type(config).__name__}")


__all__ = [
    "GROUP_GRID",
    "GROUP_MLP",
    "GRID4D_SPATIAL",
    "GRID4D_TEMPORAL",
    "Bounds",
    "DeformationConfig",
    "DeformationKind",
    "DeformationModel",
    "DeformedGaussians",
    "Grid4D",
    "Grid4DConfig",
    "HashGrid",
    "HashGridBackend",
    "HashGridConfig",
    "IdentityDeformation",
    "IdentityDeformationConfig",
    "MLPDeformation",
    "MLPDeformationConfig",
    "as_bounds",
    "build_deformation",
    "hash_encode",
    "hash_encode_reference",
    "quat_multiply",
    "quat_rotate",
    "unit_quat_from_delta",
]
