"""The interface every deformation model implements: canonical Gaussians + time -> Gaussians at that time.

Kept small on purpose so that Grid4D, the MLP baseline and "no deformation" are interchangeable from the config:
``forward(means, quats, log_scales, t, static_mask, regularize, invariant) -> DeformedGaussians`` and
``parameter_groups()`` (so the trainer can give hash grids a larger learning rate than MLPs). A model with a
regulariser (Grid4D's smoothness term) returns it with the pass that asked for it (``regularize=True``), so a step
that deforms to several times (t and t+1 for the flow loss) knows which pass each term belongs to. A model whose
features of a Gaussian partly do not depend on time (Grid4D's directional attention) returns them with the pass
(``DeformedGaussians.invariant``), and a pass over the same Gaussians at another time takes them back
(``invariant=``) instead of computing them again: the same values and gradients for less work.

Conventions shared by the models:
  * quaternions are (w, x, y, z) like the renderer, and need not be normalised (the renderer normalises);
  * scales are in log space, and a predicted scale change is added there (``log s' = log s + ds``): the scale
    stays positive whatever ds is, and ds is a relative change (Grid4D adds ds to the linear scale instead);
  * a predicted rotation increment ``dr`` acts as the unit quaternion ``normalize((1, 0, 0, 0) + dr)``
    multiplied on the left of the Gaussian's quaternion (a rotation in world space), so dr = 0 is the identity;
  * positions are normalised by an axis-aligned box (``Bounds``) before any encoding, so that encodings and
    learning rates do not depend on the scene's units; predicted translations are in units of the box's
    half-extent.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pidg.kernel_math import select_distinct_rows

GROUP_GRID = "grid"  # hash-grid tables: the trainer's high-learning-rate group
GROUP_MLP = "mlp"  # network weights


@dataclass
class DeformedGaussians:
    """Gaussians at one time: the canonical ones moved by a deformation model."""

    means: Tensor  # [N, 3] world units
    quats: Tensor  # [N, 4] (w, x, y, z)
    log_scales: Tensor  # [N, 3] log of world units
    regularization: Tensor | None = None  # the model's regulariser for this pass (scalar; None unless asked for)
    #: the model's time-independent features of these Gaussians (Grid4D: its directional attention; None for models
    #: without any), for a pass over the same Gaussians at another time: [N, D], one row per Gaussian, or, from a pass
    #: whose static mask skipped some, [M, D] for the M it deformed (``invariant_rows``): a pass that only renders
    #: then pays nothing for the skipped rows
    invariant: Tensor | None = None
    #: [M] (ascending) the Gaussians ``invariant``'s rows belong to when it holds only the deformed ones; None: all
    invariant_rows: Tensor | None = None

    def invariant_of(self, rows: Tensor) -> Tensor | None:
        """The invariant features [len(rows), D] of the Gaussians ``rows`` (indices), 0 for those the pass skipped,
        whichever layout ``invariant`` holds."""
        if self.invariant is None:
            return None
        if self.invariant_rows is None:
            return _rows_of(self.invariant, rows)
        deformed_rows = self.invariant_rows
        if deformed_rows.numel() == 0:
            return self.invariant.new_zeros(rows.numel(), self.invariant.shape[1])
        # each asked Gaussian's place among the deformed ones (ascending): a search over the few asked rows, not a
        # position map over all N built per call
        at = torch.searchsorted(deformed_rows, rows).clamp_max(deformed_rows.numel() - 1)
        found = deformed_rows.index_select(0, at) == rows
        if self.invariant.device.type != "cpu":  # no host sync on an accelerator
            return _masked_rows(self.invariant, at, found)
        if bool(found.all()):  # only moving Gaussians asked: their rows as they are
            return _rows_of(self.invariant, at)
        # static ones too (zero rows): gather the others' and place them, so that increasing rows stay a distinct gather
        placed = found.nonzero().squeeze(1)
        gathered = _rows_of(self.invariant, at.index_select(0, placed))
        return gathered.new_zeros(rows.numel(), gathered.shape[1]).index_copy(0, placed, gathered)


def _masked_rows(source: Tensor, index: Tensor, keep: Tensor) -> Tensor:
    """``source``'s rows ``index`` [K], zero where ``keep`` [K] is False, without a host sync (any device)."""
    return source.index_select(0, index) * keep.unsqueeze(1).to(source.dtype)


def _rows_of(source: Tensor, index: Tensor) -> Tensor:
    """``source.index_select(0, index)``; on the CPU, for strictly increasing indices (the flow loss's Gaussians), by
    ``select_distinct_rows``, whose gradient re-zeroes the rows it writes instead of a zero-filled [N, D] copy (the
    [13k, 64] attention: 1.2 of the 1.4 ms its gather cost forward and backward)."""
    if source.device.type == "cpu" and (index.numel() < 2 or bool((index[1:] > index[:-1]).all())):
        return select_distinct_rows(source, index)
    return source.index_select(0, index)


