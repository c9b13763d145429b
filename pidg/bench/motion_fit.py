"""``pidg bench motion-fit RUN``: can the run's deformation field, and its material field, represent the scene's
true motion at all?

A learned motion can be wrong because the field cannot express the truth (capacity: resolution, table size, width,
the time axis) or because training through images does not lead it there (the optimisation's path, the supervision).
This bench separates the two on a scene from ``pidg make-scene``: a fresh field of the run's own configuration (its
bounds, learning rates, their decay and, by default, its number of steps) is fitted *directly* to the true 3D
trajectories, with no image in the loop, and scored beside the run's trained field on the same points:

* the points: ``surface_points`` samples on the dynamic objects' surfaces at the first ground-truth time (area-
  weighted, carried by their triangle's vertices at every sample: exact for the generators' meshes; a truth of
  points without triangles, as the embedded demo scene's, gives its vertices), plus up to
  ``static_points`` of the run's canonical Gaussians that stay farther than twice the motion radius from every true
  vertex and surface sample at every time (the truth says nothing moves there; they keep the fit from moving the whole box);
* the fit: each step one ground-truth sample time, every point deformed from its first-time position, L1 of the
  position error (world units) plus the field's own regulariser, with the trainer's own optimizer of the field
  (:func:`pidg.training.optim.deformation_optimizer`: its rates and their decay, over the fit's steps);
* the scores (:class:`FieldScores`), for the fitted and for the trained field deforming the same first-time points:
  the mean position error over every sample and surface point (world units) and as a share of the mean distance
  travelled from the first time; the frame-to-frame step error as a share of the true step (pooled over the
  intervals between consecutive samples: what a flow sees); and the spin of every object over the intervals in which
  it moves rigidly and turns (:func:`pidg.evaluation.motion.rigid_turn`), as ``pidg eval --motion-gt`` defines it
  (degrees per sample interval; relative 0 = right, 1 = not turning), here on the surface points rather than on
  matched Gaussians.

With a material field (``--physics cmr`` or ``--flow lpfm``), a fresh one of the run's configuration is fitted the
same way to the true *velocities* (:func:`fit_velocity_field`): each step one sample time, the L1 error of v at the
surface points' true positions (each point its own index row) and of zero at the still points, with the trainer's
own optimizers of the field (:func:`pidg.training.optim.material_optimizers`). :class:`VelocityScores` compares it and
the trained field (at the same true positions, with the index of the run's Gaussian nearest each point at that time)
with the truth, pooled and per sample time: the share of the true speed that is off (0 right, 1 = as far off as
standing still), after converting v from world units per physics time unit to the truth's units (world units per
unit of dataset time, :func:`pidg.evaluation.motion.velocity_per_dataset_time`).

The trained field's scores on these points say how the run moves the *first-time surfaces*, which a relay of
Gaussians (docs/motion.md, "The bodies' spin") leaves behind; the run's rendered motion is scored by
``pidg eval --motion-gt``. A fitted field near 0 where the trained one is near 1 says the limit is not capacity.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from pidg.config_tools import load_config
from pidg.data.motion_gt import MotionGroundTruth, read_motion_gt
from pidg.evaluation.motion import (
    best_rotation,
    default_radius,
    nearest_gaussians,
    ratio_or_none,
    rigid_turn,
    rotation_angle_deg,
    velocity_per_dataset_time,
)
from pidg.export.run_model import check_run_folder
from pidg.models.deformation import DeformationConfig, DeformationModel, build_deformation
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.material_field import MaterialField
from pidg.models.time_axis import TimeAxis
from pidg.training.config import TrainConfig
from pidg.training.motion_start import fit_config, fit_field, identity_rows
from pidg.training.optim import ScheduledOptimizer, deformation_optimizer, material_optimizers


@dataclass(frozen=True)
class MotionFitConfig:
    """Settings of ``pidg bench motion-fit``."""

    steps: int | None = None
    """Fitting steps (None: the run's ``optim.iterations``, the budget its field had)."""
    surface_points: int = 4000
    """Points sampled on the dynamic objects' surfaces at the first ground-truth time."""
    static_points: int = 4000
    """At most this many of the run's canonical Gaussians far from every moving point, held still by the fit."""
    seed: int = 0
    """Seed of the sampling and of the fit's choice of times."""

    def __post_init__(self) -> None:
        if self.steps is not None and self.steps < 0:
            raise ValueError(f"motion-fit: --steps must be >= 0, got {self.steps}")
        if self.surface_points < 3:
            raise ValueError(f"motion-fit: --points must be >= 3 (a rotation needs three points), got {self.surface_points}")
        if self.static_points < 0:
            raise ValueError(f"motion-fit: --static-points must be >= 0, got {self.static_points}")


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on the dynamic surfaces, carried through the recording."""

    trajectories: Tensor  # [T, P, 3] world units, at the ground truth's sample times
    velocities: Tensor  # [T, P, 3] world units per unit of dataset time, the same points' (the same interpolation)
    owner: Tensor  # [P] index of the object (``MotionGroundTruth.objects``) each point lies on
    times: Tensor  # [T] dataset time


@dataclass(frozen=True)
class FieldScores:
    """How well a field moves the first-time surface points (module docstring); world units, degrees."""

    position_error: float  # mean |x_field(t) - x_true(t)| over samples and points, world units
    position_relative: float | None  # that error / the mean true distance from the first time (0 right, 1 = still)
    step_relative: float | None  # sum |step_field - step_true| / sum |step_true| over consecutive samples
    spin_true_deg: float | None  # mean true turn of the scored (interval, rigid object) pairs, degrees per interval
    spin_learned_deg: float | None  # the field's mean turn of the same
    spin_relative: float | None  # pooled angle of R_field R_true^T / pooled true angle (0 right, 1 = not turning)
    spin_intervals: int = 0
    per_object: dict[str, float] = field(default_factory=dict)  # position error per object, world units


@dataclass(frozen=True)
class VelocityScores:
    """How far a material field's v is from the surface points' true velocities (module docstring)."""

    relative: float | None  # sum |v - v_true| / sum |v_true| over samples and points (0 right, 1 = standing still)
    relative_by_time: list[float | None]  # the same at each ground-truth sample time
    error: float  # mean |v - v_true|, world units per unit of dataset time


@dataclass(frozen=True)
class MotionFitResult:
    run: str
    steps: int
    seconds: float  # wall time of the fits (the deformation field and, with one, the material field)
    surface_points: int
    static_points: int
    fitted: FieldScores
    trained: FieldScores
    fitted_velocity: VelocityScores | None = None  # None: the run has no material field
    trained_velocity: VelocityScores | None = None


def surface_samples(truth: MotionGroundTruth, count: int, generator: torch.Generator) -> SurfaceSamples:
    """``count`` points on the dynamic meshes at the first sample (area-weighted triangles, uniform barycentric
    weights), carried by their triangle's vertices at every sample time. A ground truth without triangles (points
    only, as the embedded procedural scene's) gives up to ``count`` of its vertices themselves."""
    v = truth.vertices
    faces = torch.from_numpy(v.faces).long()
    positions = torch.from_numpy(v.positions).double()  # [T, V, 3]
    if faces.numel() == 0:
        rows = torch.randperm(positions.shape[1], generator=generator)[:count].sort().values
        faces = torch.stack([rows, rows, rows], dim=1)  # degenerate triangles: the vertices themselves
        chosen = torch.arange(len(rows))
        weights = torch.full((len(rows), 3), 1.0 / 3.0, dtype=torch.float64)
        return _carried(truth, positions, faces, chosen, weights)
    corners = positions[0][faces]  # [F, 3, 3]
    area = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=1)
    chosen = torch.multinomial(area.float(), count, replacement=True, generator=generator)
    uv = torch.rand(count, 2, generator=generator, dtype=torch.float64)
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    weights = torch.stack([1 - uv.sum(1), uv[:, 0], uv[:, 1]], dim=1)  # [P, 3]
    return _carried(truth, positions, faces, chosen, weights)


