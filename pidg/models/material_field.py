"""PIDG's time-evolving material field f_theta: (particle position x, time t, particle index i) -> (v, sigma).

Features (paper Sec. 4.2), concatenated:
  * six learnable planes XY, XZ, YZ, XT, YT, ZT (``plane_channels`` each), looked up bilinearly at the particle's
    normalised (x, y, z, t): x_hat = (x - centre) / half_extent (the ``Bounds`` box maps onto [-1, 1]^3) and
    t in [0, 1] spans the time axis (t_hat = 2t - 1 in [-1, 1]);
  * a Fourier time encoding sin / cos(pi 2^k t_hat), k < ``time_frequencies``;
  * a learnable embedding of the particle index (``embedding_dim``, paper: 64), indexed by the Gaussians'
    ``particle_index`` buffer. Children of a clone or split inherit their parent's index (``GaussianModel``), so
    the table has one row per *initial* particle (``GaussianModel.num_particles``) and never needs resizing.
A shared MLP trunk (``depth`` x ``width``, smooth activation) feeds two linear heads: v in R^3 and the six
independent stress components (xx, yy, zz, xy, xz, yz). The stress head starts at exactly zero (a stress-free
material) and the velocity head at ``velocity_init_scale`` times PyTorch's default init (small but non-zero, so
that the residual has a gradient from the first step: v = sigma = 0 is a stationary point of L_CMR). Stress only
enters L_CMR through its divergence, so a constant stress (the stress bias) gets no gradient from it.

Why concatenation rather than the K-planes / HexPlane product: the paper's feature vector is the concatenation
[F_planes, T(t), e_i]; a product of six features makes each plane's gradient (and each tangent) scale with the
five others, so one small plane silences all of them and the derivative picks up six product-rule terms; with
concatenation every plane's contribution and derivative is independent and the MLP learns the interactions.

Units: the field is evaluated at dataset time t in [0, 1] (the whole sequence), but its velocity is in world
units per *physics* time unit (:class:`pidg.models.time_axis.TimeAxis`; by default one training-frame interval),
so a particle moves by about v * TimeAxis.to_physics(dt) over a dataset-time span dt: v itself per frame.

``jet`` returns the field and its exact first derivatives with respect to (x, y, z, t) by forward-mode tangents
written by hand: four tangent directions are pushed through the network as one [4, M, D] tensor next to the
primal [M, D], so the derivatives cost a few matmuls (torch's grid_sample has no forward-mode derivative, and
``torch.func.jvp`` of ``forward`` measured ~3.5x slower per training step, see ``pidg bench cmr``). The result
is an ordinary autograd graph: L_CMR, which contains these derivatives, is differentiated with respect to the
parameters and the positions by ``backward()`` as usual.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, Range, validate_config
from pidg.errors import NonFiniteError, all_finite
from pidg.models.deformation.base import (
    GROUP_GRID,
    GROUP_MLP,
    Bounds,
    NormalizedPositions,
    times_column,
)
from pidg.models.deformation.hash_grid import HashGridBackend
from pidg.models.jet import FieldJet
from pidg.models.parallel_linear import Linear, linear
from pidg.models.planes import lookup_planes
from pidg.models.tanh_tangents import tanh_with_tangents

GROUP_EMBEDDING = "embedding"  # the index embedding table: its own learning rate

# plane k of the spatial table spans axes (SPATIAL_AXES[0][k], SPATIAL_AXES[1][k]): XY, XZ, YZ
SPATIAL_AXES = ((0, 0, 1), (1, 2, 2))
# plane k of the temporal table spans (axis k, t): XT, YT, ZT; axis 3 is time
TEMPORAL_AXES = ((0, 1, 2), (3, 3, 3))
NUM_DIRECTIONS = 4  # tangent directions d/dx, d/dy, d/dz, d/dt

#: (z [M, W], dz [4, M, W], kernel) -> (phi(z), phi'(z) dz): a trunk layer's activations and their tangents
ActivationWithTangents = Callable[[Tensor, Tensor, bool | None], tuple[Tensor, Tensor]]
Activation = Literal["tanh", "silu", "softplus"]


@dataclass
class MaterialFieldConfig:
    """Sizes of the material field f_theta (paper Sec. 4.2; NOTES.md section 4). It exists when the momentum
    residual (``--physics cmr``) or the flow loss (``--flow lpfm``) needs a velocity; its learning rates are
    ``--optim.material_*``."""

    # Coarse planes: a bilinear lookup's derivative is piecewise constant per cell, so fine planes make the
    # velocity gradient noisy; the index embedding carries per-particle detail instead.
    spatial_resolution: Annotated[int, Range(2)] = 32
    """Cells per spatial axis of the six planes."""
    time_resolution: Annotated[int, Range(2)] = 16
    """Cells along t of the XT, YT, ZT planes."""
    plane_channels: Annotated[int, AT_LEAST_ONE] = 8
    """Feature channels per plane."""
    time_frequencies: Annotated[int, NON_NEGATIVE] = 6
    """n: the Fourier time encoding sin/cos(pi 2^k (2t - 1)), k < n."""
    embedding_dim: Annotated[int, AT_LEAST_ONE] = 64
    """H: size of the particle-index embedding (paper: 64)."""
    width: Annotated[int, AT_LEAST_ONE] = 256
    """MLP width (paper: 256)."""
    depth: Annotated[int, AT_LEAST_ONE] = 2
    """Hidden layers of the shared MLP trunk (paper: 2)."""
    activation: Activation = "tanh"
    """Smooth trunk activation (the residual differentiates through its derivative, so not ReLU)."""
    init_std: Annotated[float, NON_NEGATIVE] = 0.1
    """Standard deviation of the initial plane and embedding values."""
    velocity_init_scale: Annotated[float, NON_NEGATIVE] = 0.01
    """The velocity head starts at PyTorch's default init times this (v = sigma = 0 would be a stationary point)."""
    stress: bool = True
    """False: the paper's "no stress" ablation, sigma == 0."""
    backend: HashGridBackend = "auto"
    """Implementation of the plane lookups (:mod:`pidg.models.planes`) and of the jet's tanh tangents
    (:mod:`pidg.models.tanh_tangents`): the numba kernels on float32 CPU tensors, the torch references otherwise
    (CUDA); cpu or torch force one."""

    def __post_init__(self) -> None:
        validate_config(self)


