"""Deformable-3DGS-style MLP deformation baseline: positional encodings of (x, y, z) and t -> deep MLP.

Yang et al. (Deformable 3D Gaussians) feed NeRF positional encodings of the raw position (10 frequencies) and
time (6 frequencies) to an 8 x 256 ReLU MLP with a skip connection re-injecting the input after layer 4, and
three heads (translation, rotation, scale). Differences here, for a shared interface with Grid4D:
  * positions are normalised by the ``Bounds`` box to [-1, 1] before encoding (the original encodes raw world
    coordinates, which ties the frequencies to the scene's units); translations are in half-extent units;
  * rotation and scale changes follow ``base``'s conventions (unit-quaternion increment, log-space scale change);
  * the heads start at zero, so the initial deformation is the identity;
  * Deformable-3DGS's annealed time noise for real scenes is a training-loop matter and is not included.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, validate_config

from pidg.models.deformation.base import (
    Bounds,
    DeformationModel,
    DeformedGaussians,
    NormalizedPositions,
    quat_multiply,
    unit_quat_from_delta,
)
from pidg.models.parallel_linear import Linear


@dataclass
class MLPDeformationConfig:
    """Defaults: Deformable-3DGS (8 x 256, skip after layer 4). A CPU configuration may use e.g. 4 x 64."""

    depth: Annotated[int, AT_LEAST_ONE] = 8
    """Hidden layers of the MLP."""
    width: Annotated[int, AT_LEAST_ONE] = 256
    """Width of every hidden layer."""
    skips: Annotated[tuple[int, ...], NON_NEGATIVE] = (4,)
    """Re-inject the encoded input after these layers (0-based)."""
    position_frequencies: Annotated[int, NON_NEGATIVE] = 10
    """NeRF positional-encoding frequencies of the normalised position."""
    time_frequencies: Annotated[int, NON_NEGATIVE] = 6
    """NeRF positional-encoding frequencies of the time t in [0, 1]."""
    detach_positions: bool = True
    """Encode detached positions, as Deformable-3DGS does (canonical means still get gradients through mu')."""

    def __post_init__(self) -> None:
        validate_config(self)
        if any(not 0 <= s < self.depth - 1 for s in self.skips):
            raise ValueError(f"MLPDeformationConfig: skips must be layer indices in [0, depth - 1), got {self.skips}")


def positional_encoding(x: Tensor, n_frequencies: int) -> Tensor:
    """NeRF encoding [x, sin(2^k x), cos(2^k x) for k < n] of x [N, D] -> [N, D * (1 + 2 n)]."""
    if n_frequencies == 0:
        return x
    freqs = 2.0 ** torch.arange(n_frequencies, dtype=x.dtype, device=x.device)
    angles = (x[:, None, :] * freqs[:, None]).reshape(x.shape[0], n_frequencies * x.shape[1])  # frequency-major
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class MLPDeformation(DeformationModel):
    """Deformable-3DGS deformation MLP behind the shared interface."""

    def __init__(self, config: MLPDeformationConfig | None = None, bounds: Bounds | None = None) -> None:
        super().__init__()
        self.config = cfg = config or MLPDeformationConfig()
        self.normalize = NormalizedPositions(bounds)
        in_dim = 3 * (1 + 2 * cfg.position_frequencies) + (1 + 2 * cfg.time_frequencies)
        layers = [Linear(in_dim, cfg.width)]
        for i in range(cfg.depth - 1):  # layer i + 1 also sees the input when layer i is a skip
            layers.append(Linear(cfg.width + (in_dim if i in cfg.skips else 0), cfg.width))
        self.layers = nn.ModuleList(layers)
        self.head_translation = Linear(cfg.width, 3)
        self.head_rotation = Linear(cfg.width, 4)
        self.head_scale = Linear(cfg.width, 3)
        for head in (self.head_translation, self.head_rotation, self.head_scale):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def encode(self, means: Tensor, times: Tensor) -> Tensor:
        x = positional_encoding(self.normalize(means), self.config.position_frequencies)
        t = positional_encoding(times[:, None], self.config.time_frequencies)
        return torch.cat([x, t], dim=-1)

    def deform(self, means: Tensor, quats: Tensor, log_scales: Tensor, times: Tensor, regularize: bool = False) -> DeformedGaussians:
        """Deform every row (the baseline has no regulariser: ``regularize`` changes nothing)."""
        dtype = self.head_scale.weight.dtype
        positions = means.detach() if self.config.detach_positions else means
        inputs = self.encode(positions.to(dtype), times.to(dtype))
        h = inputs
        for i, layer in enumerate(self.layers):
            h = torch.relu(layer(h))
            if i in self.config.skips:
                h = torch.cat([inputs, h], dim=-1)
        translation = self.head_translation(h) * self.normalize.half_extent.to(dtype)
        new_quats = quat_multiply(unit_quat_from_delta(self.head_rotation(h)), quats.to(dtype))
        return DeformedGaussians(
            (means.to(dtype) + translation).to(means.dtype),
            new_quats.to(quats.dtype),
            (log_scales.to(dtype) + self.head_scale(h)).to(log_scales.dtype),
        )
