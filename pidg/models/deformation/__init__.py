"""Deformation models: canonical Gaussians + time -> Gaussians at that time, behind one small interface.

``DeformationConfig`` says which model to build (``kind``) and holds each model's settings; the run config
composes it. ``build_deformation(config, bounds)`` turns it (or a single model's config) into a
``DeformationModel``; ``bounds`` is the box positions are normalised by (see ``as_bounds``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal

from torch import Tensor

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
    bench_hash_grid,
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
    grid4d: Grid4DConfig = field(default_factory=Grid4DConfig)
    mlp: MLPDeformationConfig = field(default_factory=MLPDeformationConfig)

    def __post_init__(self) -> None:
        if self.kind not in _MODELS:
            raise ValueError(f"DeformationConfig: unknown kind {self.kind!r}; expected one of {sorted(_MODELS)}")
        if isinstance(self.grid4d, dict):  # from a saved (JSON) run config
            self.grid4d = _from_dict(Grid4DConfig, self.grid4d)
        if isinstance(self.mlp, dict):
            self.mlp = _from_dict(MLPDeformationConfig, self.mlp)

    @property
    def selected(self) -> Grid4DConfig | MLPDeformationConfig | IdentityDeformationConfig:
        return self.grid4d if self.kind == "grid4d" else self.mlp if self.kind == "mlp" else IdentityDeformationConfig()

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "DeformationConfig":
        """Inverse of ``dataclasses.asdict`` (also after a JSON round trip)."""
        return _from_dict(cls, values)


def _from_dict(config_type: type, values: dict[str, Any]) -> Any:
    known = {f.name for f in fields(config_type)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"{config_type.__name__}: unknown fields {sorted(unknown)}")
    return config_type(**values)


_MODELS: dict[str, tuple[type, type[DeformationModel]]] = {
    "grid4d": (Grid4DConfig, Grid4D),
    "mlp": (MLPDeformationConfig, MLPDeformation),
    "identity": (IdentityDeformationConfig, IdentityDeformation),
}


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
    "HashGridConfig",
    "IdentityDeformation",
    "IdentityDeformationConfig",
    "MLPDeformation",
    "MLPDeformationConfig",
    "as_bounds",
    "bench_hash_grid",
    "build_deformation",
    "hash_encode",
    "hash_encode_reference",
    "quat_multiply",
    "quat_rotate",
    "unit_quat_from_delta",
]
