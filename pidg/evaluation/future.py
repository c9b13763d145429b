"""Future prediction: render the evaluation frames after the last training time two ways and score both.

* ``deformation``: the deformation field queried at the future time, as the paper does (the hash grid's and the
  decoder's extrapolation);
* ``advection`` (runs with a material field): every Gaussian starts at its deformed position at the last training
  time and moves with the field's velocity, integrated in time (:mod:`pidg.physics.advection`);
* ``hold``: the Gaussians frozen at the last training time, the zero-motion baseline that gives the other two a
  scale (a predictor that does not beat it has learnt nothing about the future).

The split into past and future is the data's (``DataConfig.train_until``): this module only predicts and scores.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import torch

from pidg.data.scene import Frame
from pidg.evaluation.evaluate import evaluate_views
from pidg.metrics import NetName
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.physics.advection import Advection, Integrator

PREDICTORS = ("deformation", "advection", "hold")


def evaluate_future(
    model: DynamicGaussians,
    frames: Sequence[Frame],
    t_last: float,
    out_dir: Path | None = None,
    lpips_nets: tuple[NetName, ...] = ("alex", "vgg"),
    method: Integrator = "rk4",
    max_step: float | None = None,
    progress: bool = False,
) -> dict[str, dict]:
    """Metrics of each predictor on ``frames`` (all after ``t_last``, the last training time), keyed by predictor
    name (see the module docstring); the advection entry is absent without a material field. With ``out_dir``, each predictor's renders and
    ``metrics.json`` go to ``out_dir/<predictor>/``."""
    early = [f.name for f in frames if f.time <= t_last]
    if early:
        raise ValueError(f"future prediction scores frames after the last training time {t_last}; got {early[:3]}")
    ordered = sorted(frames, key=lambda f: f.time)  # advection then integrates the interval once
    renders = {"deformation": lambda frame: model.render(frame.camera, frame.time)}
    if model.material_field is not None:
        advection = Advection(model, t_last, method, max_step)
        renders["advection"] = lambda frame: model.render_state(advection.at(frame.time), frame.camera)
    with torch.no_grad():
        frozen = model.at(t_last)
    renders["hold"] = lambda frame: model.render_state(frozen, frame.camera)
    results = {}
    for name, render in renders.items():
        where = None if out_dir is None else Path(out_dir) / name
        result = evaluate_views(render, ordered, where, lpips_nets, progress=progress, device=model.device)
        result.update(predictor=name, t_last=t_last, gaussians=model.num_gaussians)
        if name == "advection":
            result.update(integrator=method, max_step=advection.max_step)
        if where is not None:
            where.mkdir(parents=True, exist_ok=True)
            (where / "metrics.json").write_text(json.dumps(result, indent=2))
        results[name] = result
    return results
