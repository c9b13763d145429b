"""``pidg bench step``: training-step rate and where a step's time goes, for several variants in one run.

The Gaussian count is held fixed (no densification) so variants are compared on equal work, and the variants'
steps are interleaved in chunks so each sees the same machine load (this class of machine is shared and noisy).
"""
from __future__ import annotations

import dataclasses
import json
import statistics
from pathlib import Path
from typing import Callable

import torch

from pidg.bench.provenance import git_commit, machine, machine_line
from pidg.checkpoint import CHECKPOINT_FILE, load_checkpoint
from pidg.config_tools import apply_overrides
from pidg.data import load_scene
from pidg.data.scene import parse_downscale
from pidg.training.config import ABLATION_VARIANTS, TrainConfig
from pidg.training.losses import LossTerm, StepInputs
from pidg.training.run_folder import claim_run_folder
from pidg.training.trainer import STEP_PHASES, Trainer


def run_step_bench(
    scene_path: Path,
    base: TrainConfig,
    variants: list[str],
    downscale: str | None = "400x400",
    gaussians: int = 20_000,
    iterations: int = 60,
    warmup: int = 10,
    chunk: int = 10,
    out: Path | None = None,
    from_run: Path | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, dict]:
    """Train each variant for ``warmup`` steps (compilation, caches), then ``iterations`` timed steps in
    interleaved chunks; report it/s and the per-phase breakdown (ms per step).

    The flow loss's viewpoint check (``FlowConfig.max_view_change``) is off here: the bench times steps, so the full
    method is timed on D-NeRF scenes too, where training refuses it.

    ``from_run``: start every variant from that run's trained Gaussians and deformation (its checkpoint) instead
    of ``gaussians`` freshly initialised ones -- the realistic case: trained Gaussians are smaller and sparser
    than a random initialisation, which overlaps heavily and costs the renderer several times more.
    """
    data = dataclasses.replace(base.data, path=scene_path, progress=False)
    if downscale:
        data = dataclasses.replace(data, downscale=parse_downscale(downscale))
    scene = load_scene(data)
    common = dataclasses.replace(
        base,
        data=data,
        gaussians=dataclasses.replace(base.gaussians, random_init_points=gaussians, max_init_points=gaussians),
        densify=dataclasses.replace(base.densify, start=10**9, stop=10**9),
        # a step's cost, not its quality: the flow loss is timed on any data, D-NeRF's jumping views included
        flow=dataclasses.replace(base.flow, max_view_change=180.0),
    )
    trainers = {}
    for name in variants:
        config = apply_overrides(common, ABLATION_VARIANTS[name])
        config = dataclasses.replace(
            config,
            output=dataclasses.replace(config.output, dir=Path(base.output.dir) / f"bench_step_{name}", checkpoint_every=0, preview_every=0, progress=False),
        )
        claim_run_folder(config.output.dir, overwrite=True)
        trainer = Trainer(config, scene)
        if from_run is not None:
            _load_trained_model(trainer, Path(from_run) / CHECKPOINT_FILE, log)
        _observe_every_frame(trainer)
        trainer.train(trainer.step + warmup)
        trainer.timer.totals.clear()
        trainer.timer.steps = 0
        trainer.train_seconds = 0.0
        trainers[name] = trainer
    round_seconds: dict[str, list[float]] = {name: [] for name in trainers}
    for _ in range(0, iterations, chunk):
        for name, trainer in trainers.items():
            before = trainer.train_seconds
            trainer.train(trainer.step + chunk)
            round_seconds[name].append(trainer.train_seconds - before)
    results = {}
    first = next(iter(trainers))
    for name, trainer in trainers.items():
        summary = trainer.summary()
        results[name] = {
            "iterations_per_second": summary["iterations_per_second"],
            # each round's step time over the first variant's in the same round: the spread says how far one
            # bench's ratio can be trusted on a noisy machine
            "round_ratios": [mine / max(theirs, 1e-12) for mine, theirs in zip(round_seconds[name], round_seconds[first])],
            "gaussians": summary["gaussians"],
            "step_breakdown_ms": summary["step_breakdown_ms"],
            "device": summary["device"],
            "peak_rss_mb": summary["peak_rss_mb"],  # of the process, all variants alive
            "peak_gpu_memory_mb": summary.get("peak_gpu_memory_mb"),
            # at this fixed Gaussian count; a real run's count grows with densification
            "projected_minutes": trainer.config.optim.iterations / max(summary["iterations_per_second"], 1e-9) / 60.0,
            "projected_iterations": trainer.config.optim.iterations,
        }
    here, commit = machine(), git_commit()
    log(format_step_table(results, f"{scene.name} {scene.train[0].width}x{scene.train[0].height}"))
    log(f"  {machine_line(here, commit)}")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"git_commit": commit, "machine": here, "variants": results}, indent=2))
    return results


