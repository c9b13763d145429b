"""Adaptive density control of 3DGS (clone, split, prune, opacity reset), in gsplat's shape.

The strategy is a config and the scene extent; it holds no tensors. Its evolving state (gradient statistics and
the split sampler) is a :class:`DensificationState` the trainer keeps and checkpoints, and the Gaussians (their
``params`` and per-Gaussian ``buffers``) and optimizers are passed on every call::

    state = strategy.initialize_state(num_gaussians, device)
    out = render(...)
    strategy.step_pre_backward(out)          # keep means2d's gradient
    loss.backward()
    strategy.step_post_backward(gaussians, optimizers, state, step, out)

so loading other Gaussians or rebuilding optimizers needs nothing from the strategy. The elementary operations
(:func:`clone`, :func:`split`, :func:`prune`, :func:`reset_opacity`) take the same arguments. They edit the parameter
dict *and* the optimizers holding those parameters, so that Adam's moments stay row-aligned with the Gaussians
(new rows start with zero moments, pruned rows take theirs with them), and every per-Gaussian row travels together:
all entries of ``params`` (extra ones too), of ``buffers`` (``particle_index``, the static/dynamic split) and the
state's statistics. A child (clone or split) copies its parent's row, except the sampled position and shrunk scale
of split children. Tensors indexed by ``particle_index`` (the material field's index embedding) need nothing.

Gradient statistic. 3DGS thresholds the norm of the gradient with respect to the projected centre in NDC
coordinates. Our ``means2d`` are in pixels, and pixel = ((ndc + 1) * W - 1) / 2, so dL/d(ndc_x) = dL/d(px) * W/2
(and H/2 for y). The accumulated statistic is therefore ||grad_px * (W/2, H/2)||, averaged over the views in
which the Gaussian was visible, and the 3DGS threshold 2e-4 keeps its meaning at any resolution.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Annotated, Any, Callable, Mapping, MutableMapping, Protocol, Sequence

import torch
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, Range, validate_config
from pidg.render import RenderOutput
from pidg.render.projection import quat_to_rotmat

logger = logging.getLogger(__name__)

OptimizerSet = Mapping[str, torch.optim.Optimizer] | Sequence[torch.optim.Optimizer] | torch.optim.Optimizer


class Densifiable(Protocol):
    """What densification edits: per-Gaussian parameters and buffers, all with N rows (GaussianModel fits)."""

    params: MutableMapping[str, nn.Parameter]
    buffers: MutableMapping[str, Tensor]


@dataclass
class DensificationConfig:
    """3DGS adaptive density control (clone, split, prune, opacity reset); defaults: 3DGS and the reference
    configs. Statistics are gathered and the schedule runs while step < stop; the screen- and world-size pruning
    rules apply only after the first opacity reset (as in 3DGS), since before it large Gaussians are expected."""

    start: Annotated[int, NON_NEGATIVE] = 500
    """Densify (clone + split, then prune) at steps after this one that are multiples of every."""
    stop: Annotated[int, NON_NEGATIVE] = 15_000
    """Last step (exclusive) of densification, its statistics and opacity resets; static/dynamic decoupling
    happens here."""
    every: Annotated[int, AT_LEAST_ONE] = 100
    """Steps between densification rounds."""
    grad_threshold: Annotated[float, NON_NEGATIVE] = 2e-4
    """Densify Gaussians whose mean NDC-equivalent view-space positional gradient reaches this (see the module)."""
    percent_dense: Annotated[float, POSITIVE] = 0.01
    """Max scale <= this x scene extent: clone; larger: split."""
    split_samples: Annotated[int, AT_LEAST_ONE] = 2
    """Children per split Gaussian."""
    split_scale_factor: Annotated[float, POSITIVE] = 1.6
    """Children's scales = the parent's / this (3DGS: 0.8 x split_samples)."""
    opacity_reset_every: Annotated[int, AT_LEAST_ONE] = 3000
    """Steps between opacity resets."""
    opacity_reset_value: Annotated[float, Range(0, 1, lo_open=True, hi_open=True)] = 0.01
    """An opacity reset clamps opacities to at most this."""
    prune_opacity: Annotated[float, Range(0, 1, hi_open=True)] = 0.005
    """Prune Gaussians less opaque than this."""
    prune_screen_radius: Annotated[float, POSITIVE] = 20.0
    """Prune Gaussians whose radius exceeded this many pixels since the last densification (after the first reset)."""
    prune_world_scale: Annotated[float, POSITIVE] = 0.1
    """Prune Gaussians whose max scale exceeds this x scene extent (after the first reset; PIDG scenes: 0.015)."""
    max_gaussians: Annotated[int, NON_NEGATIVE] = 0
    """Densification adds Gaussians only up to this count, the highest-gradient candidates first (a CPU budget:
    a step's cost grows with the count); 0: no limit. Pruning is unaffected."""
    seed: Annotated[int, NON_NEGATIVE] | None = 42
    """Seed of the split sampling; none = torch's global generator."""

    def __post_init__(self) -> None:
        validate_config(self)


@dataclass
class DensifyReport:
    """What one densification round did, for logging."""

    step: int
    cloned: int
    split: int
    pruned: int
    num_gaussians: int


@dataclass
class DensificationState:
    """Per-Gaussian statistics since the last densification round, and the split sampler."""

    grad_accum: Tensor  # [N] float32, sum of NDC-equivalent gradient norms over the views that saw the Gaussian
    count: Tensor  # [N] int32, views that saw it
    max_radii: Tensor  # [N] float32, largest screen radius (pixels)
    generator: torch.Generator | None  # split sampling, on the CPU (None: torch's global generator)

    @property
    def num_gaussians(self) -> int:
        return int(self.grad_accum.shape[0])

    def reset_statistics(self, n: int | None = None) -> None:
        """Zero the statistics (for ``n`` Gaussians, default the current count)."""
        n = self.num_gaussians if n is None else n
        device = self.grad_accum.device
        self.grad_accum = torch.zeros(n, dtype=torch.float32, device=device)
        self.count = torch.zeros(n, dtype=torch.int32, device=device)
        self.max_radii = torch.zeros(n, dtype=torch.float32, device=device)

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"grad_accum": self.grad_accum.clone(), "count": self.count.clone(), "max_radii": self.max_radii.clone()}
        if self.generator is not None:
            state["generator"] = self.generator.get_state()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        device = self.grad_accum.device
        self.grad_accum = state["grad_accum"].to(device)
        self.count = state["count"].to(device)
        self.max_radii = state["max_radii"].to(device)
        if self.generator is not None and "generator" in state:
            self.generator.set_state(state["generator"])