# ---------------------------------------------------------------------------------------------------------------
# smooth activations with their tangents
# ---------------------------------------------------------------------------------------------------------------
def _by_slope(value_and_slope: Callable[[Tensor], tuple[Tensor, Tensor]]) -> ActivationWithTangents:
    """An activation given as (phi(z), phi'(z)) in torch, as (phi(z), phi'(z) dz) (no kernel: ``kernel`` is ignored)."""

    def with_tangents(z: Tensor, dz: Tensor, kernel: bool | None = None) -> tuple[Tensor, Tensor]:
        a, slope = value_and_slope(z)
        return a, slope * dz

    return with_tangents


def _silu(z: Tensor) -> tuple[Tensor, Tensor]:
    s = torch.sigmoid(z)
    return z * s, s * (1.0 + z * (1.0 - s))


def _softplus(z: Tensor) -> tuple[Tensor, Tensor]:
    return F.softplus(z), torch.sigmoid(z)


#: (phi(z), phi'(z) dz); tanh's is a numba kernel with its torch reference (:mod:`pidg.models.tanh_tangents`).
#: Smooth on purpose: the CMR backward differentiates through the tangents phi'(z) * dz, so it needs phi''. With
#: ReLU phi'' = 0, grad v would be piecewise constant in x (jumping across activation
#: boundaries) and the loss gradient with respect to the positions would lose every curvature term. tanh is the
#: default because it is the cheapest: one transcendental per element and phi' = 1 - phi^2 from the output.
ACTIVATIONS: dict[Activation, ActivationWithTangents] = {
    "tanh": tanh_with_tangents, "silu": _by_slope(_silu), "softplus": _by_slope(_softplus),
}
#: the same functions without the derivative, for ``forward``
ACTIVATION_VALUES: dict[Activation, Callable[[Tensor], Tensor]] = {"tanh": torch.tanh, "silu": F.silu, "softplus": F.softplus}