def _load_trained_model(trainer: Trainer, checkpoint: Path, log: Callable[[str], None] = print) -> None:
    """Replace a fresh trainer's Gaussians and deformation by a checkpoint's, with the run's optimiser moments for
    them: the timed steps then cost what that run's steps cost (fresh moments hide, e.g., the denormal ones a long
    run accumulates, ``TrainConfig.flush_denormals``: 8 against 24 ms of optimiser a step, measured).

    A deformation of another shape (a run trained with other grid or layer sizes) is left freshly initialised, and
    said so: the step then renders the canonical positions, which need not cost what the trained deformed ones do
    (measured: 65 instead of 35 ms of rendering on bouncingballs). Train a state with the same sizes for figures.
    The material field, if the variant has one, stays fresh (the run's may be absent or of another variant).
    """
    state = load_checkpoint(checkpoint)
    saved = state["model"]
    model = trainer.model
    model.gaussians.load_state_dict(saved["gaussians"])
    current = model.deformation.state_dict()
    deformation = saved["deformation"]
    same_deformation = set(deformation) == set(current) and all(deformation[k].shape == current[k].shape for k in current)
    if same_deformation:
        model.deformation.load_state_dict(deformation)
    else:
        log(f"{checkpoint}: its deformation has other sizes than the configured one; timing a fresh (untrained) deformation, not representative")
    if model.material_field is not None and model.material_field.num_particles < model.gaussians.num_particles:
        raise ValueError(f"{checkpoint}: its Gaussians descend from more particles than the fresh material field has rows")
    trainer.reset_optimization()
    moments = state["optimizers"]
    for name, optimizer in trainer.optimizers.items():  # the material field's stay fresh, as the field itself
        if name in moments and (name != "deformation" or same_deformation):
            optimizer.load_state_dict(moments[name])
    trainer.step = int(state["step"])


def _observe_every_frame(trainer: Trainer) -> None:
    """Show the loss terms that keep something from renders a no-grad render of every training frame, as a run past
    its first epoch has shown them: the timed steps then cost what the rest of a run's steps cost (the flow term
    builds its targets from kept depths instead of rendering frame t+1 again). One difference stays, on the
    conservative side: every timed step builds its pair's flow target (no target is cached yet), where a run's
    steps reuse a cached one about half the time (``FlowConfig.target_refresh_steps`` 300 against epochs of ~150
    steps), so the bench's ``flow_target`` phase is about twice a run's (~3 of its ~6 ms at 400x400)."""
    terms = [term for term in trainer.loss_terms if type(term).observe is not LossTerm.observe]
    if not terms:
        return
    model, deforming = trainer.model, trainer.deformation_active()
    with torch.no_grad():
        for frame in trainer.scene.train:
            state = model.at(frame.time) if deforming else model.canonical()
            inputs, out = StepInputs(trainer.step, frame, model, state, deforming), model.render_state(state, frame.camera)
            for term in terms:
                term.observe(inputs, out)


def format_step_table(results: dict[str, dict], title: str) -> str:
    phases = sorted({p for r in results.values() for p in r["step_breakdown_ms"]}, key=_phase_order)
    head = f"{'variant':<10}{'it/s':>7}{'ms/step':>9}{'Gaussians':>10}" + "".join(f"{p[:11]:>12}" for p in phases)
    lines = [f"training step, {title}, interleaved (ms per step by phase):", head]
    for name, r in results.items():
        ms = r["step_breakdown_ms"]
        lines.append(
            f"{name:<10}{r['iterations_per_second']:>7.2f}{1e3 / max(r['iterations_per_second'], 1e-9):>9.1f}{r['gaussians']:>10}"
            + "".join(f"{ms.get(p, 0.0):>12.1f}" for p in phases)
        )
    for name, r in results.items():
        lines.append(f"  {name}: {r['projected_iterations']} iterations would take {r['projected_minutes']:.1f} min at this rate")
    first = next(iter(results.values()))
    if first.get("peak_gpu_memory_mb") is not None:  # one process holds every variant: run one variant for its own peak
        lines.append(f"  peak GPU memory of the bench process (all variants alive): {first['peak_gpu_memory_mb']:.0f} MB")
    for name, r in list(results.items())[1:]:
        ratio = first["iterations_per_second"] / max(r["iterations_per_second"], 1e-9)
        line = f"  {name}: step time x{ratio:.2f} of {next(iter(results))}"
        rounds = sorted(r.get("round_ratios", []))
        if len(rounds) > 1:
            line += f" (its {len(rounds)} rounds: x{rounds[0]:.2f} to x{rounds[-1]:.2f}, median x{statistics.median(rounds):.2f})"
        lines.append(line)
    return "\n".join(lines)


def _phase_order(phase: str) -> int:
    return STEP_PHASES.index(phase) if phase in STEP_PHASES else len(STEP_PHASES)