def _carried(truth: MotionGroundTruth, positions: Tensor, faces: Tensor, chosen: Tensor, weights: Tensor) -> SurfaceSamples:
    """Samples on the triangles ``faces[chosen]`` with barycentric ``weights`` [P, 3], through every sample time."""
    def carry(per_vertex: Tensor) -> Tensor:
        return (per_vertex[:, faces[chosen]] * weights[None, :, :, None]).sum(2).float()

    owner = truth.vertex_objects()[faces[chosen, 0]]  # the object of each sample's triangle
    velocities = torch.from_numpy(truth.vertices.velocities).double()
    return SurfaceSamples(carry(positions), carry(velocities), owner, torch.from_numpy(truth.vertices.times).float())


def static_anchors(means: Tensor, moving: Tensor, radius: float, count: int, generator: torch.Generator) -> Tensor:
    """Up to ``count`` of ``means`` [N, 3] farther than ``radius`` from every moving point ``moving`` [T, M, 3] (the
    true vertices and the surface samples) at every sample time: places the truth keeps still."""
    clear = torch.ones(len(means), dtype=torch.bool)
    for positions in moving:
        _, distance = nearest_gaussians(means, positions.to(means.dtype))
        clear &= distance > radius
    candidates = means[clear]
    pick = torch.randperm(len(candidates), generator=generator)[:count]
    return candidates[pick]