@dataclass(frozen=True)
class Bounds:
    """Box used to normalise positions: ``x_hat = (x - centre) / half_extent`` is in [-1, 1]^3 inside it."""

    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    half_extent: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        if len(self.centre) != 3 or len(self.half_extent) != 3:
            raise ValueError(f"Bounds: centre and half_extent need 3 values, got {self.centre}, {self.half_extent}")
        if min(self.half_extent) <= 0:
            raise ValueError(f"Bounds: half_extent must be positive, got {self.half_extent}")

    @classmethod
    def from_aabb(cls, lo: Tensor | tuple[float, ...], hi: Tensor | tuple[float, ...], margin: float = 0.0) -> "Bounds":
        """The box [lo, hi] grown by ``margin`` (a fraction of its half-extent) on every side."""
        lo_t = torch.as_tensor(lo, dtype=torch.float64).reshape(3)
        hi_t = torch.as_tensor(hi, dtype=torch.float64).reshape(3)
        half = ((hi_t - lo_t) / 2 * (1 + margin)).clamp_min(1e-6)
        centre = (hi_t + lo_t) / 2
        return cls(tuple(centre.tolist()), tuple(half.tolist()))  # type: ignore[arg-type]

    @classmethod
    def from_points(cls, points: Tensor, margin: float = 0.1, cube: bool = True) -> "Bounds":
        """Box around points [P, 3] plus ``margin``; ``cube`` keeps the grids' cells cubic (as Grid4D's bound)."""
        lo, hi = points.detach().min(dim=0).values, points.detach().max(dim=0).values
        if cube:
            centre, half = (hi + lo) / 2, ((hi - lo) / 2).max()
            lo, hi = centre - half, centre + half
        return cls.from_aabb(lo, hi, margin)


def as_bounds(source: "Bounds | Tensor | object | None", margin: float = 0.1) -> Bounds:
    """Normalisation box from what a caller has at hand.

    ``Bounds``: used as is. A tensor of points [P, 3] (best: the initial Gaussians' means): a cube around them
    plus ``margin``. A ``pidg.data.SceneBounds``: a cube around its point-cloud box if it has one, otherwise
    the sphere of the training cameras (``center``, ``radius``), which is much larger than an object seen from
    outside, so the grids' resolution is spent on empty space; prefer passing points then. None: the unit box.
    """
    if source is None:
        return Bounds()
    if isinstance(source, Bounds):
        return source
    if isinstance(source, Tensor):
        return Bounds.from_points(source.reshape(-1, 3), margin=margin)
    lo, hi = getattr(source, "points_min", None), getattr(source, "points_max", None)
    if lo is not None and hi is not None:
        return Bounds.from_points(torch.stack([torch.as_tensor(lo), torch.as_tensor(hi)]), margin=margin)
    centre, radius = getattr(source, "center", None), getattr(source, "radius", None)
    if centre is not None and radius is not None:
        r = float(radius)
        return Bounds(tuple(float(c) for c in torch.as_tensor(centre).reshape(3)), (r, r, r))  # type: ignore[arg-type]
    raise TypeError(f"as_bounds: cannot make a box from {type(source).__name__}")


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of (w, x, y, z) quaternions [..., 4]: rotate by b, then by a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def unit_quat_from_delta(delta: Tensor) -> Tensor:
    """``normalize((1, 0, 0, 0) + delta)`` for a predicted increment delta [..., 4]; delta = 0 -> identity."""
    identity = torch.zeros_like(delta)
    identity[..., 0] = 1.0
    return F.normalize(identity + delta, dim=-1, eps=1e-8)


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors v [..., 3] by unit quaternions q [..., 4] (Rodrigues form, no 3x3 matrices)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(xyz, v, dim=-1)
    return v + w * t + torch.linalg.cross(xyz, t, dim=-1)


def times_column(t: float | Tensor, n: int, like: Tensor) -> Tensor:
    """Times as an [N] tensor on ``like``'s device and dtype, from a float, a 0-d, [1] or [N] tensor."""
    times = torch.as_tensor(t, dtype=like.dtype, device=like.device)
    if times.dim() == 0 or times.numel() == 1:
        return times.reshape(1).expand(n)
    if tuple(times.shape) not in ((n,), (n, 1)):
        raise ValueError(f"deformation: t must be a float or a tensor of shape [N] = [{n}], got {list(times.shape)}")
    return times.reshape(n)