# ---------------------------------------------------------------------------------------------------------------
# elementary operations
# ---------------------------------------------------------------------------------------------------------------
def _num_rows(gaussians: Densifiable) -> int:
    return int(gaussians.params["means"].shape[0])


def check_sanity(gaussians: Densifiable) -> None:
    """Raise if the Gaussians lack a parameter the rules need or their per-Gaussian rows disagree."""
    missing = [k for k in ("means", "quats", "log_scales", "opacity_logits") if k not in gaussians.params]
    if missing:
        raise KeyError(f"densification: the Gaussians have no parameter(s) {missing}")
    n = _num_rows(gaussians)
    rows = {**{k: v.shape[0] for k, v in gaussians.params.items()}, **{k: v.shape[0] for k, v in gaussians.buffers.items()}}
    bad = {k: r for k, r in rows.items() if r != n}
    if bad:
        raise ValueError(f"densification: per-Gaussian tensors must all have {n} rows, got {bad}")


def _indices(gaussians: Densifiable, mask: Tensor) -> Tensor:
    n = _num_rows(gaussians)
    if mask.dtype != torch.bool or tuple(mask.shape) != (n,):
        raise ValueError(f"densification: expected a bool mask of shape [{n}], got {mask.dtype} {list(mask.shape)}")
    return mask.nonzero().squeeze(1)


def _optimizer_list(optimizers: OptimizerSet) -> list[torch.optim.Optimizer]:
    if isinstance(optimizers, torch.optim.Optimizer):
        return [optimizers]
    if isinstance(optimizers, Mapping):
        return list(optimizers.values())
    return list(optimizers)


