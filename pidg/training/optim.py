"""Every optimizer of a run and the learning-rate schedule each follows, built in one place.

* Gaussians: one Adam per parameter (gsplat's layout): densification can then swap a parameter's rows and its Adam
  moments without touching the others. Positions follow 3DGS's log-linear decay; the rest keep their rate.
* Deformation field and material field: Adam over their parameter groups (hash grids / planes get a multiple of
  the network rate), decayed x0.1 per ``OptimConfig.deformation_lr_decay_every`` steps, applied smoothly. The
  deformation's optimizer waits for the end of the static warm-up. The material field's index embedding has a
  sparse gradient and gets ``SparseAdam`` (torch's, its CPU update fused: :mod:`pidg.training.sparse_adam`).

The scene model supplies the parameters (``GaussianModel.params``, ``parameter_groups()`` of its fields); nothing
below the training layer builds an optimizer.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.autograd.graph import increment_version

from pidg.models.deformation import GROUP_GRID, GROUP_MLP, DeformationModel
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModel
from pidg.models.material_field import GROUP_EMBEDDING, MaterialField
from pidg.training.config import GaussianOptimConfig, TrainConfig
from pidg.training.sparse_adam import SparseAdam

#: (step, a parameter group's base learning rate) -> the group's learning rate at that step
Schedule = Callable[[int, float], float]
BETAS = (0.9, 0.999)
EPS = 1e-15  # 3DGS: tiny, so that Adam's normalised step is not damped for small-gradient parameters


@dataclass
class ScheduledOptimizer:
    """An optimizer, the schedule of its learning rates, and the first step it steps at (gradients that arrive
    earlier are dropped, e.g. the deformation's during a static warm-up)."""

    optimizer: torch.optim.Optimizer
    schedule: Schedule
    start: int = 0

    def step(self, step: int, lr_scale: float = 1.0) -> None:
        """Set each group's rate for ``step`` (times ``lr_scale``, which rollbacks after a divergence lower) and step
        (once started). The gradients stay until ``zero_grad``: the trainer reads them to name the cause when the
        updated parameters are not finite."""
        if step >= self.start:
            for group in self.optimizer.param_groups:
                lr = self.schedule(step, group["base_lr"])
                group["lr"] = lr if lr_scale == 1.0 else lr * lr_scale
            self.optimizer.step()

    def zero_grad(self) -> None:
        """Clear the gradients (those that arrived before ``start`` are dropped here unused)."""
        self.optimizer.zero_grad(set_to_none=True)

    def load_state_dict(self, state: dict) -> None:
        """Restore moments and step counts, but keep this optimizer's hyper-parameters (learning rates, betas,
        eps): on resume the new config's values apply instead of being silently replaced by the saved ones."""
        hyper = [{k: v for k, v in group.items() if k != "params"} for group in self.optimizer.param_groups]
        self.optimizer.load_state_dict(state)
        for group, values in zip(self.optimizer.param_groups, hyper):
            group.update(values)


def means_lr_at(step: int, config: GaussianOptimConfig, scene_extent: float, iterations: int) -> float:
    """Log-linear decay of the position learning rate (3DGS ``expon_lr_func`` without the warm-up delay), over
    ``means_lr_decay_steps`` or, when that is 0, over the run's ``iterations`` (as 3DGS, whose schedule ends with
    its run: a 2400-step run on a 30k-step schedule would end at 69% of the initial rate instead of 1%)."""
    t = min(max(step, 0) / max(1, config.means_lr_decay_steps or iterations), 1.0)
    lr = math.exp((1.0 - t) * math.log(config.means_lr) + t * math.log(config.means_lr_final))
    return lr * scene_extent


def adam(param_groups: list[dict], **kwargs) -> torch.optim.Adam:
    """Adam, fused into one kernel per step when every parameter is a float32 CPU or CUDA tensor.

    The unfused CPU Adam runs ~10 tensor ops per parameter; on the Grid4D hash tables (~8M entries) that was
    30 ms per step against 6 ms fused (measured on 2 cores). The update is the same algorithm. The fused kernel
    writes the parameters without bumping their version counters (torch 2.13, CPU), so each step bumps them, as
    torch's own in-place update would: autograd's in-place checks and caches keyed by a parameter's version (Grid4D's
    attention) then see the change.
    """
    params = [p for group in param_groups for p in group["params"]]
    fused = bool(params) and all(p.dtype == torch.float32 and p.device.type in ("cpu", "cuda") for p in params)
    optimizer = torch.optim.Adam(param_groups, fused=fused, **kwargs)
    if fused:
        optimizer.register_step_post_hook(_mark_updated)
    return optimizer


def _mark_updated(optimizer: torch.optim.Optimizer, args: tuple, kwargs: dict) -> None:
    """Bump the version of every parameter of ``optimizer`` after its step (see :func:`adam`)."""
    increment_version([p for group in optimizer.param_groups for p in group["params"]])


def make_gaussian_optimizers(
    model: GaussianModel, config: GaussianOptimConfig | None = None, scene_extent: float = 1.0
) -> dict[str, torch.optim.Adam]:
    """One Adam per Gaussian parameter, keyed like ``model.params`` (extra parameters are left to their owners)."""
    config = config or GaussianOptimConfig()
    lrs = {
        "means": config.means_lr * scene_extent,  # the schedule's start (set every step)
        "quats": config.quats_lr,
        "log_scales": config.log_scales_lr,
        "opacity_logits": config.opacity_lr,
        "sh_dc": config.sh_dc_lr,
        "sh_rest": config.sh_rest_lr,
    }
    return {
        name: adam([{"params": [model.params[name]], "lr": lr, "base_lr": lr, "name": name}], lr=lr, betas=config.betas, eps=config.eps)
        for name, lr in lrs.items()
    }


def _groups(groups: dict[str, list[torch.nn.Parameter]], lrs: dict[str, float], prefix: str) -> list[dict]:
    return [
        {"params": params, "lr": lrs[name], "base_lr": lrs[name], "name": f"{prefix}{name}"}
        for name, params in groups.items() if params and name in lrs
    ]


#: The optimizers whose rates decay like the networks' (``OptimConfig.deformation_lr_decay_every``)
FIELD_OPTIMIZERS = ("deformation", "material", "material_embedding")


def schedule_for(name: str, config: TrainConfig, scene_extent: float) -> Schedule:
    """The learning-rate schedule of the optimizer ``name`` (a key of ``make_optimizers``' result) under ``config``:
    positions decay log-linearly, the fields' networks and grids x0.1 per decay period, the rest keep their rate."""
    o, g = config.optim, config.gaussian_optim
    if name == "means":
        return lambda step, base: means_lr_at(step, g, scene_extent, o.iterations)
    if name in FIELD_OPTIMIZERS:
        return lambda step, base: base * 0.1 ** (step / max(o.deformation_lr_decay_every or o.iterations, 1))
    return lambda step, base: base


def reschedule(optimizers: dict[str, ScheduledOptimizer], config: TrainConfig, scene_extent: float) -> None:
    """Give every optimizer the schedule of ``config`` (a run shortened to fit its time budget decays over the new
    length); moments and step counts stay."""
    for name, opt in optimizers.items():
        opt.schedule = schedule_for(name, config, scene_extent)


def deformation_optimizer(field: DeformationModel, config: TrainConfig, scene_extent: float) -> ScheduledOptimizer | None:
    """The deformation field's optimizer in a run of ``config``: its networks at ``optim.deformation_lr``, its hash
    grids ``grid_lr_factor`` times that, decayed as :func:`schedule_for` says, from step ``optim.static_warmup``
    (None for a field without parameters). ``pidg bench motion-fit`` fits a fresh field with it too."""
    o = config.optim
    lrs = {GROUP_GRID: o.deformation_lr * o.grid_lr_factor, GROUP_MLP: o.deformation_lr}
    groups = _groups(field.parameter_groups(), lrs, "")
    if not groups:
        return None
    return ScheduledOptimizer(adam(groups, betas=BETAS, eps=EPS), schedule_for("deformation", config, scene_extent),
                              start=o.static_warmup)


def material_optimizers(field: MaterialField, config: TrainConfig, scene_extent: float) -> dict[str, ScheduledOptimizer]:
    """The material field's optimizers in a run of ``config``: ``material`` (its MLP at ``optim.material_lr``, its
    planes ``material_grid_lr_factor`` times that) and ``material_embedding`` (the index embedding, sparse).
    ``pidg bench motion-fit`` fits a fresh field with them too."""
    o = config.optim
    field_groups = field.parameter_groups()
    lrs = {GROUP_GRID: o.material_lr * o.material_grid_lr_factor, GROUP_MLP: o.material_lr}
    out = {}
    dense = _groups(field_groups, lrs, "material_")
    if dense:
        out["material"] = ScheduledOptimizer(adam(dense, betas=BETAS, eps=EPS), schedule_for("material", config, scene_extent))
    # The embedding's gradient is sparse (only the M sampled rows): a dense one would cost a zero-filled [P, H]
    # tensor and a full Adam update per step, i.e. time and memory growing with the number of particles
    # (measured: +24 ms per step at P = 200k). SparseAdam also leaves rows that were not sampled untouched.
    sparse = _groups(field_groups, {GROUP_EMBEDDING: o.material_embedding_lr}, "material_")
    if sparse:
        out["material_embedding"] = ScheduledOptimizer(SparseAdam(sparse, betas=BETAS, eps=EPS),
                                                       schedule_for("material_embedding", config, scene_extent))
    return out


def make_optimizers(model: DynamicGaussians, config: TrainConfig, scene_extent: float) -> dict[str, ScheduledOptimizer]:
    """All optimizers of a run: the Gaussian parameters' (keyed by parameter name), ``deformation``, and with a
    material field ``material`` and ``material_embedding``."""
    g = config.gaussian_optim
    out = {
        name: ScheduledOptimizer(opt, schedule_for(name, config, scene_extent))
        for name, opt in make_gaussian_optimizers(model.gaussians, g, scene_extent).items()
    }
    deformation = deformation_optimizer(model.deformation, config, scene_extent)
    if deformation is not None:
        out["deformation"] = deformation
    if model.material_field is not None:
        out.update(material_optimizers(model.material_field, config, scene_extent))
    return out