class DeformationModel(nn.Module, ABC):
    """Base class: handles time broadcasting and the static mask; subclasses implement ``deform``."""

    def forward(
        self,
        means: Tensor,
        quats: Tensor,
        log_scales: Tensor,
        t: float | Tensor,
        static_mask: Tensor | None = None,
        regularize: bool = False,
        invariant: Tensor | None = None,
    ) -> DeformedGaussians:
        """Deform canonical Gaussians [N, ...] to time t (a float or [N] times, in [0, 1]).

        Rows where ``static_mask`` [N] bool is True are returned unchanged and are not evaluated at all (stage 2
        of PIDG keeps static Gaussians out of the deformation), so they receive no gradient through the model.
        ``regularize``: also return the model's regulariser on the deformed rows (training). ``invariant``: the
        ``DeformedGaussians.invariant`` of a pass of this model over these same Gaussians (same canonical parameters
        and static mask, any time), used instead of computing them: [N, D], or [M, D] for the M rows the static mask
        leaves to deform, in order (what a pass with that mask returns).
        """
        n = means.shape[0]
        if means.shape != (n, 3) or quats.shape != (n, 4) or log_scales.shape != (n, 3):
            raise ValueError(
                f"deformation: expected means [N, 3], quats [N, 4], log_scales [N, 3], got "
                f"{list(means.shape)}, {list(quats.shape)}, {list(log_scales.shape)}"
            )
        times = times_column(t, n, means)
        if static_mask is None:
            _check_invariant_rows(invariant, n)
            return self._deform(means, quats, log_scales, times, regularize, invariant)
        if static_mask.shape != (n,) or static_mask.dtype != torch.bool:
            raise ValueError(f"deformation: static_mask must be a bool tensor [N] = [{n}], got {static_mask.dtype} {list(static_mask.shape)}")
        rows = torch.nonzero(~static_mask).squeeze(1)
        _check_invariant_rows(invariant, n, rows.numel())
        if rows.numel() == n:
            return self._deform(means, quats, log_scales, times, regularize, invariant)
        if rows.numel() == 0:
            return DeformedGaussians(means, quats, log_scales)
        if invariant is not None and invariant.shape[0] == n:
            # index_select rather than x[rows]: its backward (index_add) is ~3x faster on the CPU for the invariant's
            # 64-wide rows than advanced indexing's (index_put with accumulate)
            invariant = invariant.index_select(0, rows)
        moved = self._deform(*(x.index_select(0, rows) for x in (means, quats, log_scales, times)), regularize, invariant)
        return DeformedGaussians(
            means.index_copy(0, rows, moved.means.to(means.dtype)),
            quats.index_copy(0, rows, moved.quats.to(quats.dtype)),
            log_scales.index_copy(0, rows, moved.log_scales.to(log_scales.dtype)),
            moved.regularization,
            # the deformed rows' only, not spread over all N with zeros: nothing but a later pass's invariant_of reads
            # them, and most passes have no later pass (an [N, 64] zero-fill and copy, ~1 ms a step at 18k)
            moved.invariant,
            None if moved.invariant is None else rows,
        )

    def _deform(
        self, means: Tensor, quats: Tensor, log_scales: Tensor, times: Tensor, regularize: bool, invariant: Tensor | None
    ) -> DeformedGaussians:
        """``deform``, handing ``invariant`` on only when there are some: a model that returns none (the MLP, identity,
        a user's own) keeps the five-argument ``deform``."""
        if invariant is None:
            return self.deform(means, quats, log_scales, times, regularize)
        return self.deform(means, quats, log_scales, times, regularize, invariant=invariant)  # type: ignore[call-arg]

    @abstractmethod
    def deform(self, means: Tensor, quats: Tensor, log_scales: Tensor, times: Tensor, regularize: bool = False) -> DeformedGaussians:
        """Deform every row; ``times`` is [N]; with ``regularize``, fill ``regularization`` if the model has one. A
        model that returns time-independent features (``DeformedGaussians.invariant``) also takes them back as
        ``invariant=`` [N, D] (``forward``'s); only such a model is ever given them."""

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by optimiser group (``GROUP_GRID``, ``GROUP_MLP``); empty groups are left out."""
        params = [p for p in self.parameters() if p.requires_grad]
        return {GROUP_MLP: params} if params else {}


def _check_invariant_rows(invariant: Tensor | None, n: int, deformed: int | None = None) -> None:
    """``invariant`` has one row per Gaussian (n) or, with a static mask, one per deformed Gaussian."""
    if invariant is None or invariant.shape[0] == n or invariant.shape[0] == deformed:
        return
    per = f"one row per Gaussian ({n})" + ("" if deformed is None else f" or per deformed Gaussian ({deformed})")
    raise ValueError(f"deformation: invariant features must have {per}, got {list(invariant.shape)}")


class NormalizedPositions(nn.Module):
    """Holds the normalisation box as buffers, so it is saved in checkpoints and follows ``.to(device)``."""

    def __init__(self, bounds: "Bounds | Tensor | object | None" = None) -> None:
        super().__init__()
        b = as_bounds(bounds)
        self.register_buffer("centre", torch.tensor(b.centre, dtype=torch.float32))
        self.register_buffer("half_extent", torch.tensor(b.half_extent, dtype=torch.float32))

    def set_bounds(self, bounds: "Bounds | Tensor | object") -> None:
        """Replace the box (e.g. once the initial Gaussians are known); only sensible before training."""
        b = as_bounds(bounds)
        self.centre.copy_(torch.tensor(b.centre))
        self.half_extent.copy_(torch.tensor(b.half_extent))

    def forward(self, x: Tensor) -> Tensor:
        """World positions [N, 3] -> [-1, 1]^3 inside the box (not clamped: outside points map outside)."""
        return (x - self.centre.to(x.dtype)) / self.half_extent.to(x.dtype)