def _swap_parameter(optimizers: OptimizerSet, old: nn.Parameter, new: nn.Parameter, update: Callable[[Tensor], Tensor]) -> None:
    """Put ``new`` where ``old`` was in every optimizer (found by identity), mapping its per-row state tensors."""
    for opt in _optimizer_list(optimizers):
        for group in opt.param_groups:
            for i, p in enumerate(group["params"]):
                if p is old:
                    group["params"][i] = new
                    moments = opt.state.pop(old, None)
                    if moments is not None:
                        opt.state[new] = {k: update(v) if isinstance(v, Tensor) and v.shape == old.shape else v for k, v in moments.items()}


def _ensure_statistics(gaussians: Densifiable, state: DensificationState) -> None:
    """Restart the statistics if the Gaussians were resized behind the state's back (e.g. another model loaded)."""
    if state.num_gaussians != _num_rows(gaussians):
        state.reset_statistics(_num_rows(gaussians))


def _rebuild(
    gaussians: Densifiable, optimizers: OptimizerSet, state: DensificationState, keep: Tensor, parents: Tensor,
    new_values: Mapping[str, Tensor] | None = None,
) -> None:
    """New rows = old rows ``keep`` followed by children of ``parents`` (index tensors into the old rows).

    Children copy their parent's row unless ``new_values`` gives it. Optimizer moments and statistics: kept rows
    keep theirs, children start at zero.
    """
    _ensure_statistics(gaussians, state)
    new_values = new_values or {}
    n_new = int(parents.numel())
    source = torch.cat([keep, parents])

    def update(v: Tensor) -> Tensor:
        return torch.cat([v[keep], v.new_zeros((n_new,) + v.shape[1:])])

    for name, old in list(gaussians.params.items()):
        child = new_values.get(name)
        child = old.data[parents] if child is None else child.to(old.dtype)
        new = nn.Parameter(torch.cat([old.data[keep], child]), requires_grad=old.requires_grad)
        _swap_parameter(optimizers, old, new, update)
        gaussians.params[name] = new
    for name, buf in list(gaussians.buffers.items()):
        gaussians.buffers[name] = buf[source]
    state.grad_accum, state.count, state.max_radii = (update(s) for s in (state.grad_accum, state.count, state.max_radii))


def clone(gaussians: Densifiable, optimizers: OptimizerSet, state: DensificationState, mask: Tensor) -> int:
    """Append an exact copy of each selected Gaussian (zero Adam moments for the copies)."""
    idx = _indices(gaussians, mask)
    if idx.numel():
        _rebuild(gaussians, optimizers, state, torch.arange(_num_rows(gaussians), device=idx.device), idx)
    return int(idx.numel())


def split(
    gaussians: Densifiable, optimizers: OptimizerSet, state: DensificationState, mask: Tensor,
    samples: int = 2, scale_factor: float = 1.6,
) -> int:
    """Replace each selected Gaussian by ``samples`` children drawn from it, scales / ``scale_factor``.

    Child positions are samples of N(mean, R diag(scale)^2 R^T), i.e. of the parent Gaussian itself.
    """
    idx = _indices(gaussians, mask)
    if idx.numel() == 0:
        return 0
    parents = idx.repeat(samples)  # [k * m]: sample 1 of every parent, then sample 2, ...
    p = gaussians.params
    with torch.no_grad():
        scales = torch.exp(p["log_scales"][parents])
        # drawn on the CPU (the sampler is a CPU generator on every device, so checkpoints move between devices)
        noise = torch.randn(scales.shape, generator=state.generator, dtype=scales.dtype).to(scales.device)
        rot = quat_to_rotmat(p["quats"][parents])
        means = p["means"][parents] + (rot @ (noise * scales).unsqueeze(-1)).squeeze(-1)
        log_scales = torch.log(scales / scale_factor)
    keep = (~mask).nonzero().squeeze(1)
    _rebuild(gaussians, optimizers, state, keep, parents, {"means": means, "log_scales": log_scales})
    return int(idx.numel())


