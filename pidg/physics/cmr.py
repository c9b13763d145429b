"""Cauchy momentum residual r = rho (dv/dt + (v . grad) v) - div sigma and the block-sampled loss L_CMR.

Conventions (NOTES.md section 5), with the jet layout dv_dx[m, j, i] = d v_j / d x_i:
  * convective term ((v . grad) v)_j = sum_i v_i d v_j / d x_i, i.e. (grad v) v with grad v the Jacobian. The
    reference code computes (grad v)^T v = grad(|v|^2 / 2) instead, which differs whenever grad v is not
    symmetric (e.g. shear flow v = (y, 0, 0): (v . grad) v = 0 but grad(|v|^2 / 2) = (0, y, 0));
  * (div sigma)_j = sum_i d sigma_ji / d x_i with sigma symmetric, assembled from (xx, yy, zz, xy, xz, yz).

Units: positions in world units, velocities in world units per physics time unit, the residual in world units per
physics time unit squared (at unit density); see :mod:`pidg.models.time_axis`.

``cmr_loss`` is what the trainer calls every step (from ``PhysicsConfig.start`` on): it draws M particles
(``samples``) without replacement from the N deformed Gaussians and evaluates the field's jet on them in blocks of
``block_size``. Only those M rows ever go through the network, so time and memory are independent of N apart from
drawing the subset (paper supp. "Block-sampled CMR"). The paper frees each block's graph by calling backward per
block; here the loss is one scalar the trainer adds to its total, and ``checkpoint_blocks`` is the equivalent:
each block's activations are recomputed during backward instead of being stored. Measured peak RSS growth of one
step (``pidg bench cmr``): ~40 MiB at M = 1024 for both N = 20k and 200k; at M = 4096, 155 MiB in one block,
110 MiB in blocks of 1024, 60 MiB in checkpointed blocks of 1024 (+15-30% time).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from pidg.errors import NonFiniteError, all_finite
from pidg.models.deformation.base import times_column
from pidg.models.jet import SYMMETRIC_INDEX, FieldJet
from pidg.models.time_axis import TimeAxis
from pidg.physics.config import PhysicsConfig

#: names of ``CMRResult.stats``: means over the sampled particles of the norms of these [M, 3] / [M, 6] rows
STAT_NAMES = ("residual", "velocity", "stress", "inertia", "stress_divergence")


class JetField(Protocol):
    """Anything that gives a FieldJet at positions, times and particle indices (the MaterialField does)."""

    def jet(self, x: Tensor, t: float | Tensor, index: Tensor) -> FieldJet: ...


@dataclass
class CMRResult:
    """L_CMR (unweighted) and diagnostics: ``stats[name]`` is the mean norm over the M samples (detached)."""

    loss: Tensor
    stats: dict[str, Tensor]
    num_samples: int


# ---------------------------------------------------------------------------------------------------------------
# the residual
# ---------------------------------------------------------------------------------------------------------------
def convective_acceleration(jet: FieldJet) -> Tensor:
    """((v . grad) v)_j = sum_i v_i d v_j / d x_i  [M, 3] (not grad(|v|^2 / 2))."""
    return (jet.dv_dx @ jet.v.unsqueeze(-1)).squeeze(-1)


def material_acceleration(jet: FieldJet) -> Tensor:
    """Dv/Dt = dv/dt + (v . grad) v  [M, 3]."""
    return jet.dv_dt + convective_acceleration(jet)


def stress_divergence(dsigma_dx: Tensor) -> Tensor:
    """(div sigma)_j = sum_i d sigma_ji / d x_i  [M, 3] from dsigma_dx [M, 6, 3] (d sigma_c / d x_i)."""
    component = torch.tensor(SYMMETRIC_INDEX, device=dsigma_dx.device)  # [3, 3]: sigma_ji is component[j, i]
    axis = torch.arange(3, device=dsigma_dx.device)
    return dsigma_dx[:, component, axis].sum(dim=-1)  # [M, j, i] = d sigma_ji / d x_i, summed over i


def momentum_residual(jet: FieldJet, density: float = 1.0, stress: bool = True) -> Tensor:
    """r = rho Dv/Dt - div sigma  [M, 3]; with ``stress`` False the stress term is dropped (sigma == 0)."""
    inertia = density * material_acceleration(jet)
    return inertia - stress_divergence(jet.dsigma_dx) if stress else inertia


# ---------------------------------------------------------------------------------------------------------------
# the sampled, blocked loss
# ---------------------------------------------------------------------------------------------------------------
def sample_rows(n: int, m: int, generator: torch.Generator | None = None) -> Tensor | None:
    """M distinct rows out of N drawn with ``generator`` (CPU), or None for "all rows" when N <= M."""
    if n <= m:
        return None
    return torch.randperm(n, generator=generator)[:m]


def _block_terms(field: JetField, x: Tensor, times: Tensor, index: Tensor, density: float, time_scale: float) -> tuple[Tensor, Tensor]:
    """Sum over the block of |r|^2 and the detached sums of the diagnostic norms (STAT_NAMES order).

    ``time_scale``: physics time units per unit of the field's time input, so dv/d(tau) = dv/dt / time_scale. A
    field without stress returns zero stress derivatives, so its divergence is exactly 0.
    """
    jet = field.jet(x, times, index)
    if time_scale != 1.0:
        jet = replace(jet, dv_dt=jet.dv_dt / time_scale)
    inertia = density * material_acceleration(jet)
    divergence = stress_divergence(jet.dsigma_dx)
    residual = inertia - divergence
    rows = (residual, jet.v, jet.sigma, inertia, divergence)
    stats = torch.stack([r.detach().norm(dim=-1).sum() for r in rows])
    return residual.square().sum(), stats


def cmr_loss(
    field: JetField,
    positions: Tensor,
    t: float | Tensor,
    index: Tensor,
    config: PhysicsConfig,
    time_axis: TimeAxis,
    generator: torch.Generator | None = None,
) -> CMRResult:
    """L_CMR = mean over M sampled particles of |r|^2 at their deformed positions and time, in physics time units.

    positions [N, 3]: the Gaussians' positions at time t (the deformation's output; gradients flow into it unless
    ``config.detach_positions``). t: dataset time, float or [N] in [0, 1]. index [N]: ``GaussianModel.particle_index``.
    time_axis: the scene's clocks (dv/d tau = dv/dt / ``time_axis.physics_per_dataset``).
    generator: the trainer's CPU generator for the subset (saved in checkpoints for reproducibility).
    """
    if positions.dim() != 2 or positions.shape[1] != 3:
        raise ValueError(f"cmr_loss: positions must be [N, 3], got {list(positions.shape)}")
    n = positions.shape[0]
    if index.shape != (n,):
        raise ValueError(f"cmr_loss: index must be [N] = [{n}], got {list(index.shape)}")
    if n == 0:
        raise ValueError("cmr_loss: no particles")
    if not all_finite(positions.detach()):  # all N rows: a broken deformation, sampled or not
        bad = torch.nonzero(~torch.isfinite(positions.detach()).all(dim=1)).squeeze(1)
        raise NonFiniteError(f"cmr_loss: non-finite positions in {bad.numel()} rows, e.g. rows {bad[:5].tolist()}")
    times = times_column(t, n, positions)
    x = positions.detach() if config.detach_positions else positions
    rows = sample_rows(n, config.samples, generator)
    if rows is not None:
        rows = rows.to(positions.device)
        x, times, index = x[rows], times[rows], index[rows]
    m = x.shape[0]
    total_sq = x.new_zeros(())
    total_stats = x.new_zeros(len(STAT_NAMES))
    for start in range(0, m, config.block_size):
        block = slice(start, start + config.block_size)
        args = (field, x[block], times[block], index[block], config.density, time_axis.physics_per_dataset)
        if config.checkpoint_blocks and torch.is_grad_enabled():
            sq, stats = checkpoint(_block_terms, *args, use_reentrant=False)
        else:
            sq, stats = _block_terms(*args)
        total_sq = total_sq + sq
        total_stats = total_stats + stats
    return CMRResult(
        loss=total_sq / m,
        stats={name: value for name, value in zip(STAT_NAMES, (total_stats / m).unbind())},
        num_samples=m,
    )