# ---------------------------------------------------------------------------------------------------------------
# stress and plane-axis helpers (the plane lookup itself: pidg.models.planes)
# ---------------------------------------------------------------------------------------------------------------
def stress_magnitude(sigma: Tensor) -> Tensor:
    """|sigma|_F [N] of symmetric stresses given by their six components [N, 6] (xx, yy, zz, xy, xz, yz): the
    off-diagonal ones count twice."""
    return (sigma[:, :3].square().sum(-1) + 2.0 * sigma[:, 3:].square().sum(-1)).sqrt()


def _axis_scales(axes: tuple[tuple[int, ...], tuple[int, ...]], scale: Tensor) -> tuple[Tensor, Tensor]:
    """[4, K] matrices S_a, S_b with S[d, k] = dp/d(direction d) for plane k's a / b axis (0 if not that axis)."""
    directions = torch.arange(NUM_DIRECTIONS, device=scale.device)[:, None]
    out = []
    for plane_axes in axes:
        axis = torch.tensor(plane_axes, device=scale.device)[None, :]
        out.append(torch.where(directions == axis, scale[axis], torch.zeros((), dtype=scale.dtype, device=scale.device)))
    return out[0], out[1]


# ---------------------------------------------------------------------------------------------------------------
# the field
# ---------------------------------------------------------------------------------------------------------------
class MaterialField(nn.Module):
    """f_theta(x, t, i) -> (v, sigma); see the module docstring."""

    def __init__(self, bounds: Bounds | Tensor | object | None, num_particles: int, config: MaterialFieldConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or MaterialFieldConfig()
        if num_particles < 1:
            raise ValueError(f"MaterialField: need at least one particle, got num_particles={num_particles}")
        self.num_particles = int(num_particles)
        self.normalize = NormalizedPositions(bounds)
        rs, rt, c = cfg.spatial_resolution, cfg.time_resolution, cfg.plane_channels
        self.spatial_planes = nn.Parameter(torch.randn(3, rs, rs, c) * cfg.init_std)  # XY, XZ, YZ
        self.temporal_planes = nn.Parameter(torch.randn(3, rs, rt, c) * cfg.init_std)  # XT, YT, ZT
        self.index_embedding = nn.Parameter(torch.randn(self.num_particles, cfg.embedding_dim) * cfg.init_std)
        self.register_buffer("frequencies", math.pi * 2.0 ** torch.arange(cfg.time_frequencies, dtype=torch.float32))
        # the spatial planes' a and b axes as column indices (index_select: a gather, where a list index is the slower
        # advanced indexing); not saved, derived from SPATIAL_AXES
        self.register_buffer("spatial_axis_a", torch.tensor(SPATIAL_AXES[0]), persistent=False)
        self.register_buffer("spatial_axis_b", torch.tensor(SPATIAL_AXES[1]), persistent=False)
        self.activation, self.activation_value = ACTIVATIONS[cfg.activation], ACTIVATION_VALUES[cfg.activation]
        self.tangent_dim = 6 * c + 2 * cfg.time_frequencies  # feature columns that depend on (x, t)
        dims = [self.tangent_dim + cfg.embedding_dim] + [cfg.width] * cfg.depth
        self.trunk = nn.ModuleList(Linear(d_in, d_out) for d_in, d_out in itertools.pairwise(dims))
        self.head_velocity = Linear(cfg.width, 3)
        self.head_stress = Linear(cfg.width, 6)
        with torch.no_grad():
            self.head_velocity.weight.mul_(cfg.velocity_init_scale)
            self.head_velocity.bias.zero_()
            self.head_stress.weight.zero_()
            self.head_stress.bias.zero_()

    # -- public API ---------------------------------------------------------------------------------------------
    def forward(self, x: Tensor, t: float | Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """v [M, 3] (world units per physics time unit) and sigma [M, 6] at world positions x [M, 3], dataset times t
        (float or [M], in [0, 1]) and particle indices [M]."""
        x, times = self._check_inputs(x, t, index)
        hidden = self._features(x, times, index)
        for layer in self.trunk:
            hidden = self.activation_value(layer(hidden))
        out = linear(hidden, *self._heads())
        sigma = out[:, 3:] if self.config.stress else hidden.new_zeros(hidden.shape[0], 6)
        return out[:, :3], sigma

    def jet(self, x: Tensor, t: float | Tensor, index: Tensor) -> FieldJet:
        """v, sigma and their exact derivatives with respect to world (x, y, z) and t, by hand-written tangents.

        Every tensor is differentiable with respect to the parameters and x by ordinary autograd.
        """
        x, times = self._check_inputs(x, t, index)
        hidden, tangent = self._features_with_tangents(x, times, index)
        for depth, layer in enumerate(self.trunk):
            z = layer(hidden)
            weight = layer.weight[:, : self.tangent_dim] if depth == 0 else layer.weight  # embedding: no tangent
            dz = linear(tangent, weight)  # [4, M, width]
            hidden, tangent = self.activation(z, dz, False if self.config.backend == "torch" else None)
        # both heads in one matmul: slicing the [4, M, width] tangent for the stress head instead costs, in
        # backward, a zero-filled gradient of that size and a sum of two (profiled: ~2 ms fill per step at M = 1024)
        weight, bias = self._heads()
        out = linear(hidden, weight, bias)
        d_out = linear(tangent, weight)  # [4, M, 3 or 9]
        v, dv = out[:, :3], d_out[..., :3]
        if self.config.stress:
            sigma, dsigma = out[:, 3:], d_out[:3, :, 3:]  # d sigma / dt is computed but the residual needs none
        else:
            sigma, dsigma = hidden.new_zeros(hidden.shape[0], 6), hidden.new_zeros(3, hidden.shape[0], 6)
        return FieldJet(
            v=v,
            sigma=sigma,
            dv_dx=dv[:3].permute(1, 2, 0),
            dv_dt=dv[3],
            dsigma_dx=dsigma.permute(1, 2, 0),
        )

    def _heads(self) -> tuple[Tensor, Tensor]:
        """Weight and bias of the output layer: velocity rows, then stress rows unless stress is off."""
        if not self.config.stress:
            return self.head_velocity.weight, self.head_velocity.bias
        return (
            torch.cat([self.head_velocity.weight, self.head_stress.weight]),
            torch.cat([self.head_velocity.bias, self.head_stress.bias]),
        )

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by optimiser group: planes (``GROUP_GRID``), MLP (``GROUP_MLP``), ``GROUP_EMBEDDING``. The
        embedding's gradient is sparse (only the rows of the particles evaluated), so it wants a sparse optimiser."""
        special = {id(self.spatial_planes), id(self.temporal_planes), id(self.index_embedding)}
        groups = {
            GROUP_GRID: [self.spatial_planes, self.temporal_planes],
            GROUP_MLP: [p for p in self.parameters() if id(p) not in special],
            GROUP_EMBEDDING: [self.index_embedding],
        }
        return {name: [p for p in params if p.requires_grad] for name, params in groups.items()}

    # -- inputs and features ------------------------------------------------------------------------------------
    def _check_inputs(self, x: Tensor, t: float | Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """Shape, dtype, range and finiteness checks with messages that name the problem; -> (x, times [M])."""
        if x.dim() != 2 or x.shape[1] != 3:
            raise ValueError(f"MaterialField: x must be [M, 3], got {list(x.shape)}")
        m = x.shape[0]
        if index.shape != (m,):
            raise ValueError(f"MaterialField: index must be [M] = [{m}], got {list(index.shape)}")
        if index.dtype.is_floating_point or index.dtype == torch.bool or index.dtype.is_complex:
            raise ValueError(f"MaterialField: index must be an integer tensor, got {index.dtype}")
        dtype = self.spatial_planes.dtype
        x = x.to(dtype)
        times = times_column(t, m, x)
        if m == 0:
            return x, times
        lo, hi = int(index.min()), int(index.max())
        if lo < 0 or hi >= self.num_particles:
            raise IndexError(
                f"MaterialField: particle index out of range [0, {self.num_particles}): min {lo}, max {hi} "
                "(the table has one row per initial particle, GaussianModel.num_particles)"
            )
        if not all_finite(x.detach()):
            bad = torch.nonzero(~torch.isfinite(x).all(dim=1)).squeeze(1)
            raise NonFiniteError(f"MaterialField: non-finite positions in {bad.numel()} rows, e.g. rows {bad[:5].tolist()}")
        if not all_finite(times.detach()):
            raise NonFiniteError("MaterialField: non-finite times")
        return x, times

    def _plane_coordinates(self, x: Tensor, times: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Continuous cell coordinates: spatial [M, 3], temporal [M], and dp/d(x, y, z, t) [4] (constant)."""
        rs, rt = self.config.spatial_resolution, self.config.time_resolution
        p_space = (self.normalize(x) + 1.0) * (0.5 * (rs - 1))
        p_time = times * (rt - 1)
        half = self.normalize.half_extent.to(x.dtype)
        scale = torch.cat([(0.5 * (rs - 1)) / half, half.new_full((1,), float(rt - 1))])
        return p_space, p_time, scale

    def _plane_lookups(
        self, x: Tensor, times: Tensor, derivatives: bool
    ) -> tuple[tuple[Tensor, Tensor | None, Tensor | None], tuple[Tensor, Tensor | None, Tensor | None], Tensor]:
        """Values, d/dpa and d/dpb of the spatial planes [M, 3, C] (XY, XZ, YZ) and, apart, of the temporal ones
        [M, 3, C] (XT, YT, ZT) (the derivatives None without ``derivatives``), and dp/d(x, y, z, t) [4]. The feature
        columns are the spatial planes', then the temporal ones', each plane's C channels together."""
        p_space, p_time, scale = self._plane_coordinates(x, times)
        backend = self.config.backend
        pa, pb = p_space.index_select(1, self.spatial_axis_a), p_space.index_select(1, self.spatial_axis_b)
        spatial = lookup_planes(self.spatial_planes, pa, pb, derivatives, backend)
        temporal = lookup_planes(self.temporal_planes, p_space, p_time[:, None].expand(-1, 3), derivatives, backend)
        return spatial, temporal, scale

    def _fourier(self, times: Tensor, derivative: bool = True) -> tuple[Tensor, Tensor | None]:
        """sin / cos(omega_k t_hat) [M, 2n] and its t-derivative [M, 2n] (None without ``derivative``; t_hat = 2t - 1)."""
        omega = self.frequencies.to(times.dtype)
        angles = (2.0 * times - 1.0)[:, None] * omega
        sin, cos = torch.sin(angles), torch.cos(angles)
        if not derivative:
            return torch.cat([sin, cos], dim=-1), None
        return torch.cat([sin, cos], dim=-1), torch.cat([2.0 * omega * cos, -2.0 * omega * sin], dim=-1)

    def _embed(self, index: Tensor) -> Tensor:
        """Index embedding rows [M, H]; sparse gradient (see ``make_optimizers``)."""
        return F.embedding(index, self.index_embedding, sparse=True)

    def _features(self, x: Tensor, times: Tensor, index: Tensor) -> Tensor:
        (spatial, _, _), (temporal, _, _), _ = self._plane_lookups(x, times, derivatives=False)
        fourier, _ = self._fourier(times, derivative=False)
        embedding = self._embed(index)
        return torch.cat([spatial.flatten(1), temporal.flatten(1), fourier, embedding], dim=-1)

    def _features_with_tangents(self, x: Tensor, times: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
        """Features [M, D] and their derivatives along x, y, z, t [4, M, tangent_dim] (the embedding's are 0)."""
        spatial, temporal, scale = self._plane_lookups(x, times, derivatives=True)
        m, c = x.shape[0], spatial[0].shape[-1]
        tangents = []
        for (_, d_pa, d_pb), axes in ((spatial, SPATIAL_AXES), (temporal, TEMPORAL_AXES)):
            assert d_pa is not None and d_pb is not None
            scale_a, scale_b = _axis_scales(axes, scale)  # [4, 3]
            # one scale per feature column, so that the products run along rows of 3C contiguous floats: broadcast over
            # [4, M, 3, C] the same products took ~2.5x longer, forward and backward (C = 8)
            cols_a, cols_b = scale_a.repeat_interleave(c, dim=1), scale_b.repeat_interleave(c, dim=1)
            tangents.append(d_pa.flatten(1) * cols_a[:, None, :] + d_pb.flatten(1) * cols_b[:, None, :])  # [4, M, 3C]
        fourier, d_fourier = self._fourier(times)
        assert d_fourier is not None
        tangents.append(torch.cat([d_fourier.new_zeros(3, m, d_fourier.shape[1]), d_fourier[None]], dim=0))
        embedding = self._embed(index)
        features = torch.cat([spatial[0].flatten(1), temporal[0].flatten(1), fourier, embedding], dim=-1)
        return features, torch.cat(tangents, dim=-1)