def prune(gaussians: Densifiable, optimizers: OptimizerSet, state: DensificationState, mask: Tensor) -> int:
    """Remove the selected Gaussians together with their optimizer moments, statistics and buffers."""
    n = int(_indices(gaussians, mask).numel())
    if n:
        _rebuild(gaussians, optimizers, state, (~mask).nonzero().squeeze(1), torch.zeros(0, dtype=torch.long, device=mask.device))
    return n


def within_budget(candidates: Tensor, grads: Tensor, large: Tensor, room: int, split_samples: int) -> Tensor:
    """The densification candidates [N] bool that fit in ``room`` more Gaussians, highest gradient first: a clone
    adds one Gaussian, a split (``large``) ``split_samples - 1``."""
    index = candidates.nonzero().squeeze(1)
    cost = torch.where(large[index], split_samples - 1, 1)
    if int(cost.sum()) <= room:
        return candidates
    order = torch.argsort(grads[index], descending=True, stable=True)
    fits = torch.cumsum(cost[order], 0) <= max(room, 0)
    kept = torch.zeros_like(candidates)
    kept[index[order[fits]]] = True
    return kept


def reset_opacity(gaussians: Densifiable, optimizers: OptimizerSet, value: float) -> None:
    """Clamp opacities to at most ``value`` and zero the opacity parameter's Adam moments.

    Zeroed moments let the opacities that matter climb back at full speed instead of carrying old momentum.
    """
    p = gaussians.params["opacity_logits"]
    with torch.no_grad():
        p.clamp_(max=math.log(value / (1.0 - value)))
    for opt in _optimizer_list(optimizers):
        moments = opt.state.get(p)
        if moments:
            for t in moments.values():
                if isinstance(t, Tensor) and t.shape == p.shape:
                    t.zero_()


# ---------------------------------------------------------------------------------------------------------------
# the strategy
# ---------------------------------------------------------------------------------------------------------------
def _outputs(render_output: RenderOutput | Sequence[RenderOutput]) -> list[RenderOutput]:
    return [render_output] if isinstance(render_output, RenderOutput) else list(render_output)