def fresh_field(run_field: DeformationModel) -> DeformationModel:
    """A new field of ``run_field``'s kind and configuration, normalising positions with the same box; ValueError for a
    field with nothing to fit (the identity of the w/o-deformation ablation)."""
    if not isinstance(getattr(run_field, "normalize", None), torch.nn.Module) or not run_field.parameter_groups():
        raise ValueError(f"the run's deformation ({type(run_field).__name__}) has nothing to fit: `pidg bench motion-fit` "
                         "needs a run with a deformation field (grid4d or mlp)")
    new = build_deformation(DeformationConfig.of(run_field))
    new.normalize.load_state_dict(run_field.normalize.state_dict())
    return new


@torch.no_grad()
def carried_points(model: DeformationModel, start: Tensor, times: Tensor) -> Tensor:
    """``start`` [P, 3] deformed by ``model`` to every time of ``times`` [T]: [T, P, 3]."""
    quats, log_scales = identity_rows(len(start), start.device)
    return torch.stack([model.deform(start, quats, log_scales, t.expand(len(start))).means for t in times])


def score_field(carried: Tensor, samples: SurfaceSamples, truth: MotionGroundTruth) -> FieldScores:
    """Scores (module docstring) of the field's trajectories ``carried`` [T, P, 3] against the samples'."""
    true = samples.trajectories.double()
    ours = carried.double()
    error = (ours - true).norm(dim=2)  # [T, P]
    travel = (true - true[0]).norm(dim=2)
    true_step = (true[1:] - true[:-1]).norm(dim=2)
    step_error = ((ours[1:] - ours[:-1]) - (true[1:] - true[:-1])).norm(dim=2)
    spins: list[tuple[float, float, float]] = []  # true, learned, error angles
    per_object: dict[str, float] = {}
    for j, obj in enumerate(truth.objects):
        rows = samples.owner == j
        if not bool(rows.any()):
            continue
        per_object[obj.name] = float(error[:, rows].mean())
        if int(rows.sum()) < 3:
            continue
        vertices = torch.from_numpy(truth.vertices.positions[:, obj.first_vertex : obj.first_vertex + obj.n_vertices])
        for k in range(len(true) - 1):
            turn = rigid_turn(vertices[k], vertices[k + 1])
            if turn is None:
                continue
            rotation, angle = turn
            learned, _ = best_rotation(ours[k, rows], ours[k + 1, rows])
            spins.append((angle, rotation_angle_deg(learned), rotation_angle_deg(learned @ rotation.T)))
    true_total = sum(s[0] for s in spins)
    return FieldScores(
        position_error=float(error.mean()),
        position_relative=ratio_or_none(float(error.sum()), float(travel.sum())),
        step_relative=ratio_or_none(float(step_error.sum()), float(true_step.sum())),
        spin_true_deg=ratio_or_none(true_total, len(spins)),
        spin_learned_deg=ratio_or_none(sum(s[1] for s in spins), len(spins)),
        spin_relative=ratio_or_none(sum(s[2] for s in spins), true_total),
        spin_intervals=len(spins),
        per_object=per_object,
    )


