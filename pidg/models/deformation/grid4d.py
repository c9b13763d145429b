"""Grid4D deformation field: 4D decomposed hash encoding + directional attention + multi-head decoder.

    a = 2 sigmoid(f_s(G_xyz(x, y, z))) - 1                      (time independent: cached at render time)
    h = a * f_t([G_xyt(x, y, t), G_yzt(y, z, t), G_xzt(x, z, t)])
    D(h) -> rigid warp (quaternion q_x, translation T_x), rotation increment dr, scale change ds

Coordinates the grids see (all hash grids take the unit box [0, 1]^3):
  * space: ``u = 0.5 + 0.5 * (x - centre) / half_extent``, so the ``Bounds`` box maps onto the unit box;
  * time: ``u_t = 0.5 + 0.5 * time_margin * (2 t - 1)``. This is Grid4D's ``t' = time_margin * (2 b t - b)`` in
    [-0.9 b, 0.9 b] for t in [0, 1], seen through its encoder's ``(t' + b) / (2 b)``: with the default 0.9,
    t in [0, 1] lands in [0.05, 0.95]. Training times then never sit on the grids' boundary, and times slightly
    outside the training range (t in [-0.055, 1.055]) still fall inside the grids instead of being clamped.

The deformed Gaussian (see ``base`` for the quaternion and log-scale conventions):
    mean     mu' = centre + R(q_x) (mu - centre) + half_extent * T_x
    rotation q'  = q_x * dq * q   with dq = normalize(1 + dr)  (q_x is left out if ``rotate_with_warp`` is False)
where q_x = normalize(1 + w) for the warp head's quaternion output w (1 = the identity quaternion (1, 0, 0, 0)).
    scale    log s' = log s + ds
The paper writes mu' = R_x mu + T_x; rotating about the box centre instead of the world origin is the same set
of rigid motions, but a small rotation no longer moves far-from-origin scenes by a large distance that T_x must
cancel. The warp rotates the Gaussian's orientation too (a rigidly moving neighbourhood rotates its covariance);
Grid4D's code only adds dr. All decoder output layers start at zero, so the initial deformation is exactly the
identity; consequently the first backward pass only reaches the output layers, and everything else starts
receiving gradients once they have moved away from zero (one optimiser step). The warp itself is ``warp.py``'s (a
numba kernel on the CPU, its torch reference elsewhere).

Regulariser (Grid4D): on a random ``reg_fraction`` of the points of a forward pass called with ``regularize=True``,
perturb the grid coordinates by uniform noise and penalise the squared change of the spatial and temporal grid
features; the pass returns the term in ``DeformedGaussians.regularization``.
Each grid computes its features and its share of the term in one call (``HashGrid.with_smoothness``): the
sample's own features are its rows of the pass's features, only the perturbed copies are encoded besides the
points, and on the CPU one autograd node returns both and writes one table gradient. (Before: the points, the
sample and its copies went through one encoder call whose output was split, N + 2M points per kernel and a
concatenation of the pieces' gradients in the backward; separate calls for the sample would add a table-sized
gradient sum per grid, and gathering the sample through autograd a dense zero-filled gradient of the features.)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import torch
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, UNIT, Range, validate_config
from pidg.models.deformation.base import (
    GROUP_GRID,
    GROUP_MLP,
    Bounds,
    DeformationModel,
    DeformedGaussians,
    NormalizedPositions,
)
from pidg.models.deformation.hash_grid import (
    GRID4D_SPATIAL,
    GRID4D_TEMPORAL,
    HashGridBackend,
    HashGrid,
    HashGridConfig,
)
from pidg.models.deformation.gate import attention, gate
from pidg.models.deformation.warp import apply_warp, split_heads
from pidg.models.parallel_linear import Linear, linear


@dataclass
class Grid4DConfig:
    """Grid4D field. Defaults: the paper's synthetic-scene settings (decoder depth 0; use 1 for real scenes).

    ``width`` (the paper's 256) sets f_s, f_t and the decoder. On CPU the f_t layer (3 * 64 -> width) and the
    heads are most of the field's cost at width 256; a CPU configuration may use 64-128.
    """

    spatial_grid: HashGridConfig = field(default_factory=lambda: GRID4D_SPATIAL)
    """G_xyz, the time-independent grid behind the directional attention."""
    temporal_grid: HashGridConfig = field(default_factory=lambda: GRID4D_TEMPORAL)
    """G_xyt, G_yzt, G_xzt (one config for the three; the third axis of each is time)."""
    width: Annotated[int, AT_LEAST_ONE] = 256
    """Width of f_s, f_t and the decoder (paper: 256)."""
    decoder_depth: Annotated[int, NON_NEGATIVE] = 0
    """Hidden Linear+ReLU layers between h and the heads (paper: 0 for synthetic scenes, 1 for real ones)."""
    spatial_relu: bool = False
    """ReLU after f_s, as the paper's text says. Off by default: Grid4D's code uses a bare Linear, which lets
    a = 2 sigmoid - 1 be negative, while the ReLU confines a to [0, 1), contradicting the text's own a in (-1, 1)."""
    time_margin: Annotated[float, Range(0, 1, lo_open=True)] = 0.9
    """t in [0, 1] maps to [0.5 - m/2, 0.5 + m/2] on the temporal grids (away from their boundary)."""
    rotate_with_warp: bool = True
    """The rigid warp also rotates the Gaussian's orientation (Grid4D's code only adds dr)."""
    detach_positions: bool = True
    """Encode detached positions (as Grid4D and Deformable-3DGS do): canonical means still get gradients through
    mu' directly, just not through the grids' coordinate derivatives (which would cost about a forward pass)."""
    reg_fraction: Annotated[float, UNIT] = 0.1
    """Share of the points the smoothness regulariser samples in each regularised pass."""
    reg_spatial_perturb: Annotated[tuple[float, float, float], NON_NEGATIVE] = (3.125e-3, 3.125e-3, 3.125e-3)
    """Perturbation half-widths x y z in unit-box coordinates (Grid4D's 1e-2 in its [-1.6, 1.6] box is 1e-2 / 3.2)."""
    reg_temporal_perturb: Annotated[tuple[float, float, float, float], NON_NEGATIVE] = (3.125e-3, 3.125e-3, 3.125e-3, 0.0)
    """Perturbation half-widths x y z t of the temporal grids' coordinates (unit box)."""
    reg_spatial_weight: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the spatial grid's smoothness term."""
    reg_temporal_weight: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the temporal grids' smoothness term."""
    max_translation: Annotated[float, NON_NEGATIVE] = 0.0
    """Soft bound on the warp's translation T, in box half-extents: T = b tanh(T_raw / b) (0: unbounded). Early
    in a run the field can push Gaussians tens of half-extents away, and at fine temporal grids it runs away."""
    max_log_scale_change: Annotated[float, NON_NEGATIVE] = 0.0
    """Soft bound on ds, the change of log-scale: ds = b tanh(ds_raw / b) (0: unbounded)."""
    backend: HashGridBackend = "auto"
    """Implementation of the hash encoding, of the warp (``warp.py``) and of the attention gate (``gate.py``): numba
    kernels on float32 CPU tensors, the torch references otherwise (CUDA); cpu or torch force one (the gate follows
    torch only: its kernel needs float32 CPU tensors)."""

    def __post_init__(self) -> None:
        validate_config(self)
        if len(self.reg_spatial_perturb) != 3 or len(self.reg_temporal_perturb) != 4:
            raise ValueError("Grid4DConfig: reg_spatial_perturb needs 3 values and reg_temporal_perturb 4 (x, y, z, t)")


class Grid4D(DeformationModel):
    """The Grid4D deformation field (see the module docstring)."""

    def __init__(self, config: Grid4DConfig | None = None, bounds: Bounds | None = None) -> None:
        super().__init__()
        self.config = cfg = config or Grid4DConfig()
        self.normalize = NormalizedPositions(bounds)
        self.grid_xyz = HashGrid(cfg.spatial_grid, cfg.backend)
        self.grid_xyt = HashGrid(cfg.temporal_grid, cfg.backend)
        self.grid_yzt = HashGrid(cfg.temporal_grid, cfg.backend)
        self.grid_xzt = HashGrid(cfg.temporal_grid, cfg.backend)
        f_s_activation = [nn.ReLU()] if cfg.spatial_relu else []
        self.spatial_mlp = nn.Sequential(Linear(self.grid_xyz.out_dim, cfg.width), *f_s_activation)
        self.temporal_mlp = nn.Sequential(Linear(3 * self.grid_xyt.out_dim, cfg.width), nn.ReLU())
        hidden: list[nn.Module] = []
        for _ in range(cfg.decoder_depth):
            hidden += [Linear(cfg.width, cfg.width), nn.ReLU()]
        self.decoder = nn.Sequential(*hidden)
        self.head_warp = Linear(cfg.width, 7)  # rigid warp: quaternion increment (4), translation (3)
        self.head_rotation = Linear(cfg.width, 4)  # dr
        self.head_scale = Linear(cfg.width, 3)  # ds (log space)
        for head in (self.head_warp, self.head_rotation, self.head_scale):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        self._attention_cache: tuple[tuple, Tensor, Tensor] | None = None

    # -- coordinates and features ------------------------------------------------------------------------------

    def grid_coordinates(self, means: Tensor, times: Tensor) -> tuple[Tensor, Tensor]:
        """World positions [N, 3] and times [N] in [0, 1] -> unit-box positions [N, 3] and times [N]."""
        u_xyz = 0.5 + 0.5 * self.normalize(means)
        u_t = 0.5 + 0.5 * self.config.time_margin * (2.0 * times - 1.0)
        return u_xyz, u_t

    def encode_spatial(self, u_xyz: Tensor) -> Tensor:
        return self.grid_xyz(u_xyz)

    def encode_temporal(self, u_xyz: Tensor, u_t: Tensor) -> Tensor:
        inputs = _temporal_inputs(torch.cat([u_xyz, u_t[:, None]], dim=-1))
        return torch.cat([grid(coords) for grid, coords in zip(self.temporal_grids, inputs)], dim=-1)

    @property
    def temporal_grids(self) -> tuple[HashGrid, HashGrid, HashGrid]:
        """G_xyt, G_yzt, G_xzt, in the order of ``TEMPORAL_AXES``."""
        return self.grid_xyt, self.grid_yzt, self.grid_xzt

    def attention(self, spatial_features: Tensor) -> Tensor:
        """Directional attention a = 2 sigmoid(f_s(.)) - 1, in (-1, 1)."""
        return attention(self.spatial_mlp(spatial_features), self._kernels)

    @property
    def _kernels(self) -> bool | None:
        """The gate's implementation: the torch reference when ``config.backend`` is torch, else by the tensors
        (numba for float32 CPU ones)."""
        return False if self.config.backend == "torch" else None

    def _cached_attention(self, u_xyz: Tensor) -> Tensor:
        """Attention at canonical positions. Without autograd (rendering many frames of one model), the attention
        of unchanged canonical positions and parameters is reused: it does not depend on time."""
        if torch.is_grad_enabled():
            return self.attention(self.encode_spatial(u_xyz))
        versions = tuple(p._version for p in [self.grid_xyz.table, *self.spatial_mlp.parameters()])
        key = (versions, u_xyz.shape, u_xyz.device, u_xyz.dtype)
        cache = self._attention_cache
        if cache is not None and cache[0] == key and torch.equal(cache[1], u_xyz):
            return cache[2]
        a = self.attention(self.encode_spatial(u_xyz))
        self._attention_cache = (key, u_xyz.clone(), a)
        return a

    # -- deformation ---------------------------------------------------------------------------------------------

    def deform(  # type: ignore[override]  # also takes its invariant features back (DeformationModel.deform)
        self, means: Tensor, quats: Tensor, log_scales: Tensor, times: Tensor, regularize: bool = False,
        invariant: Tensor | None = None,
    ) -> DeformedGaussians:
        """The deformed Gaussians, with the directional attention a as their ``invariant`` features: it depends on
        the canonical position only, so a pass at another time takes it back (``invariant``) and skips G_xyz and
        f_s (the flow loss's pass at t+1; measured on bouncingballs' full step, 26k Gaussians: ~5 of 300 ms). A pass
        with ``regularize`` computes its own (the regulariser perturbs G_xyz's inputs)."""
        dtype = self.grid_xyz.table.dtype
        positions = means.detach() if self.config.detach_positions else means
        u_xyz, u_t = self.grid_coordinates(positions.to(dtype), times.to(dtype))
        regularization = None
        if regularize:
            spatial, temporal, regularization = self._encode_with_regularizer(u_xyz, u_t)
            # a and a * f_t(.) in one pass: f_t is Linear + ReLU, the ReLU applied by the gate
            a, gated = gate(self.spatial_mlp(spatial), self.temporal_mlp[0](temporal), self._kernels)
        else:
            a = self._cached_attention(u_xyz) if invariant is None else invariant.to(dtype)
            gated = a * self.temporal_mlp(self.encode_temporal(u_xyz, u_t))
        h = self.decoder(gated)
        new_means, new_quats, new_log_scales = apply_warp(
            means.to(dtype), quats.to(dtype), log_scales.to(dtype), self._heads(h), self.normalize.centre.to(dtype),
            self.normalize.half_extent.to(dtype), self.config.rotate_with_warp, self.config.backend,
        )
        return DeformedGaussians(
            new_means.to(means.dtype), new_quats.to(quats.dtype), new_log_scales.to(log_scales.dtype), regularization, a
        )

    def _heads(self, h: Tensor) -> Tensor:
        """The warp (w, T), dr and ds heads' outputs [N, 14] (``warp.WARP_COLUMNS``) as one matrix product (a third
        of the launches and of the backward's passes over h)."""
        heads = (self.head_warp, self.head_rotation, self.head_scale)
        out = linear(h, torch.cat([m.weight for m in heads]), torch.cat([m.bias for m in heads]))
        bound_t, bound_s = self.config.max_translation, self.config.max_log_scale_change
        if not (bound_t or bound_s):
            return out
        w, translation, dr, ds = split_heads(out)
        if bound_t:
            translation = bound_t * torch.tanh(translation / bound_t)
        if bound_s:
            ds = bound_s * torch.tanh(ds / bound_s)
        return torch.cat([w, translation, dr, ds], dim=-1)

    # -- regulariser --------------------------------------------------------------------------------------------

    def _encode_with_regularizer(self, u_xyz: Tensor, u_t: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """Spatial [N, Fs] and temporal [N, Ft] features of the points, and Grid4D's smoothness term on a random
        ``reg_fraction`` of them: weight * mean over the sampled points of the summed squared feature change under
        a small uniform perturbation, spatial plus temporal grids (None when nothing is sampled)."""
        cfg = self.config
        n = u_xyz.shape[0]
        m = int(round(n * cfg.reg_fraction))
        spatial_w = cfg.reg_spatial_weight if m else 0.0
        temporal_w = cfg.reg_temporal_weight if m else 0.0
        if not (spatial_w or temporal_w):
            return self.encode_spatial(u_xyz), self.encode_temporal(u_xyz, u_t), None
        rows = torch.randperm(n, device=u_xyz.device)[:m]
        term = u_xyz.new_zeros(())
        if spatial_w:
            jittered = u_xyz[rows].detach() + _uniform_like(u_xyz[:m], cfg.reg_spatial_perturb)
            spatial, change = self.grid_xyz.with_smoothness(u_xyz, jittered, rows)
            term = term + spatial_w * change / m
        else:
            spatial = self.encode_spatial(u_xyz)
        if temporal_w:
            u4 = torch.cat([u_xyz, u_t[:, None]], dim=-1)
            jittered4 = u4[rows].detach() + _uniform_like(u4[:m], cfg.reg_temporal_perturb)
            pairs = [grid.with_smoothness(coords, jittered, rows) for grid, coords, jittered
                     in zip(self.temporal_grids, _temporal_inputs(u4), _temporal_inputs(jittered4))]
            temporal = torch.cat([features for features, _ in pairs], dim=-1)
            term = term + temporal_w * sum(change for _, change in pairs) / m
        else:
            temporal = self.encode_temporal(u_xyz, u_t)
        return spatial, temporal, term

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        grids = [g.table for g in (self.grid_xyz, self.grid_xyt, self.grid_yzt, self.grid_xzt)]
        grid_ids = {id(p) for p in grids}
        networks = [p for p in self.parameters() if id(p) not in grid_ids]
        groups = {GROUP_GRID: [p for p in grids if p.requires_grad], GROUP_MLP: [p for p in networks if p.requires_grad]}
        return {k: v for k, v in groups.items() if v}


#: The columns of (x, y, z, t) that G_xyt, G_yzt and G_xzt read, in this order.
TEMPORAL_AXES = ((0, 1, 3), (1, 2, 3), (0, 2, 3))
_TEMPORAL_COLUMNS = [c for axes in TEMPORAL_AXES for c in axes]


def _temporal_inputs(u4: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The three temporal grids' inputs [N, 3] from points [N, 4] (x y z t): views of one gathered [N, 9] tensor
    (one op instead of a stack per grid; the kernels read strided inputs)."""
    columns = torch.tensor(_TEMPORAL_COLUMNS, device=u4.device)
    return tuple(u4.index_select(1, columns).split(3, dim=-1))  # type: ignore[return-value]


def _uniform_like(x: Tensor, half_widths: tuple[float, ...]) -> Tensor:
    """Uniform noise in [-w, w] per column."""
    w = torch.tensor(half_widths, dtype=x.dtype, device=x.device)
    return (torch.rand_like(x) * 2.0 - 1.0) * w
