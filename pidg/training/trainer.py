"""The training loop: a thin, generic driver around the scene model, its loss terms, optimizers and hooks.

One step: pick a training frame (a seeded permutation per epoch) -> the model's Gaussians at its time -> render
(with any feature channels the loss terms ask for) -> sum of the active loss terms -> backward -> every optimizer
steps on its schedule -> densification strategy -> static/dynamic decoupling. Every piece of state (the model,
optimizer moments, densification statistics, loss-term state, random generators, the frame order) goes into atomic
checkpoints, so an interrupted run resumes to the same result.
"""
from __future__ import annotations

import json
import logging
import signal
import threading
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

import torch
from torch import Tensor
from tqdm import tqdm

from pidg._env import retain_freed_memory
from pidg.checkpoint import (
    CHECKPOINT_FILE,
    CONFIG_FILE,
    FAILED_CHECKPOINT_FILE,
    atomic_torch_save,
    load_checkpoint,
    random_states,
    remove_stale_temporaries,
    restore_random_states,
    seed_everything,
)
from pidg.config_tools import from_jsonable, save_config, to_jsonable
from pidg.data.scene import Frame, SceneData
from pidg.device import describe, peak_memory_mb, rasterizer_for, resolve_device, synchronize
from pidg.errors import NonFiniteError, TrainingFailed
from pidg.flow import FlowCache, check_flow_viewpoints, open_flow_cache
from pidg.metrics import psnr
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.parallel_linear import matmul_threads
from pidg.render import composite
from pidg.training.config import TrainConfig, describe_schedule
from pidg.training.decoupling import StaticDynamicDecoupling
from pidg.training.densification import DensificationStrategy
from pidg.training.losses import LossTerm, StepInputs, build_loss_terms, ssim_kernel
from pidg.training.motion_start import TrackTargets, start_from_rigid_tracks
from pidg.training.optim import make_optimizers, reschedule
from pidg.training.run_folder import with_absolute_data_path

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "pidg-checkpoint-2"
STEP_PHASES = ("deformation", "physics", "flow_target", "flow", "render", "loss", "backward", "optimizer", "densification")
#: A budget-fitted schedule measures the step time over this many steps (at most a tenth of what is left)
FIT_WINDOW_STEPS = 200
#: ... and plans to use this share of the budget, so that the machine's noise does not end the run at the hard stop
FIT_BUDGET_SHARE = 0.98
#: The fit is made once more this share of the way from the fit to the run's end, with the step time measured since: a
#: machine whose speed drifted (a shared CPU's load, a hotter chip) would otherwise end the run at the budget's hard
#: stop before its learning rates decayed, or leave minutes of the budget unused
REFIT_AT = 2 / 3


@dataclass
class StepTimer:
    """Wall time per phase of a training step. CPU work is synchronous, so perf_counter is exact there; on CUDA each
    phase waits for its GPU work (``sync``), which costs a little speed for a true breakdown."""

    totals: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    steps: int = 0
    sync: torch.device | None = None  # the CUDA device to synchronise at phase boundaries

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if self.sync is not None:
            synchronize(self.sync)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.sync is not None:
                synchronize(self.sync)
            self.totals[name] += time.perf_counter() - t0

    def breakdown_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self.steps, 1) for k, v in self.totals.items()}