def fresh_material_field(run_field: MaterialField, num_points: int) -> MaterialField:
    """A new material field of ``run_field``'s configuration and box with one index row per fitted point."""
    new = MaterialField(None, num_points, run_field.config)
    new.normalize.load_state_dict(run_field.normalize.state_dict())
    return new


def fit_velocity_field(
    field: MaterialField, positions: Tensor, velocities: Tensor, times: Tensor, optimizers: dict[str, ScheduledOptimizer],
    steps: int, generator: torch.Generator,
) -> float:
    """Fit ``field``'s v to ``velocities`` [T, P, 3] (world units per physics time unit) at ``positions`` [T, P, 3],
    point p with index row p, in ``steps`` steps: each step one time of ``times`` [T] drawn at random, the mean
    absolute error. Returns the last step's loss."""
    index = torch.arange(positions.shape[1])
    loss = torch.zeros(())
    field.train()
    for step in range(steps):
        k = int(torch.randint(len(times), (1,), generator=generator))
        v, _ = field(positions[k], times[k].expand(positions.shape[1]), index)
        loss = (v - velocities[k]).abs().mean()
        for optimizer in optimizers.values():
            optimizer.zero_grad()
        loss.backward()
        for optimizer in optimizers.values():
            optimizer.step(step)
    return float(loss.detach())


def score_velocities(velocities: Tensor, samples: SurfaceSamples) -> VelocityScores:
    """Scores of a field's ``velocities`` [T, P, 3] (world units per unit of dataset time) at the surface points
    against theirs (module docstring)."""
    true = samples.velocities.double()
    error = (velocities.double() - true).norm(dim=2)  # [T, P]
    speed = true.norm(dim=2)
    return VelocityScores(
        relative=ratio_or_none(float(error.sum()), float(speed.sum())),
        relative_by_time=[ratio_or_none(float(e), float(s)) for e, s in zip(error.sum(1), speed.sum(1))],
        error=float(error.mean()),
    )


