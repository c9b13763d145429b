"""Adaptive density control of 3DGS (clone, split, prune, opacity reset) as a strategy object.

In the style of gsplat's ``DefaultStrategy``: the trainer calls :meth:`DensificationStrategy.step_pre_backward`
after rendering and :meth:`DensificationStrategy.step_post_backward` after ``loss.backward()``; the strategy edits
the model's parameter dict *and* the optimizers that hold those parameters, so that Adam's moments stay row-aligned
with the Gaussians (new rows start with zero moments, pruned rows take theirs with them).

Every per-Gaussian row travels together: all entries of ``model.params`` (including extra ones other modules add)
and of ``model.buffers`` (``particle_index``, later e.g. a dynamic mask). A child (clone or split) copies its
parent's row, except the sampled position and shrunk scale of split children. Tensors owned elsewhere can follow
through :attr:`DensificationStrategy.row_callbacks`: each is called with ``source`` [N_new], the old row every
new row comes from, so ``t = t[source]`` keeps them in step. Tensors indexed by ``particle_index`` (the material
field's index embedding) need nothing.

Gradient statistic. 3DGS thresholds the norm of the gradient with respect to the projected centre in NDC
coordinates. Our ``means2d`` are in pixels, and pixel = ((ndc + 1) * W - 1) / 2, so dL/d(ndc_x) = dL/d(px) * W/2
(and H/2 for y). The accumulated statistic is therefore ||grad_px * (W/2, H/2)||, averaged over the views in
which the Gaussian was visible, and the 3DGS threshold 2e-4 keeps its meaning at any resolution.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, MutableMapping, Protocol, Sequence

import torch
from torch import Tensor, nn

from pidg.render.api import RenderOutput
from pidg.render.projection import quat_to_rotmat

logger = logging.getLogger(__name__)

OptimizerSet = Mapping[str, torch.optim.Optimizer] | Sequence[torch.optim.Optimizer] | torch.optim.Optimizer


class Densifiable(Protocol):
    """What the strategy edits: per-Gaussian parameters and buffers, all with N rows (GaussianModel fits)."""

    params: MutableMapping[str, nn.Parameter]
    buffers: MutableMapping[str, Tensor]


@dataclass
class DensificationConfig:
    """3DGS / reference-config defaults. Steps are the trainer's step numbers.

    Statistics are gathered and the schedule runs while ``step < stop``. Densification (clone + split, then
    prune) happens when ``start < step`` and ``step % every == 0``; opacity is reset when ``step % opacity_reset_every
    == 0``. The screen- and world-size pruning rules apply only after the first opacity reset (as in 3DGS), since
    before it large Gaussians are still expected.
    """

    start: int = 500
    stop: int = 15_000
    every: int = 100
    grad_threshold: float = 2e-4  # on the NDC-equivalent view-space positional gradient (module docstring)
    percent_dense: float = 0.01  # max scale <= this x scene extent: clone; larger: split
    split_samples: int = 2  # children per split Gaussian
    split_scale_factor: float = 1.6  # children's scales = parent's / this (3DGS: 0.8 x split_samples)
    opacity_reset_every: int = 3000
    opacity_reset_value: float = 0.01  # opacities are clamped to at most this
    prune_opacity: float = 0.005
    prune_screen_radius: float = 20.0  # pixels, max radius seen since the last densification
    prune_world_scale: float = 0.1  # max scale > this x scene extent (PIDG scenes: 0.015, supp. D)
    seed: int | None = 42  # split sampling; None = torch's global generator

    def __post_init__(self) -> None:
        if self.every < 1 or self.opacity_reset_every < 1:
            raise ValueError("DensificationConfig: every and opacity_reset_every must be >= 1")
        if self.split_samples < 1 or self.split_scale_factor <= 0:
            raise ValueError("DensificationConfig: split_samples must be >= 1 and split_scale_factor > 0")
        if not 0.0 < self.opacity_reset_value < 1.0:
            raise ValueError(f"DensificationConfig.opacity_reset_value must be in (0, 1), got {self.opacity_reset_value}")


@dataclass
class DensifyReport:
    """What one densification round did, for logging."""

    step: int
    cloned: int
    split: int
    pruned: int
    num_gaussians: int


class DensificationStrategy:
    """Clone / split / prune / opacity reset on a :class:`Densifiable` model and its optimizers.

    ``optimizers`` may be a dict (one optimizer per parameter, as :func:`pidg.training.optim.make_gaussian_optimizers`
    builds), a list, or a single optimizer with several parameter groups: parameters are found by identity.
    Assign :attr:`optimizers` again if the trainer rebuilds them. ``scene_extent`` is the ``SceneBounds.radius``.
    """

    def __init__(
        self,
        model: Densifiable,
        optimizers: OptimizerSet,
        scene_extent: float,
        config: DensificationConfig | None = None,
    ) -> None:
        if not scene_extent > 0:
            raise ValueError(f"DensificationStrategy: scene_extent must be > 0, got {scene_extent}")
        self.model = model
        self.optimizers = optimizers
        self.scene_extent = float(scene_extent)
        self.config = config or DensificationConfig()
        self.row_callbacks: list[Callable[[Tensor], None]] = []
        self.generator: torch.Generator | None = None
        if self.config.seed is not None:
            self.generator = torch.Generator(device=self._device).manual_seed(self.config.seed)
        self.check_sanity()
        self.grad_accum, self.count, self.max_radii = self._zero_stats(self.num_gaussians)

    # ---- bookkeeping ----------------------------------------------------------------------------------------
    @property
    def params(self) -> MutableMapping[str, nn.Parameter]:
        return self.model.params

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def _device(self) -> torch.device:
        return self.params["means"].device

    def _zero_stats(self, n: int) -> tuple[Tensor, Tensor, Tensor]:
        z = lambda dtype: torch.zeros(n, dtype=dtype, device=self._device)  # noqa: E731
        return z(torch.float32), z(torch.int32), z(torch.float32)

    def reset_statistics(self) -> None:
        self.grad_accum, self.count, self.max_radii = self._zero_stats(self.num_gaussians)

    def _ensure_statistics(self) -> None:
        """Restart the statistics if the model was resized behind our back (e.g. a checkpoint was loaded)."""
        if self.grad_accum.shape[0] != self.num_gaussians:
            self.reset_statistics()

    def _indices(self, mask: Tensor) -> Tensor:
        if mask.dtype != torch.bool or tuple(mask.shape) != (self.num_gaussians,):
            raise ValueError(f"DensificationStrategy: expected a bool mask of shape [{self.num_gaussians}], got {mask.dtype} {list(mask.shape)}")
        return mask.nonzero().squeeze(1)

    def check_sanity(self) -> None:
        """Raise if the model lacks a parameter the rules need or rows disagree."""
        missing = [k for k in ("means", "quats", "log_scales", "opacity_logits") if k not in self.params]
        if missing:
            raise KeyError(f"DensificationStrategy: the model has no parameter(s) {missing}")
        n = self.num_gaussians
        rows = {**{k: v.shape[0] for k, v in self.params.items()}, **{k: v.shape[0] for k, v in self.model.buffers.items()}}
        bad = {k: r for k, r in rows.items() if r != n}
        if bad:
            raise ValueError(f"DensificationStrategy: per-Gaussian tensors must all have {n} rows, got {bad}")

    def _optimizer_list(self) -> list[torch.optim.Optimizer]:
        if isinstance(self.optimizers, torch.optim.Optimizer):
            return [self.optimizers]
        if isinstance(self.optimizers, Mapping):
            return list(self.optimizers.values())
        return list(self.optimizers)

    def _swap_parameter(self, old: nn.Parameter, new: nn.Parameter, update: Callable[[Tensor], Tensor]) -> None:
        """Put ``new`` where ``old`` was in every optimizer, mapping its per-row state tensors with ``update``."""
        for opt in self._optimizer_list():
            for group in opt.param_groups:
                for i, p in enumerate(group["params"]):
                    if p is old:
                        group["params"][i] = new
                        state = opt.state.pop(old, None)
                        if state is not None:
                            opt.state[new] = {
                                k: update(v) if isinstance(v, Tensor) and v.shape == old.shape else v for k, v in state.items()
                            }

    def _rebuild(self, keep: Tensor, parents: Tensor, new_values: Mapping[str, Tensor] | None = None) -> None:
        """New rows = old rows ``keep`` followed by children of ``parents`` (index tensors into the old rows).

        Children copy their parent's row unless ``new_values`` gives it. Optimizer moments: kept rows keep theirs,
        children start at zero. Statistics likewise.
        """
        self._ensure_statistics()
        new_values = new_values or {}
        n_new = int(parents.numel())
        source = torch.cat([keep, parents])

        def update(v: Tensor) -> Tensor:
            return torch.cat([v[keep], v.new_zeros((n_new,) + v.shape[1:])])

        for name, old in list(self.params.items()):
            child = new_values.get(name)
            child = old.data[parents] if child is None else child.to(old.dtype)
            new = nn.Parameter(torch.cat([old.data[keep], child]), requires_grad=old.requires_grad)
            self._swap_parameter(old, new, update)
            self.params[name] = new
        for name, buf in list(self.model.buffers.items()):
            self.model.buffers[name] = buf[source]
        self.grad_accum, self.count, self.max_radii = (
            torch.cat([s[keep], s.new_zeros(n_new)]) for s in (self.grad_accum, self.count, self.max_radii)
        )
        for callback in self.row_callbacks:
            callback(source)

    # ---- elementary operations ------------------------------------------------------------------------------
    def clone(self, mask: Tensor) -> int:
        """Append an exact copy of each selected Gaussian (zero Adam moments for the copies)."""
        idx = self._indices(mask)
        if idx.numel():
            self._rebuild(torch.arange(self.num_gaussians, device=self._device), idx)
        return int(idx.numel())

    def split(self, mask: Tensor) -> int:
        """Replace each selected Gaussian by ``split_samples`` children drawn from it, scales / ``split_scale_factor``.

        Child positions are samples of N(mean, R diag(scale)^2 R^T), i.e. of the parent Gaussian itself.
        """
        idx = self._indices(mask)
        if idx.numel() == 0:
            return 0
        k = self.config.split_samples
        parents = idx.repeat(k)  # [k * m]: sample 1 of every parent, then sample 2, ...
        p = self.params
        with torch.no_grad():
            scales = torch.exp(p["log_scales"][parents])
            noise = torch.randn(scales.shape, generator=self.generator, device=scales.device, dtype=scales.dtype)
            rot = quat_to_rotmat(p["quats"][parents])
            means = p["means"][parents] + (rot @ (noise * scales).unsqueeze(-1)).squeeze(-1)
            log_scales = torch.log(scales / self.config.split_scale_factor)
        keep = (~mask).nonzero().squeeze(1)
        self._rebuild(keep, parents, {"means": means, "log_scales": log_scales})
        return int(idx.numel())

    def prune(self, mask: Tensor) -> int:
        """Remove the selected Gaussians together with their optimizer moments, statistics and buffers."""
        n = int(self._indices(mask).numel())
        if n:
            self._rebuild((~mask).nonzero().squeeze(1), torch.zeros(0, dtype=torch.long, device=self._device))
        return n

    def reset_opacity(self) -> None:
        """Clamp opacities to at most ``opacity_reset_value`` and zero the opacity parameter's Adam moments.

        Zeroed moments let the opacities that matter climb back at full speed instead of carrying old momentum.
        """
        p = self.params["opacity_logits"]
        v = self.config.opacity_reset_value
        with torch.no_grad():
            p.clamp_(max=math.log(v / (1.0 - v)))
        for opt in self._optimizer_list():
            state = opt.state.get(p)
            if state:
                for t in state.values():
                    if isinstance(t, Tensor) and t.shape == p.shape:
                        t.zero_()

    # ---- statistics -----------------------------------------------------------------------------------------
    def update_statistics(
        self, render_output: RenderOutput | Sequence[RenderOutput], width: int | None = None, height: int | None = None
    ) -> None:
        """Accumulate the NDC-equivalent positional gradient norm, the visibility count and the max radius.

        Several outputs (e.g. frames t and t+1 rendered in one step) each count as one view. Outputs whose
        ``means2d`` received no gradient are skipped. Width/height default to the size of the rendered image.
        """
        outputs = [render_output] if isinstance(render_output, RenderOutput) else list(render_output)
        n = self.num_gaussians
        self._ensure_statistics()
        for out in outputs:
            grad = out.means2d.grad
            if grad is None:
                continue
            if grad.shape != (n, 2):
                raise ValueError(f"DensificationStrategy: means2d.grad has shape {list(grad.shape)}, the model has {n} Gaussians")
            h, w = out.rgb.shape[:2]
            w, h = width or w, height or h
            norm = (grad.detach().to(torch.float32) * grad.new_tensor([w / 2.0, h / 2.0], dtype=torch.float32)).norm(dim=-1)
            vis = out.visible
            self.grad_accum[vis] += norm[vis]
            self.count[vis] += 1
            radius = out.radii.max(dim=-1).values.to(torch.float32)
            self.max_radii[vis] = torch.maximum(self.max_radii[vis], radius[vis])

    # ---- hooks ----------------------------------------------------------------------------------------------
    def step_pre_backward(self, render_output: RenderOutput | Sequence[RenderOutput]) -> None:
        """Make sure ``means2d`` keeps its gradient (``rasterize`` already does; other producers may not)."""
        outputs = [render_output] if isinstance(render_output, RenderOutput) else list(render_output)
        for out in outputs:
            if out.means2d.requires_grad:
                out.means2d.retain_grad()

    def step_post_backward(
        self,
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
        self.update_statistics(render_output, width, height)
        report = None
        if step > c.start and step % c.every == 0:
            report = self.densify_and_prune(step)
        if step > 0 and step % c.opacity_reset_every == 0:
            self.reset_opacity()
        return report

    def densify_and_prune(self, step: int) -> DensifyReport:
        """One 3DGS densification round: clone small and split large high-gradient Gaussians, then prune."""
        c = self.config
        grads = self.grad_accum / self.count.clamp_min(1)
        high = (grads >= c.grad_threshold) & (self.count > 0)
        with torch.no_grad():
            max_scale = torch.exp(self.params["log_scales"]).max(dim=-1).values
        large = max_scale > c.percent_dense * self.scene_extent
        split_mask = high & large  # decided before cloning; the clones (appended at the end) are never split
        cloned = self.clone(high & ~large)
        split = self.split(torch.cat([split_mask, split_mask.new_zeros(cloned)]))
        pruned = self.prune(self.prune_mask(step))
        self.reset_statistics()
        report = DensifyReport(step, cloned, split, pruned, self.num_gaussians)
        logger.debug("densify step %d: +%d cloned, %d split, -%d pruned -> %d", step, cloned, split, pruned, report.num_gaussians)
        return report

    def prune_mask(self, step: int) -> Tensor:
        """Gaussians to remove: nearly transparent ones, and after the first opacity reset too-large ones."""
        c = self.config
        with torch.no_grad():
            mask = torch.sigmoid(self.params["opacity_logits"]).reshape(self.num_gaussians, -1)[:, 0] < c.prune_opacity
            if step > c.opacity_reset_every:
                mask |= self.max_radii > c.prune_screen_radius
                mask |= torch.exp(self.params["log_scales"]).max(dim=-1).values > c.prune_world_scale * self.scene_extent
        return mask

    # ---- persistence ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"grad_accum": self.grad_accum.clone(), "count": self.count.clone(), "max_radii": self.max_radii.clone()}
        if self.generator is not None:
            state["generator"] = self.generator.get_state()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.grad_accum = state["grad_accum"].to(self._device)
        self.count = state["count"].to(self._device)
        self.max_radii = state["max_radii"].to(self._device)
        if self.generator is not None and "generator" in state:
            self.generator.set_state(state["generator"])