class Trainer:
    """Trains one scene. ``Trainer(config, scene).train()``; ``Trainer.from_checkpoint(path, scene)`` continues a
    run. ``model`` is the scene model being trained (a :class:`DynamicGaussians`); pass one to start from it."""

    def __init__(self, config: TrainConfig, scene: SceneData, model: DynamicGaussians | None = None) -> None:
        self.config = with_absolute_data_path(config)
        self.device = resolve_device(config.device)
        rasterizer = rasterizer_for(config.backend, self.device)  # before any work: a missing gsplat fails now
        retain_freed_memory()  # a step's large temporaries would otherwise be re-faulted from the OS every step
        seed_everything(config.optim.seed)
        self.extent = float(scene.bounds.extent)
        if config.optim.lambda_tracks > 0 and config.optim.motion_start != "rigid_tracks":
            raise ValueError(f"--optim.lambda_tracks {config.optim.lambda_tracks} holds the deformation to the tracks the "
                             "motion start fits: it needs --optim.motion_start rigid_tracks")
        for option, weight in (("--optim.lambda_depth", config.optim.lambda_depth),
                               ("--flow.lambda_depth_change", config.flow.lambda_depth_change if config.flow.enabled else 0.0)):
            if weight > 0 and not any(f.depth is not None for f in scene.train):
                raise ValueError(f"{option} {weight}: {scene.root} has no depth maps for its training frames "
                                 "(depth/<frame file name>.npy)")
        self.model = model or DynamicGaussians.from_scene(
            scene, config.gaussians, config.deformation, config.material if config.needs_material_field else None,
            config.physics.time_scale,
        )
        self.model.to(self.device)
        self.model.backend = config.backend
        self.scene = scene.to(self.device)  # images stay uint8 on the device
        self.optimizers = make_optimizers(self.model, config, self.extent)
        self.flow_cache: FlowCache | None = None
        if config.flow.enabled:
            check_flow_viewpoints(self.scene, config.flow)
            self.flow_cache = open_flow_cache(self.scene, config.flow, Path(config.output.dir) / "flow_cache", config.output.progress)
        tracks = None
        if config.optim.motion_start == "rigid_tracks" and model is None:  # a new run (a resumed one has its field)
            tracks = self._start_from_rigid_tracks()
        self.loss_terms: list[LossTerm] = build_loss_terms(config, self.flow_cache, tracks)
        self.strategy = DensificationStrategy(config.densify, self.extent)
        self.densify_state = self.strategy.initialize_state(self.model.num_gaussians, self.model.device)
        self.decoupling = StaticDynamicDecoupling(
            config.densify.stop, config.optim.dynamic_vote, config.optim.motion_split_px,
            motion_at_step=config.densify.stop + config.optim.static_warmup,
        )
        self.frame_generator = torch.Generator().manual_seed(config.optim.seed)
        self._order: list[int] = []
        self.step = 0
        self.train_seconds = 0.0
        self.clock = time.perf_counter  # what train_seconds is measured with (a test can drive it)
        self.schedule_fit: dict | None = None  # how the run was fitted to its time budget ("fit", "fill"), and refitted
        self._fit_mark: tuple[int, float] | None = None  # (step, train_seconds) where the fit's step timing began
        self.rollbacks = 0  # times a non-finite step sent the run back to its last good checkpoint
        self.lr_scale = 1.0  # every learning rate times this (rollback_lr_factor per rollback)
        self.last_good_step: int | None = None  # the step of the last checkpoint this trainer wrote or resumed from
        self.timer = StepTimer(sync=self.device if self.device.type == "cuda" else None)
        self.history: list[dict[str, float]] = []
        hash_grids = getattr(self.model.deformation.config, "backend", None)
        if hash_grids == "auto":
            hash_grids = "numba kernel" if self.device.type == "cpu" else "torch"
        self.hardware = {
            "device": describe(self.device), "rasterizer": rasterizer, "hash_grids": hash_grids or "-",
            "ssim": "numba kernel" if ssim_kernel(config.backend, self.device) else "torch",
        }
        logger.info("training on %s", ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in self.hardware.items()))
        logger.info(describe_schedule(config))

    # ---- data -------------------------------------------------------------------------------------------
    def next_frame(self) -> Frame:
        """Training frames in a fresh random order each epoch, from a generator saved in checkpoints; during a time
        curriculum an epoch holds the frames inside the window of the step that starts it."""
        if not self._order:
            order = torch.randperm(len(self.scene.train), generator=self.frame_generator).tolist()
            end = self.time_window_end()
            self._order = order if end is None else [i for i in order if self.scene.train[i].time <= end]
        return self.scene.train[self._order.pop()]

    def time_window_end(self) -> float | None:
        """The latest dataset time the time curriculum lets this step train on (None: no limit, the curriculum is off
        or over); the window holds at least the first training time."""
        steps, start = self.config.optim.time_curriculum_steps, self.config.optim.time_curriculum_start
        if self.step >= steps:
            return None
        times = [frame.time for frame in self.scene.train]
        first, last = min(times), max(times)
        return first + (start + (1.0 - start) * self.step / steps) * (last - first)

    # ---- one step ---------------------------------------------------------------------------------------
    def deformation_active(self) -> bool:
        return self.step >= self.config.optim.static_warmup

    def gaussian_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """The optimizers of the Gaussians' parameters (what densification edits), by parameter name."""
        return {name: self.optimizers[name].optimizer for name in self.model.gaussians.params if name in self.optimizers}

    def train_step(self, log: bool = True) -> dict[str, float]:
        """One optimisation step; returns the loss, its terms and the number of Gaussians, and with ``log`` also the
        training PSNR (an extra pass over the image, so the loop asks for it on the steps it logs only)."""
        model, timer, step = self.model, self.timer, self.step
        frame = self.next_frame()
        model.gaussians.update_sh_degree(step)
        deforming = self.deformation_active()
        with timer.phase("deformation"):
            state = model.at(frame.time, regularize=True) if deforming else model.canonical()
        with timer.phase("render"):  # projected first: a term asks it which Gaussians reach its pixels
            screen = model.prepare_render(state, frame.camera)
        inputs = StepInputs(step, frame, model, state, deforming, screen)
        terms = [term for term in self.loss_terms if term.active(step)]
        slices, channels, pixels = self._render_features(terms, inputs)
        with timer.phase("render"):
            out = composite(screen, channels, feature_pixels=pixels)
        loss: Tensor | None = None
        parts: dict[str, float] = {}
        features = _split_features(out.features, slices)
        for term in terms:
            with timer.phase(term.phase):
                term.observe(inputs, out)
                value, scalars = term.loss(inputs, out, features.get(term.name))
                loss = value if loss is None else loss + value
                parts.update(scalars)
        assert loss is not None  # the photometric term is always active
        if not torch.isfinite(loss):
            raise NonFiniteError(f"the loss is {float(loss.detach())} at step {step} ({parts})")
        self.strategy.step_pre_backward(out)
        with timer.phase("backward"):
            loss.backward()
        with timer.phase("optimizer"):
            for optimizer in self.optimizers.values():
                optimizer.step(step, self.lr_scale)
        try:
            self._check_update(step)
        finally:
            for optimizer in self.optimizers.values():
                optimizer.zero_grad()
        with timer.phase("densification"):
            report = self.strategy.step_post_backward(
                model.gaussians, self.gaussian_optimizers(), self.densify_state, step, out, frame.width, frame.height
            )
            self.decoupling.step_post_backward(model, self.scene.train, step)
        timer.steps += 1
        parts.update(loss=float(loss.detach()), gaussians=model.num_gaussians)
        if log:
            parts["psnr"] = float(psnr(out.rgb.detach().clamp(0, 1), frame.image))
        if report is not None:
            parts["densified"] = 1.0
        self.step += 1
        return parts

    def _check_update(self, step: int) -> None:
        """Raise NonFiniteError if the step left a parameter non-finite, naming the gradients when they were the
        cause. Adam's update is elementwise, so a NaN or infinite gradient makes its parameter's entries non-finite
        too: one pass over the parameters finds both, and the gradients (still there) are read only then (a pass
        over every gradient cost 1-1.7 ms a step at 18k Gaussians)."""
        named = self._named_parameters()
        try:
            _check_finite("parameters after the optimizer step", named, step)
        except NonFiniteError:
            _check_finite("gradients", named, step, grads=True)
            raise

    def _named_parameters(self) -> list[tuple[str, Tensor]]:
        """Every optimised tensor with a name for messages."""
        model = self.model
        named = [(f"gaussians.{k}", p) for k, p in model.gaussians.params.items()]
        named += [(f"deformation.{k}", p) for k, p in model.deformation.named_parameters()]
        if model.material_field is not None:
            named += [(f"material_field.{k}", p) for k, p in model.material_field.named_parameters()]
        return named

    def _render_features(self, terms: list[LossTerm], inputs: StepInputs) -> tuple[dict[str, slice], Tensor | None, Tensor | None]:
        """The extra channels [N, C] the active terms want in this step's render (None: none), which columns are
        whose, and the pixels [H, W] where any of them reads its channels (None: anywhere); each term's ``prepare``
        (its cached work, e.g. the flow target) runs first, timed as its own phase."""
        slices: dict[str, slice] = {}
        channels: list[Tensor] = []
        masks: list[Tensor | None] = []
        start = 0
        for term in terms:
            if type(term).prepare is not LossTerm.prepare:
                with self.timer.phase(f"{term.phase}_target"):
                    term.prepare(inputs)
            if type(term).render_features is LossTerm.render_features:  # asks for nothing
                continue
            with self.timer.phase(term.phase):
                features = term.render_features(inputs)
            if features is not None:
                slices[term.name] = slice(start, start + features.shape[-1])
                start += features.shape[-1]
                channels.append(features)
                masks.append(term.feature_pixels())
        if not channels:
            return slices, None, None
        pixels = None if any(m is None for m in masks) else torch.stack(masks).any(dim=0)  # type: ignore[arg-type]
        return slices, torch.cat(channels, dim=-1), pixels

    # ---- loop -------------------------------------------------------------------------------------------
    def train(self, iterations: int | None = None) -> dict:
        """Train to ``iterations`` (default: the config's), checkpointing on schedule, at the end, on budget and on
        a first Ctrl-C (after the step in progress).

        A failure never writes over the last good checkpoint: a step with a non-finite loss, gradient or parameter
        rolls back to it with smaller learning rates (``OptimConfig.max_rollbacks`` times at most); any other error,
        or a second Ctrl-C, stops training and writes the state it stopped in to ``checkpoint.failed.pt`` beside it.
        The run folder is written before the first step (config, a rollback point), so an unwritable folder fails
        at once rather than after the training."""
        cfg = self.config
        out_dir = Path(cfg.output.dir)
        checkpoint = out_dir / CHECKPOINT_FILE
        out_dir.mkdir(parents=True, exist_ok=True)
        for stale in remove_stale_temporaries(out_dir):
            logger.info("removed %s, left by an interrupted save", stale)
        save_config(cfg, out_dir / CONFIG_FILE)
        if self.last_good_step is None:  # a rollback point of this run's own
            self.save_checkpoint(checkpoint)
        total = iterations if iterations is not None else cfg.optim.iterations
        writer = _tensorboard(out_dir / "tensorboard")
        bar = tqdm(total=total, initial=self.step, desc="training", disable=not cfg.output.progress, dynamic_ncols=True)
        budget = None if cfg.optim.time_budget_minutes is None else 60.0 * cfg.optim.time_budget_minutes
        fitting = iterations is None and budget is not None and cfg.optim.time_budget_policy in ("fit", "fill")
        stopped_by = None
        torch_threads, flushed = torch.get_num_threads(), denormals_flushed()
        on_cpu_threads = self.device.type == "cpu" and bool(cfg.cpu_torch_threads)  # torch's own ops on that many threads
        products_threads = (cfg.cpu_matmul_threads or torch_threads) if on_cpu_threads else None
        if cfg.flush_denormals:
            torch.set_flush_denormal(True)
        try:
            with _GracefulInterrupt() as interrupt, matmul_threads(products_threads):
                while self.step < total:
                    t0 = self.clock()
                    if on_cpu_threads:
                        # every step: numba's thread pool, started by the first kernel, resets OpenMP's count
                        torch.set_num_threads(cfg.cpu_torch_threads)
                    try:
                        logs = self._logs(self.step + 1, total)
                        parts = self.train_step(log=logs)
                    except NonFiniteError as err:
                        self._roll_back(checkpoint, err)
                        if iterations is None:  # the run's length as restored with that checkpoint
                            total = self.config.optim.iterations
                        bar.reset(total=total)
                        bar.update(self.step)
                        continue
                    self.train_seconds += self.clock() - t0
                    if fitting and (self._fit_to_budget(budget, out_dir) if self.schedule_fit is None
                                    else self._refit_to_budget(budget, out_dir)):
                        total = self.config.optim.iterations
                        bar.total = total
                    # (decided before the step: a budget fit shortens the run to a later step than this one, so the
                    # decision stands, and the step computed the PSNR the log shows)
                    if logs:
                        self.history.append({"step": self.step, **parts})
                        bar.set_postfix(loss=f"{parts['loss']:.4f}", psnr=f"{parts['psnr']:.2f}", n=parts["gaussians"])
                        if writer is not None:
                            for key, value in parts.items():
                                writer.add_scalar(f"train/{key}", value, self.step)
                            writer.add_scalar("train/iterations_per_second", self.timer.steps / max(self.train_seconds, 1e-9), self.step)
                    if writer is not None and cfg.output.preview_every and self.step % cfg.output.preview_every == 0:
                        self._preview(writer)
                    if cfg.output.checkpoint_every and self.step % cfg.output.checkpoint_every == 0:
                        self.save_checkpoint(checkpoint)
                    bar.update(1)
                    if budget is not None and self.train_seconds >= budget:
                        stopped_by = "time_budget"
                        break
                    if interrupt.requested:
                        stopped_by = "interrupt"
                        break
        except KeyboardInterrupt:  # a second Ctrl-C: the step in progress may be half done
            self._save_failed_state(out_dir)
            raise
        except Exception as err:
            failed = self._save_failed_state(out_dir)
            if isinstance(err, TrainingFailed):
                raise
            raise TrainingFailed(
                f"training failed at step {self.step} ({type(err).__name__}: {err}); the last good checkpoint is "
                f"{checkpoint} (step {self.last_good_step}), the state it failed in {failed}"
            ) from err
        finally:
            torch.set_num_threads(torch_threads)
            torch.set_flush_denormal(flushed)
            bar.close()
            if writer is not None:
                writer.close()
        self.save_checkpoint(checkpoint)
        summary = self.summary(stopped_by)
        (out_dir / "train_summary.json").write_text(json.dumps(summary, indent=2))
        return summary

    def _logs(self, step: int, total: int) -> bool:
        """Whether the loop logs the state after ``step`` steps (every ``log_every`` and the last)."""
        return step % self.config.output.log_every == 0 or step == total

    def fit_start(self) -> int:
        """The step from which a budget-fitted run times its steps: after densification and the static/dynamic split,
        when the number of Gaussians (and so the step time) has settled; at a tenth of the run without them."""
        o, d = self.config.optim, self.config.densify
        settled = d.stop + o.static_warmup + 1
        return max(settled if settled < 0.9 * o.iterations else 0, o.iterations // 10)

    def _fit_to_budget(self, budget_seconds: float, out_dir: Path) -> bool:
        """Time the steps from ``fit_start()`` over ``FIT_WINDOW_STEPS``, then set the run's length so that it ends
        inside the budget, with every learning-rate schedule over the new length: policy "fit" only shortens it,
        "fill" also lengthens it, up to ``time_budget_max_stretch`` times the planned steps. True when the run's
        length was decided at this step (``self.schedule_fit`` records how), changed or not."""
        o = self.config.optim
        start = self.fit_start()
        if self.step < start:
            return False
        if self._fit_mark is None:
            self._fit_mark = (self.step, self.train_seconds)
            return False
        mark_step, mark_seconds = self._fit_mark
        if self.step - mark_step < max(1, min(FIT_WINDOW_STEPS, (o.iterations - start) // 10)):
            return False
        per_step = (self.train_seconds - mark_seconds) / (self.step - mark_step)
        iterations = self._affordable_iterations(per_step, budget_seconds, o.iterations)
        self.schedule_fit = {
            "step": self.step, "seconds_per_step": per_step, "budget_minutes": budget_seconds / 60.0,
            "iterations_planned": o.iterations, "iterations": iterations,
            "train_seconds": self.train_seconds, "refit": None,
        }
        self._set_iterations(iterations, out_dir, f"{per_step:.3f} s a step over steps {mark_step}-{self.step}",
                             budget_seconds)
        return True

    def _refit_to_budget(self, budget_seconds: float, out_dir: Path) -> bool:
        """``REFIT_AT`` of the way from the fit to the run's end, the fit once more with the step time measured since
        (a checkpoint written before refits has no record of that time and is not refitted). True when the length was
        decided again at this step."""
        fit = self.schedule_fit
        if "train_seconds" not in fit or fit["refit"] is not None:
            return False
        if self.step < fit["step"] + REFIT_AT * (fit["iterations"] - fit["step"]):
            return False
        per_step = (self.train_seconds - fit["train_seconds"]) / max(self.step - fit["step"], 1)
        iterations = self._affordable_iterations(per_step, budget_seconds, fit["iterations_planned"])
        fit["refit"] = {"step": self.step, "seconds_per_step": per_step, "iterations": iterations}
        self._set_iterations(iterations, out_dir, f"{per_step:.3f} s a step over steps {fit['step']}-{self.step}",
                             budget_seconds)
        return True

    def _affordable_iterations(self, per_step: float, budget_seconds: float, planned: int) -> int:
        """The run's length that ends inside ``FIT_BUDGET_SHARE`` of the budget at ``per_step`` seconds a step: never
        more than the planned steps under policy "fit", ``time_budget_max_stretch`` times them under "fill"."""
        o = self.config.optim
        affordable = int((FIT_BUDGET_SHARE * budget_seconds - self.train_seconds) / max(per_step, 1e-9))
        longest = planned if o.time_budget_policy == "fit" else int(planned * o.time_budget_max_stretch)
        return min(longest, self.step + max(affordable, 1))

    def _set_iterations(self, iterations: int, out_dir: Path, measured: str, budget_seconds: float) -> None:
        """The run's length from now on, with every learning-rate schedule over it (a change mid-decay moves each
        rate by the factor its schedule gives the step's new share of the run), logged and saved in config.json."""
        o = self.config.optim
        if iterations == o.iterations:
            logger.info("step %d: %s; the run's %d steps fit the %g-minute budget", self.step, measured,
                        o.iterations, budget_seconds / 60.0)
            return
        self._set_length(iterations, out_dir)
        logger.info("step %d: %s, so %d steps (not %d) fit the %g-minute budget; the run and its learning-rate "
                    "schedules now end at step %d", self.step, measured, iterations, o.iterations,
                    budget_seconds / 60.0, iterations)

    def _start_from_rigid_tracks(self) -> TrackTargets:
        """``optim.motion_start rigid_tracks``: the deformation fitted to rigid-body tracks before step 0 (returns
        what it was fitted to), or a clear stop naming what the run lacks."""
        option = "--optim.motion_start rigid_tracks"
        if self.flow_cache is None:
            raise ValueError(f"{option} tracks bodies through the optical flow: turn the flow on (--flow lpfm)")
        if not any(p.requires_grad for p in self.model.deformation.parameters()):
            raise ValueError(f"{option}: the deformation ({self.config.deformation.kind}) has nothing to fit")
        try:
            return start_from_rigid_tracks(self.model.deformation, self.flow_cache, self.config)
        except ValueError as err:
            raise ValueError(f"{option}: {err}") from None

    def _set_length(self, iterations: int, out_dir: Path) -> None:
        """The run's length, in the config (and config.json) and in every learning-rate schedule."""
        self.config = replace(self.config, optim=replace(self.config.optim, iterations=iterations))
        reschedule(self.optimizers, self.config, self.extent)
        save_config(self.config, out_dir / CONFIG_FILE)

    def _roll_back(self, checkpoint: Path, err: NonFiniteError) -> None:
        """Back to the last good checkpoint, with the run's length it was written under (its ``schedule_fit`` is
        restored with it, so the budget fit is made again as the run first made it), and every learning rate times
        ``rollback_lr_factor``; a clear stop once ``max_rollbacks`` rollbacks did not get through."""
        cfg = self.config.optim
        failed_step = self.step
        if self.rollbacks >= cfg.max_rollbacks:
            raise TrainingFailed(
                f"training diverged at step {failed_step}: {err}; after {self.rollbacks} rollbacks to the last good "
                f"checkpoint {checkpoint} (step {self.last_good_step}) with learning rates x{self.lr_scale:g}, it still "
                "does: check the options (learning rates, eps) and the data"
            )
        rollbacks, lr_scale = self.rollbacks + 1, self.lr_scale * cfg.rollback_lr_factor
        state = load_checkpoint(checkpoint)
        self.load_state_dict(state)
        self.rollbacks, self.lr_scale = rollbacks, lr_scale
        length = int(state["config"]["optim"]["iterations"])  # a budget fit after the checkpoint is undone with it
        if length != self.config.optim.iterations:
            self._set_length(length, checkpoint.parent)
        logger.warning(
            "step %d: %s; rolled back to step %d (rollback %d of at most %d) with learning rates x%g",
            failed_step, err, self.step, rollbacks, cfg.max_rollbacks, lr_scale,
        )

    def _save_failed_state(self, out_dir: Path) -> Path | None:
        """The state training stopped in, beside (never over) the last good checkpoint; None if even that fails."""
        path = out_dir / FAILED_CHECKPOINT_FILE
        try:
            atomic_torch_save({**self.state_dict(), "format": "pidg-failed-state"}, path)
        except Exception as err:  # noqa: BLE001 - the original failure is what the user needs to see
            logger.error("could not write the failed state to %s: %s", path, err)
            return None
        return path

    def summary(self, stopped_by: str | None = None) -> dict:
        dynamic = self.model.dynamic_mask
        return {
            "iterations": self.step,
            "train_minutes": self.train_seconds / 60.0,
            "iterations_per_second": self.timer.steps / max(self.train_seconds, 1e-9),
            **self.hardware,
            **peak_memory_mb(self.device),
            "gaussians": self.model.num_gaussians,
            "dynamic_gaussians": self.model.num_gaussians if dynamic is None else int(dynamic.sum()),
            "stopped_by_time_budget": stopped_by == "time_budget",
            "stopped_by": stopped_by,  # None (finished), "time_budget" or "interrupt"
            "schedule_fit": self.schedule_fit,  # a budget-fitted run: the step time measured and the length chosen
            "rollbacks": self.rollbacks,
            "lr_scale": self.lr_scale,
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
        out = self.model.render(frame.camera, frame.time)
        image = torch.cat([out.rgb.clamp(0, 1), frame.image], dim=1)
        writer.add_image("preview/render_vs_gt", image.cpu(), self.step, dataformats="HWC")

    # ---- checkpoints ------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": to_jsonable(self.config),
            "step": self.step,
            "train_seconds": self.train_seconds,
            "model": self.model.state_dict(),
            "optimizers": {name: opt.optimizer.state_dict() for name, opt in self.optimizers.items()},
            "densification": self.densify_state.state_dict(),
            "loss_terms": {term.name: term.state_dict() for term in self.loss_terms},
            "random": random_states(),
            "frame_generator": self.frame_generator.get_state(),
            "frame_order": list(self._order),
            "history": self.history,
            "timer": {"totals": dict(self.timer.totals), "steps": self.timer.steps},
            "rollbacks": self.rollbacks,
            "lr_scale": self.lr_scale,
            "schedule_fit": self.schedule_fit,
            "fit_mark": self._fit_mark,
        }

    def save_checkpoint(self, path: Path) -> Path:
        """Write the whole state atomically; it becomes the last good state (what a failure rolls back to)."""
        atomic_torch_save(self.state_dict(), path)
        self.last_good_step = self.step
        return path

    def load_state_dict(self, state: dict) -> None:
        """Restore a checkpoint's state into this trainer: the model, then everything that optimises it."""
        self.load_model_state(state["model"])
        self._load_optimization_state(state)

    def _load_optimization_state(self, state: dict) -> None:
        """Everything of a checkpoint but the model, for a model that already holds the checkpoint's values."""
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state["optimizers"][name])  # moments; this config's learning rates stay
        self.densify_state.load_state_dict(state["densification"])
        for term in self.loss_terms:
            term.load_state_dict(state["loss_terms"][term.name])
        restore_random_states(state["random"])
        self.frame_generator.set_state(state["frame_generator"])
        self._order = list(state["frame_order"])
        self.step = int(state["step"])
        self.train_seconds = float(state["train_seconds"])
        self.history = list(state["history"])
        self.timer.totals = defaultdict(float, state["timer"]["totals"])
        self.timer.steps = int(state["timer"]["steps"])
        self.rollbacks = int(state["rollbacks"])
        self.lr_scale = float(state["lr_scale"])
        self.schedule_fit = state.get("schedule_fit")  # absent from checkpoints written before budget fitting
        mark = state.get("fit_mark")
        self._fit_mark = None if mark is None else (int(mark[0]), float(mark[1]))
        for _, tensor in self._named_parameters():  # no gradient of a step that did not finish survives a rollback
            tensor.grad = None

    def load_model_state(self, model_state: dict) -> None:
        """Take another model's values (densification changes the number of Gaussians); see reset_optimization."""
        self.model.load_state_dict(model_state)
        self.reset_optimization()

    def reset_optimization(self) -> None:
        """Rebuild the optimizers (fresh moments) and restart the densification statistics for the model's current
        Gaussians, after they were replaced."""
        self.optimizers = make_optimizers(self.model, self.config, self.extent)
        self.densify_state = self.strategy.initialize_state(self.model.num_gaussians, self.model.device)

    @classmethod
    def from_checkpoint(cls, path: Path, scene: SceneData, config: TrainConfig | None = None) -> "Trainer":
        """Rebuild a trainer from a checkpoint (its own config unless one is given) and restore every state. The
        model is built from the checkpoint (its sizes), not initialised from the scene."""
        state = load_checkpoint(path)
        if state.get("format") != CHECKPOINT_FORMAT:
            raise RuntimeError(
                f"{path}: not a pidg training checkpoint of this version (format {state.get('format')!r}, "
                f"expected {CHECKPOINT_FORMAT!r}); checkpoints of pidg 0.1 are read by that version only"
            )
        config = config or from_jsonable(TrainConfig, state["config"])
        trainer = cls(config, scene, DynamicGaussians.from_state_dict(state["model"]))  # its optimizers fit the model
        trainer._load_optimization_state(state)
        trainer.last_good_step = trainer.step  # this run's own checkpoint: where a failure rolls back to
        return trainer


def denormals_flushed() -> bool:
    """Whether this thread's float arithmetic flushes denormals to zero (``torch.set_flush_denormal``, which has no
    getter): a one-element product, computed on the calling thread, of the smallest normal float32 and 0.5."""
    tiny = torch.tensor([torch.finfo(torch.float32).tiny])
    return bool((tiny * 0.5).item() == 0.0)


def _split_features(features: Tensor | None, slices: dict[str, slice]) -> dict[str, Tensor]:
    """Each term's columns of the rendered features, by one ``split`` (slicing each out would fill a zero gradient of
    the whole feature image per term in the backward)."""
    if features is None or not slices:
        return {}
    if len(slices) == 1:  # one term's columns are all of them (its split would only copy the gradient back)
        return {next(iter(slices)): features}
    names = sorted(slices, key=lambda name: slices[name].start)
    sizes = [slices[name].stop - slices[name].start for name in names]
    return dict(zip(names, features.split(sizes, dim=-1)))


def _check_finite(what: str, named: list[tuple[str, Tensor]], step: int, grads: bool = False) -> None:
    """Raise NonFiniteError naming the tensors with NaN or infinite values: one fused norm per tensor (measured at
    16k Gaussians on the cpu preset, 3.9M values: 0.7 ms alone, 1.8 ms inside a training step, where the values
    come from memory rather than cache).
    A parameter whose gradient is sparse is read at the gradient's rows only: its sparse optimiser changed no
    other row, and those were finite after the previous step (the material field's [particles, 64] index embedding,
    ~0.4 ms a step read whole, of which a step updates ~15 %)."""
    pairs = [(name, _changed_rows(t, grads)) for name, t in named]
    pairs = [(name, t) for name, t in pairs if t is not None and t.numel()]
    if not pairs:
        return
    norms = torch.stack(torch._foreach_norm([t.detach() for _, t in pairs]))
    if bool(torch.isfinite(norms).all()):
        return
    bad = [name for (name, _), ok in zip(pairs, torch.isfinite(norms).tolist()) if not ok]
    raise NonFiniteError(f"non-finite {what} at step {step} in {', '.join(bad[:6])}" + (" ..." if len(bad) > 6 else ""))


def _changed_rows(param: Tensor, grads: bool) -> Tensor | None:
    """What the finiteness check reads of ``param``: its gradient's values (``grads``), else the parameter, only the
    rows of its gradient when that is sparse (the rows its optimiser updated)."""
    grad = param.grad
    if grads:
        return None if grad is None else (grad._values() if grad.is_sparse else grad)
    if grad is not None and grad.is_sparse:
        return param.detach().index_select(0, grad._indices()[0])
    return param


class _GracefulInterrupt:
    """While active, a first Ctrl-C asks training to stop after the step in progress (with a checkpoint); a second
    one interrupts at once. Only the main thread can take signals: elsewhere it does nothing."""

    def __enter__(self) -> "_GracefulInterrupt":
        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame) -> None:  # noqa: ANN001 - signal handler signature
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        logger.warning("interrupted: stopping after this step with a checkpoint (Ctrl-C again to stop at once)")

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _tensorboard(log_dir: Path):
    """A SummaryWriter, or None (with a message) when the tensorboard package is missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # pragma: no cover - depends on the install
        logger.warning("tensorboard is not installed: no TensorBoard logs (pip install tensorboard)")
        return None
    return SummaryWriter(log_dir=str(log_dir))