@torch.no_grad()
def field_velocities(field: MaterialField, samples: SurfaceSamples, time_axis: TimeAxis,
                     index_at: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """``field``'s v at the surface points' true positions, with the index rows ``index_at(positions, t)`` gives at
    each sample time: [T, P, 3] in world units per unit of dataset time."""
    return torch.stack([velocity_per_dataset_time(field(x, t.expand(len(x)), index_at(x, t))[0], time_axis)
                        for x, t in zip(samples.trajectories, samples.times)])


def fitted_velocities(field: MaterialField, samples: SurfaceSamples, time_axis: TimeAxis) -> Tensor:
    """The fitted field's v at the surface points, point p with index row p (:func:`field_velocities`)."""
    return field_velocities(field, samples, time_axis, lambda x, t: torch.arange(len(x)))


def trained_velocities(model: DynamicGaussians, samples: SurfaceSamples) -> Tensor:
    """The run's material field's v at the surface points, each with the index of the run's Gaussian nearest it at
    that time (:func:`field_velocities`)."""
    field = model.material_field
    if field is None:
        raise ValueError("the run has no material field (trained with --physics none --flow none): no v to score")

    def nearest_index(x: Tensor, t: Tensor) -> Tensor:
        nearest, _ = nearest_gaussians(x, model.at(float(t)).means.float())
        return model.gaussians.particle_index[nearest]

    return field_velocities(field, samples, model.time_axis, nearest_index)


def run_motion_fit(run_dir: Path, config: MotionFitConfig, out: Path | None = None) -> MotionFitResult:
    """Fit a fresh field of the run's configuration to its scene's true motion, score it beside the run's own field,
    print a table and write ``out`` (JSON) when given."""
    run_dir = check_run_folder(run_dir)
    train_config = load_config(TrainConfig, run_dir / "config.json")
    truth = read_motion_gt(Path(train_config.data.path))  # DatasetError naming the missing file (the run's data.path)
    model = DynamicGaussians.from_run(run_dir, "cpu")
    trained = model.deformation
    trained.eval()
    generator = torch.Generator().manual_seed(config.seed)
    samples = surface_samples(truth, config.surface_points, generator)
    moving = torch.cat([torch.from_numpy(truth.vertices.positions).float(), samples.trajectories], dim=1)
    anchors = static_anchors(model.gaussians.params["means"].detach().float(), moving, 2.0 * default_radius(truth),
                             config.static_points, generator)
    start = torch.cat([samples.trajectories[0], anchors])
    targets = torch.cat([samples.trajectories, anchors.expand(len(samples.times), -1, -1)], dim=1)
    steps = config.steps if config.steps is not None else train_config.optim.iterations
    fitted = fresh_field(trained)
    began = time.perf_counter()
    optimizer = deformation_optimizer(fitted, fit_config(train_config, steps), scene_extent=1.0)  # extent: positions' rate only
    fit_field(fitted, start, targets, samples.times, optimizer, steps, generator)
    seconds = time.perf_counter() - began
    fitted.eval()
    surface = samples.trajectories[0]
    velocity_scores: dict[str, VelocityScores] = {}
    if model.material_field is not None:
        began = time.perf_counter()
        field = fresh_material_field(model.material_field, targets.shape[1])
        in_field_units = samples.velocities / model.time_axis.physics_per_dataset  # per physics time unit
        still = torch.zeros(len(samples.times), len(anchors), 3)
        fit_velocity_field(field, targets, torch.cat([in_field_units, still], dim=1), samples.times,  # the same points
                           material_optimizers(field, fit_config(train_config, steps), scene_extent=1.0), steps, generator)
        seconds += time.perf_counter() - began
        field.eval()
        velocity_scores = {"fitted_velocity": score_velocities(fitted_velocities(field, samples, model.time_axis), samples),
                           "trained_velocity": score_velocities(trained_velocities(model, samples), samples)}
    result = MotionFitResult(
        run=str(run_dir), steps=steps, seconds=seconds, surface_points=len(surface), static_points=len(anchors),
        fitted=score_field(carried_points(fitted, surface, samples.times), samples, truth),
        trained=score_field(carried_points(trained, surface, samples.times), samples, truth),
        **velocity_scores,
    )
    print(format_result(result))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(asdict(result), indent=2))
        print(f"-> {out}")
    return result


def format_result(result: MotionFitResult) -> str:
    """The result as a small table (world units; spin in degrees per ground-truth sample interval)."""
    def num(x: float | None, digits: int = 3) -> str:
        return "-" if x is None else f"{x:.{digits}f}"

    lines = [
        f"motion-fit {result.run}: a fresh field fitted to the true 3D motion in {result.steps} steps "
        f"({result.seconds:.0f} s; {result.surface_points} surface points, {result.static_points} still ones)",
        f"{'field':<8} {'pos err':>8} {'pos rel':>8} {'step rel':>9} {'spin rel':>9} {'turn':>14}",
    ]
    for name, s in (("fitted", result.fitted), ("trained", result.trained)):
        turn = "-" if s.spin_true_deg is None else f"{s.spin_learned_deg:.1f}/{s.spin_true_deg:.1f} deg"
        lines.append(f"{name:<8} {num(s.position_error):>8} {num(s.position_relative):>8} {num(s.step_relative):>9} "
                     f"{num(s.spin_relative):>9} {turn:>14}")
    if result.fitted_velocity is not None and result.trained_velocity is not None:
        lines.append(f"material field v, share of the true speed off: fitted {num(result.fitted_velocity.relative)}, "
                     f"trained {num(result.trained_velocity.relative)}")
    lines.append("(pos err in world units; rel: share of the truth's travel, step and turn; 0 = right, 1 = no motion)")
    return "\n".join(lines)