class DensificationStrategy:
    """3DGS's schedule of clone / split / prune / opacity reset; stateless (see the module docstring).

    ``scene_extent`` is the ``SceneBounds.radius`` the size thresholds are fractions of.
    """

    def __init__(self, config: DensificationConfig | None = None, scene_extent: float = 1.0) -> None:
        if not scene_extent > 0:
            raise ValueError(f"DensificationStrategy: scene_extent must be > 0, got {scene_extent}")
        self.config = config or DensificationConfig()
        self.scene_extent = float(scene_extent)

    def initialize_state(self, num_gaussians: int, device: torch.device | str = "cpu") -> DensificationState:
        """Zero statistics for ``num_gaussians`` Gaussians on ``device`` and a split sampler (a CPU generator)
        seeded from the config."""
        generator = None if self.config.seed is None else torch.Generator().manual_seed(self.config.seed)
        zeros = torch.zeros(num_gaussians, dtype=torch.float32, device=device)
        return DensificationState(zeros, zeros.to(torch.int32), zeros.clone(), generator)

    # ---- statistics -----------------------------------------------------------------------------------------
    def update_statistics(
        self, gaussians: Densifiable, state: DensificationState, render_output: RenderOutput | Sequence[RenderOutput],
        width: int | None = None, height: int | None = None,
    ) -> None:
        """Accumulate the NDC-equivalent positional gradient norm, the visibility count and the max radius.

        Several outputs (e.g. frames t and t+1 rendered in one step) each count as one view. Outputs whose
        ``means2d`` received no gradient are skipped. Width/height default to the size of the rendered image.
        """
        n = _num_rows(gaussians)
        _ensure_statistics(gaussians, state)
        for out in _outputs(render_output):
            grad = out.means2d_grad()
            if grad is None:
                continue
            if grad.shape != (n, 2):
                raise ValueError(f"densification: the means2d gradient has shape {list(grad.shape)}, the model has {n} Gaussians")
            h, w = out.rgb.shape[:2]
            w, h = width or w, height or h
            norm = (grad.detach().to(torch.float32) * grad.new_tensor([w / 2.0, h / 2.0], dtype=torch.float32)).norm(dim=-1)
            vis = out.visible
            # dense selects rather than boolean indexing (which finds the visible rows again for every tensor):
            # the same values, ~1.5 ms less a step at 18k Gaussians
            state.grad_accum.add_(torch.where(vis, norm, 0.0))
            state.count.add_(vis.to(state.count.dtype))
            radius = out.radii.max(dim=-1).values.to(torch.float32)
            torch.maximum(state.max_radii, torch.where(vis, radius, 0.0), out=state.max_radii)  # radii are >= 0

    # ---- hooks ----------------------------------------------------------------------------------------------
    def step_pre_backward(self, render_output: RenderOutput | Sequence[RenderOutput]) -> None:
        """Make sure ``means2d`` keeps its gradient (``rasterize`` already does; other producers may not)."""
        for out in _outputs(render_output):
            out.retain_means2d_grad()

    def step_post_backward(
        self,
        gaussians: Densifiable,
        optimizers: OptimizerSet,
        state: DensificationState,
        step: int,
        render_output: RenderOutput | Sequence[RenderOutput],
        width: int | None = None,
        height: int | None = None,
    ) -> DensifyReport | None:
        """Gather statistics, then densify / prune / reset opacity on schedule. Returns a report when it densified.

        Call it after ``loss.backward()`` and before ``optimizer.zero_grad()``; the order relative to
        ``optimizer.step()`` does not matter.
        """
        c = self.config
        if step >= c.stop:
            return None
        self.update_statistics(gaussians, state, render_output, width, height)
        report = None
        if step > c.start and step % c.every == 0:
            report = self.densify_and_prune(gaussians, optimizers, state, step)
        if step > 0 and step % c.opacity_reset_every == 0:
            reset_opacity(gaussians, optimizers, c.opacity_reset_value)
        return report

    def densify_and_prune(self, gaussians: Densifiable, optimizers: OptimizerSet, state: DensificationState, step: int) -> DensifyReport:
        """One 3DGS densification round: clone small and split large high-gradient Gaussians, then prune."""
        c = self.config
        check_sanity(gaussians)
        _ensure_statistics(gaussians, state)
        grads = state.grad_accum / state.count.clamp_min(1)
        high = (grads >= c.grad_threshold) & (state.count > 0)
        with torch.no_grad():
            max_scale = torch.exp(gaussians.params["log_scales"]).max(dim=-1).values
        large = max_scale > c.percent_dense * self.scene_extent
        if c.max_gaussians:
            high = within_budget(high, grads, large, c.max_gaussians - _num_rows(gaussians), c.split_samples)
        split_mask = high & large  # decided before cloning; the clones (appended at the end) are never split
        cloned = clone(gaussians, optimizers, state, high & ~large)
        n_split = split(
            gaussians, optimizers, state, torch.cat([split_mask, split_mask.new_zeros(cloned)]), c.split_samples, c.split_scale_factor
        )
        pruned = prune(gaussians, optimizers, state, self.prune_mask(gaussians, state, step))
        state.reset_statistics()
        report = DensifyReport(step, cloned, n_split, pruned, _num_rows(gaussians))
        logger.debug("densify step %d: +%d cloned, %d split, -%d pruned -> %d", step, cloned, n_split, pruned, report.num_gaussians)
        return report

    def prune_mask(self, gaussians: Densifiable, state: DensificationState, step: int) -> Tensor:
        """Gaussians to remove: nearly transparent ones, and after the first opacity reset too-large ones."""
        c = self.config
        n = _num_rows(gaussians)
        with torch.no_grad():
            mask = torch.sigmoid(gaussians.params["opacity_logits"]).reshape(n, -1)[:, 0] < c.prune_opacity
            if step > c.opacity_reset_every:
                mask |= state.max_radii > c.prune_screen_radius
                mask |= torch.exp(gaussians.params["log_scales"]).max(dim=-1).values > c.prune_world_scale * self.scene_extent
        return mask
