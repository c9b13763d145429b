"""The training loop: canonical Gaussians + deformation field, rendered per training frame, 3DGS densification.

One step: pick a training frame (a seeded permutation per epoch) -> deform the canonical Gaussians to its
time -> render -> photometric loss (+ regularisers) -> backward -> Adam steps -> densification strategy.
Every piece of state (parameters, Adam moments, strategy statistics, random generators, the frame order)
goes into atomic checkpoints, so an interrupted run resumes to the same result.
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import torch
from torch import Tensor

from pidg._env import retain_freed_memory
from pidg.config_tools import save_config, to_jsonable
from pidg.data.scene import Frame, SceneData
from pidg.evaluation.metrics import psnr
from pidg.models.deformation import Bounds, build_deformation
from pidg.flow import FlowCache, FlowPair, FlowTarget, LPFMResult, decode_flows, flow_target_for_pair, gaussian_flow_features, lpfm_loss, preprocess_flow
from pidg.flow.lpfm import depth_from_render
from pidg.models.gaussians import GaussianModel
from pidg.physics import build_material_field, cmr_loss
from pidg.render import RenderOutput, rasterize
from pidg.training.checkpoint import atomic_torch_save, load_checkpoint, random_states, restore_random_states, seed_everything
from pidg.training.config import TrainConfig
from pidg.training.densification import DensificationStrategy
from pidg.training.losses import photometric_loss
from pidg.training.optim import adam, make_gaussian_optimizers, means_lr_at, set_lr

logger = logging.getLogger(__name__)

STEP_PHASES = ("deformation", "physics", "flow", "render", "loss", "backward", "optimizer", "densification")


@dataclass
class StepTimer:
    """Wall time per phase of a training step (CPU work is synchronous, so perf_counter is exact)."""

    totals: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    steps: int = 0

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[name] += time.perf_counter() - t0

    def breakdown_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self.steps, 1) for k, v in self.totals.items()}


@dataclass
class _CachedTarget:
    """A pair's flow_gt, the step it was built at, and frame t+1's rendered depth (None: the dataset's depth map)."""

    step: int
    depth: Tensor | None
    target: FlowTarget | None


class Trainer:
    """Trains one scene. ``Trainer(config, scene).train()``; ``Trainer.resume(checkpoint)`` continues a run."""

    def __init__(self, config: TrainConfig, scene: SceneData) -> None:
        self.config = config
        self.scene = scene
        retain_freed_memory()  # a step's large temporaries would otherwise be re-faulted from the OS every step
        seed_everything(config.optim.seed)
        self.extent = float(scene.bounds.extent)
        self.model = GaussianModel.from_scene(scene, config.gaussians)
        # decoupling flag per Gaussian: everything is dynamic until densification ends (NOTES.md section 3)
        self.model.add_buffer("is_dynamic", torch.ones(self.model.num_gaussians, dtype=torch.bool))
        # Normalise deformation inputs by the box of the initial Gaussians, not the camera sphere: for D-NeRF-like
        # captures the sphere is ~3x the object, which wastes grid resolution and scales the warp 3x
        # (measured on bouncingballs at 200 px, 400 steps: 14 dB with the sphere, 22 dB with the box).
        bounds = Bounds.from_points(self.model.params["means"].detach())
        self.deformation = build_deformation(config.deformation, bounds)
        self.gaussian_optimizers = make_gaussian_optimizers(self.model, config.gaussian_optim, self.extent)
        self.deformation_optimizer = self._make_deformation_optimizer()
        # The material field (velocity, stress) exists when CMR or the flow loss needs it; it is evaluated at the
        # deformed positions, in the deformation's box and on the same time axis t in [0, 1].
        self.material_field = None
        self.material_optimizers: dict[str, torch.optim.Optimizer] = {}
        if config.physics.enabled or config.flow.enabled:
            self.material_field = build_material_field(config.physics, bounds, self.model.num_particles)
            self.material_optimizers = self.material_field.make_optimizers()
        self.physics_generator = torch.Generator().manual_seed(config.optim.seed + 1)
        self.physics_time_scale = self._physics_time_scale()
        self.flow_cache: FlowCache | None = self._load_flow_cache() if config.flow.enabled else None
        self._flow_targets: dict[str, _CachedTarget] = {}  # pair's first frame name -> flow_gt and what it came from
        self.strategy = DensificationStrategy(self.model, self.gaussian_optimizers, self.extent, config.densify)
        self.frame_generator = torch.Generator().manual_seed(config.optim.seed)
        self._order: list[int] = []
        self.step = 0
        self.decoupled = False
        self.train_seconds = 0.0
        self.timer = StepTimer()
        self.background = scene.background.to(torch.float32)
        self.history: list[dict[str, float]] = []

    # ---- construction -----------------------------------------------------------------------------------
    def _make_deformation_optimizer(self) -> torch.optim.Optimizer | None:
        groups = self.deformation.parameter_groups()
        cfg = self.config.optim
        param_groups = []
        for name, params in groups.items():
            params = [p for p in params if p.requires_grad]
            if not params:
                continue
            factor = cfg.grid_lr_factor if "grid" in name else 1.0
            param_groups.append({"params": params, "lr": cfg.deformation_lr * factor, "name": name, "base_lr": cfg.deformation_lr * factor})
        if not param_groups:
            return None
        return adam(param_groups, betas=(0.9, 0.999), eps=1e-15)

    def training_frame_interval(self) -> float:
        """Median time gap between consecutive distinct training times (1 with fewer than two)."""
        times = torch.tensor(sorted({f.time for f in self.scene.train}), dtype=torch.float64)
        gaps = times.diff()
        gaps = gaps[gaps > 0]
        return float(gaps.median()) if len(gaps) else 1.0

    def _physics_time_scale(self) -> float:
        """Physics time units per unit of dataset time: the config's, or (0) one per training-frame interval."""
        if self.config.physics.time_scale > 0:
            return float(self.config.physics.time_scale)
        return 1.0 / self.training_frame_interval()

    def _load_flow_cache(self) -> FlowCache:
        """Optical flow of consecutive training frames, computed once and cached next to the dataset (or in the run
        folder when the dataset folder is missing or read-only)."""
        root = Path(self.scene.root)
        cache_root = None
        if not (root.is_dir() and os.access(root, os.W_OK)):
            cache_root = Path(self.config.output.dir) / "flow_cache"
            logger.info("dataset folder %s is not writable: caching optical flow in %s", root, cache_root)
        return preprocess_flow(self.scene, self.config.flow, cache_root, progress=self.config.output.progress)

    # ---- data -------------------------------------------------------------------------------------------
    def next_frame(self) -> Frame:
        """Training frames in a fresh random order each epoch, from a generator saved in checkpoints."""
        if not self._order:
            self._order = torch.randperm(len(self.scene.train), generator=self.frame_generator).tolist()
        return self.scene.train[self._order.pop()]

    # ---- forward ----------------------------------------------------------------------------------------
    def deformation_active(self) -> bool:
        return self.step >= self.config.optim.static_warmup

    def gaussians_at(self, t: float) -> tuple[Tensor, Tensor, Tensor]:
        """Means, quaternions and log-scales of the Gaussians at time ``t`` (canonical before the warm-up ends)."""
        p = self.model.params
        if not self.deformation_active():
            return p["means"], p["quats"], p["log_scales"]
        static = ~self.model.buffers["is_dynamic"] if self.decoupled else None
        out = self.deformation(p["means"], p["quats"], p["log_scales"], t, static_mask=static)
        return out.means, out.quats, out.log_scales

    def render(self, frame: Frame, sh_degree: int | None = None) -> RenderOutput:
        means, quats, log_scales = self.gaussians_at(frame.time)
        return self._rasterize(means, quats, log_scales, frame, sh_degree)

    def _rasterize(
        self, means: Tensor, quats: Tensor, log_scales: Tensor, frame: Frame, sh_degree: int | None = None, features: Tensor | None = None
    ) -> RenderOutput:
        m = self.model
        return rasterize(
            means, quats, m.opacities, m.sh, frame.camera, log_scales=log_scales, background=self.background,
            sh_degree=m.active_sh_degree if sh_degree is None else sh_degree, backend=self.config.backend, features=features,
        )

    # ---- flow (LPFM) ------------------------------------------------------------------------------------
    def velocities(self, means: Tensor, t: float) -> Tensor:
        """v [N, 3] of the material field at the Gaussians' positions at time t; zero for static Gaussians once
        decoupled (they do not move, and evaluating the field only where it matters keeps the step cheap)."""
        assert self.material_field is not None
        index = self.model.particle_index
        if not self.decoupled:
            return self.material_field(means, t, index)[0]
        dynamic = self.model.buffers["is_dynamic"]
        v = means.new_zeros(means.shape)
        if bool(dynamic.any()):
            v = v.index_put((dynamic.nonzero().squeeze(1),), self.material_field(means[dynamic], t, index[dynamic])[0])
        return v

    def _flow_features(self, frame: Frame, state_t: tuple[Tensor, Tensor, Tensor], state_t1: tuple[Tensor, Tensor, Tensor], dt: float) -> Tensor:
        """Gaussian-flow and velocity-flow channels [N, 8] ([N, 6] without a material field) for the render of
        ``frame`` (both times in its camera)."""
        means, quats, log_scales = state_t
        means1, quats1, log_scales1 = state_t1
        # per physics time unit: x + v * dt * time_scale at t+1; without a material field, Gaussian flow only
        v = self.velocities(means, frame.time) if self.material_field is not None else None
        return gaussian_flow_features(
            frame.camera, means, quats, log_scales.exp(), self.model.opacities, means1, quats1, log_scales1.exp(), v,
            dt * self.physics_time_scale,
        )

    def flow_target(self, pair: FlowPair, state_t1: tuple[Tensor, Tensor, Tensor], max_age: int = 1) -> FlowTarget:
        """flow_gt of a pair: the decomposition needs frame t+1's depth: the dataset's depth map when it has one,
        otherwise the model's own (a no-grad render at t+1 in camera t+1, detached). That rendered depth is reused
        while younger than ``max_age`` steps (``flow.target_refresh_steps`` during training) and goes into
        checkpoints, so a resumed run builds the same targets as an uninterrupted one."""
        key = pair.frame0.name
        cached = self._flow_targets.get(key)
        if cached is not None and self.step - cached.step < max_age:
            if cached.target is None:  # restored from a checkpoint: rebuild from the saved depth
                cached.target = flow_target_for_pair(pair, cached.depth if cached.depth is not None else pair.frame1.depth, self.config.flow)
            return cached.target
        depth = None
        if pair.frame1.depth is None:
            with torch.no_grad():
                depth = depth_from_render(self._rasterize(*(x.detach() for x in state_t1), pair.frame1))
        target = flow_target_for_pair(pair, depth if depth is not None else pair.frame1.depth, self.config.flow)
        self._flow_targets[key] = _CachedTarget(self.step, depth, target)
        return target

    def _lpfm(self, pair: FlowPair, state_t1: tuple[Tensor, Tensor, Tensor], out: RenderOutput, max_age: int = 1) -> LPFMResult:
        """L_LPFM of a render (with flow feature channels) against the pair's motion-flow target."""
        target = self.flow_target(pair, state_t1, max_age)
        flow_g, flow_v, _ = decode_flows(out.features, out.alpha)
        return lpfm_loss(flow_g, flow_v, target, out.alpha, self.config.flow)

    # ---- one step ---------------------------------------------------------------------------------------
    def train_step(self) -> dict[str, float]:
        cfg = self.config
        timer = self.timer
        frame = self.next_frame()
        self.model.update_sh_degree(self.step)
        with timer.phase("deformation"):
            means, quats, log_scales = self.gaussians_at(frame.time)
        pair = self.flow_cache.pair_starting_at(frame) if self.flow_cache is not None and cfg.flow.active(self.step) else None
        flow_features = None
        if pair is not None:
            with timer.phase("flow"):
                next_state = self.gaussians_at(pair.frame1.time)
                flow_features = self._flow_features(frame, (means, quats, log_scales), next_state, pair.dt)
        with timer.phase("render"):
            out = self._rasterize(means, quats, log_scales, frame, features=flow_features)
        with timer.phase("loss"):
            gt = frame.image
            loss, parts = photometric_loss(out.rgb, gt, cfg.optim.lambda_dssim)
            if self.deformation_active():
                reg = self.deformation.regularization_loss()
                if reg is not None:
                    loss = loss + reg
                    parts["deform_reg"] = float(reg.detach())
        if cfg.physics.active(self.step) and self.material_field is not None:
            with timer.phase("physics"):
                cmr = cmr_loss(
                    self.material_field, means, frame.time, self.model.particle_index, cfg.physics, self.physics_generator,
                    time_scale=self.physics_time_scale,
                )
                loss = loss + cfg.physics.lambda_cmr * cmr.loss
                parts["cmr"] = float(cmr.loss.detach())
                parts.update({f"cmr_{k}": float(v) for k, v in cmr.stats.items()})
        if pair is not None:
            with timer.phase("flow"):
                lpfm = self._lpfm(pair, next_state, out, max_age=cfg.flow.target_refresh_steps)
                loss = loss + cfg.flow.lambda_lpfm * lpfm.loss
                parts.update({k if k == "lpfm" else f"lpfm_{k}": v for k, v in lpfm.scalars().items()})
        if not torch.isfinite(loss):
            raise FloatingPointError(f"training diverged at step {self.step}: loss is {float(loss)} ({parts})")
        self.strategy.step_pre_backward(out)
        with timer.phase("backward"):
            loss.backward()
        with timer.phase("optimizer"):
            self._optimizer_step()
        with timer.phase("densification"):
            report = self.strategy.step_post_backward(self.step, out, frame.width, frame.height)
            if (not self.decoupled) and self.step + 1 >= cfg.densify.stop and any(f.mask is not None for f in self.scene.train):
                self.decouple_static_dynamic()
        timer.steps += 1
        parts.update(loss=float(loss.detach()), psnr=float(psnr(out.rgb.detach().clamp(0, 1), gt)), gaussians=self.model.num_gaussians)
        if report is not None:
            parts["densified"] = 1.0
        self.step += 1
        return parts

    def _optimizer_step(self) -> None:
        cfg = self.config
        set_lr(self.gaussian_optimizers["means"], means_lr_at(self.step, cfg.gaussian_optim, self.extent, cfg.optim.iterations))
        for opt in self.gaussian_optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        decay = 0.1 ** (self.step / max(cfg.optim.deformation_lr_decay_every or cfg.optim.iterations, 1))  # networks and fields alike
        if self.deformation_optimizer is not None and self.deformation_active():
            for group in self.deformation_optimizer.param_groups:
                group["lr"] = group["base_lr"] * decay
            self.deformation_optimizer.step()
        if self.deformation_optimizer is not None:
            self.deformation_optimizer.zero_grad(set_to_none=True)
        for opt in self.material_optimizers.values():
            for group in opt.param_groups:
                group["lr"] = group["base_lr"] * decay
            opt.step()
            opt.zero_grad(set_to_none=True)

    @torch.no_grad()
    def flow_end_point_errors(self) -> dict[str, float]:
        """Mean end-point error (pixels) of the rendered Gaussian flow and velocity flow against flow_gt over all
        consecutive training pairs (supervised pixels only). Works for every variant: the flow cache is built if
        the run had none, and the velocity flow needs the material field (absent in the no-physics, no-flow run)."""
        cache = self.flow_cache if self.flow_cache is not None else self._load_flow_cache()
        sums: dict[str, float] = defaultdict(float)
        pixels = 0
        for k in range(len(cache)):
            pair = cache.pair(k)
            state_t, state_t1 = self.gaussians_at(pair.frame0.time), self.gaussians_at(pair.frame1.time)
            features = self._flow_features(pair.frame0, state_t, state_t1, pair.dt)
            out = self._rasterize(*state_t, pair.frame0, features=features)
            result = self._lpfm(pair, state_t1, out)
            n = result.valid_pixels
            pixels += n
            sums["gaussian_flow_epe"] += result.epe_gaussian * n
            if result.epe_velocity is not None:
                sums["velocity_flow_epe"] += result.epe_velocity * n
            sums["target_flow_px"] += result.mean_target_px * n
        return {k: v / max(pixels, 1) for k, v in sums.items()} | {"flow_supervised_pixels": float(pixels)}

    # ---- static / dynamic decoupling --------------------------------------------------------------------
    @torch.no_grad()
    def decouple_static_dynamic(self) -> None:
        """Mark each Gaussian dynamic if its centre lands in the motion mask in > vote of the views that see it."""
        inside = torch.zeros(self.model.num_gaussians)
        seen = torch.zeros(self.model.num_gaussians)
        for frame in self.scene.train:
            if frame.mask is None:
                continue
            means, _, _ = self.gaussians_at(frame.time)
            cam = frame.camera
            uv, z = cam.project_points(means)
            u, v = uv.unbind(-1)
            ok = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            ui, vi = u[ok].long(), v[ok].long()
            seen[ok] += 1
            inside[ok] += frame.mask[vi, ui].float()
        dynamic = inside > self.config.optim.dynamic_vote * seen.clamp_min(1)
        self.model.buffers["is_dynamic"] = dynamic
        self.decoupled = True
        logger.info("static/dynamic decoupling at step %d: %d dynamic, %d static Gaussians", self.step, int(dynamic.sum()), int((~dynamic).sum()))

    # ---- loop -------------------------------------------------------------------------------------------
    def train(self, iterations: int | None = None) -> dict:
        """Train to ``iterations`` (default: the config's), checkpointing on schedule, at the end and on budget."""
        cfg = self.config
        out_dir = Path(cfg.output.dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out_dir / "config.json")
        total = iterations if iterations is not None else cfg.optim.iterations
        writer = _tensorboard(out_dir / "tensorboard")
        from tqdm import tqdm

        bar = tqdm(total=total, initial=self.step, desc="training", disable=not cfg.output.progress, dynamic_ncols=True)
        budget = None if cfg.optim.time_budget_minutes is None else 60.0 * cfg.optim.time_budget_minutes
        stopped_by_budget = False
        try:
            while self.step < total:
                t0 = time.perf_counter()
                parts = self.train_step()
                self.train_seconds += time.perf_counter() - t0
                if self.step % cfg.output.log_every == 0 or self.step == total:
                    self.history.append({"step": self.step, **parts})
                    bar.set_postfix(loss=f"{parts['loss']:.4f}", psnr=f"{parts['psnr']:.2f}", n=parts["gaussians"])
                    if writer is not None:
                        for key, value in parts.items():
                            writer.add_scalar(f"train/{key}", value, self.step)
                        writer.add_scalar("train/iterations_per_second", self.timer.steps / max(self.train_seconds, 1e-9), self.step)
                if writer is not None and cfg.output.preview_every and self.step % cfg.output.preview_every == 0:
                    self._preview(writer)
                if cfg.output.checkpoint_every and self.step % cfg.output.checkpoint_every == 0:
                    self.save_checkpoint(out_dir / "checkpoint.pt")
                bar.update(1)
                if budget is not None and self.train_seconds >= budget:
                    stopped_by_budget = True
                    break
        finally:
            bar.close()
            self.save_checkpoint(out_dir / "checkpoint.pt")
            if writer is not None:
                writer.close()
        summary = self.summary(stopped_by_budget)
        (out_dir / "train_summary.json").write_text(json.dumps(summary, indent=2))
        return summary

    def summary(self, stopped_by_budget: bool = False) -> dict:
        return {
            "iterations": self.step,
            "train_minutes": self.train_seconds / 60.0,
            "iterations_per_second": self.timer.steps / max(self.train_seconds, 1e-9),
            "gaussians": self.model.num_gaussians,
            "dynamic_gaussians": int(self.model.buffers["is_dynamic"].sum()),
            "stopped_by_time_budget": stopped_by_budget,
            "step_breakdown_ms": self.timer.breakdown_ms(),
            "last": self.history[-1] if self.history else {},
            **self._loss_trace("cmr"),
        }

    def _loss_trace(self, key: str) -> dict:
        """``{key}_final`` (mean of the last 10 % of the logged values) and ``{key}_history`` [(step, value)]."""
        trace = [(h["step"], h[key]) for h in self.history if key in h]
        if not trace:
            return {}
        tail = trace[-max(1, len(trace) // 10):]
        return {f"{key}_final": sum(v for _, v in tail) / len(tail), f"{key}_history": trace}

    @torch.no_grad()
    def _preview(self, writer) -> None:
        frame = self.scene.train[0]
        out = self.render(frame)
        image = torch.cat([out.rgb.clamp(0, 1), frame.image], dim=1)
        writer.add_image("preview/render_vs_gt", image, self.step, dataformats="HWC")

    # ---- checkpoints ------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "format": "pidg-checkpoint-1",
            "config": to_jsonable(self.config),
            "step": self.step,
            "decoupled": self.decoupled,
            "train_seconds": self.train_seconds,
            "model": self.model.state_dict(),
            "deformation": self.deformation.state_dict(),
            "gaussian_optimizers": {k: v.state_dict() for k, v in self.gaussian_optimizers.items()},
            "deformation_optimizer": None if self.deformation_optimizer is None else self.deformation_optimizer.state_dict(),
            "material_field": None if self.material_field is None else self.material_field.state_dict(),
            "material_optimizers": {k: v.state_dict() for k, v in self.material_optimizers.items()},
            "physics_generator": self.physics_generator.get_state(),
            # the rendered depths behind cached flow targets (the targets are rebuilt from them on resume)
            "flow_depths": {k: (c.step, c.depth) for k, c in self._flow_targets.items()},
            "strategy": self.strategy.state_dict(),
            "random": random_states(),
            "frame_generator": self.frame_generator.get_state(),
            "frame_order": list(self._order),
            "history": self.history,
            "timer": {"totals": dict(self.timer.totals), "steps": self.timer.steps},
        }

    def save_checkpoint(self, path: Path) -> Path:
        return atomic_torch_save(self.state_dict(), path)

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.deformation.load_state_dict(state["deformation"])
        for name, opt in self.gaussian_optimizers.items():
            opt.load_state_dict(state["gaussian_optimizers"][name])
        if self.deformation_optimizer is not None and state["deformation_optimizer"] is not None:
            self.deformation_optimizer.load_state_dict(state["deformation_optimizer"])
        if self.material_field is not None:
            if state.get("material_field") is None:
                raise RuntimeError("checkpoint has no material field, but this config needs one (physics or flow is on)")
            self.material_field.load_state_dict(state["material_field"])
            for name, opt in self.material_optimizers.items():
                opt.load_state_dict(state["material_optimizers"][name])
        if "physics_generator" in state:
            self.physics_generator.set_state(state["physics_generator"])
        self._flow_targets = {k: _CachedTarget(step, depth, None) for k, (step, depth) in state.get("flow_depths", {}).items()}
        self.strategy.load_state_dict(state["strategy"])
        restore_random_states(state["random"])
        self.frame_generator.set_state(state["frame_generator"])
        self._order = list(state["frame_order"])
        self.step = int(state["step"])
        self.decoupled = bool(state["decoupled"])
        self.train_seconds = float(state["train_seconds"])
        self.history = list(state["history"])
        self.timer.totals = defaultdict(float, state["timer"]["totals"])
        self.timer.steps = int(state["timer"]["steps"])

    @classmethod
    def from_checkpoint(cls, path: Path, scene: SceneData, config: TrainConfig | None = None) -> "Trainer":
        """Rebuild a trainer from a checkpoint (its own config unless one is given) and restore every state."""
        from pidg.config_tools import from_jsonable

        state = load_checkpoint(path)
        if state.get("format") != "pidg-checkpoint-1":
            raise RuntimeError(f"{path}: not a pidg training checkpoint")
        config = config or from_jsonable(TrainConfig, state["config"])
        trainer = cls(config, scene)
        trainer.load_gaussians(state["model"])
        trainer.load_state_dict(state)
        return trainer

    def load_gaussians(self, model_state: dict) -> None:
        """Take another model's Gaussians (densification changes their number): resize the model, and rebuild its
        optimizers (fresh moments) and the densification strategy to match."""
        self.model.load_state_dict(model_state)
        self.gaussian_optimizers = make_gaussian_optimizers(self.model, self.config.gaussian_optim, self.extent)
        self.strategy = DensificationStrategy(self.model, self.gaussian_optimizers, self.extent, self.config.densify)


def _tensorboard(log_dir: Path):
    """A SummaryWriter, or None (with a message) when the tensorboard package is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # pragma: no cover - depends on the install
        logger.warning("tensorboard is not installed: no TensorBoard logs (pip install tensorboard)")
        return None
    return SummaryWriter(log_dir=str(log_dir))

