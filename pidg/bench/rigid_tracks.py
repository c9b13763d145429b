"""``pidg bench rigid-tracks DATASET``: how far from the truth are the rigid-body tracks that
``--optim.motion_start rigid_tracks`` fits the deformation to (:mod:`pidg.flow.rigid_tracks`)?

On a scene from ``pidg make-scene``, the tracks are made as a run on it makes them (the dataset's default config for
this machine with the flow on: the same flow cache, settings and seed) and each tracked point is scored against
where the true motion carries it: its object is the one whose true vertex lies nearest its first-frame position, and
that object's true motion from the first training frame to each later one is the Kabsch fit of its vertices (exact
for a rigid or keyframed object; objects of other kinds, cloth and soft bodies, are not scored). Figures per body
and in all: the position error (world units) over the frames where the body is tracked, as a share of the distance
the truth carries the points from the first frame (0 = right, 1 = as far off as standing still), and frame by frame
with the interval in which it grows most (a chain carries an error forward, so that interval is where the track
broke; whether the tracker marked it fitted says whether its own flag could have told); the step error, each
point's move from one training frame to the next against the true move (what a flow sees), as a share of the true
moves (0 = right, 1 = as far off as not moving); the move error, each point's move against the move its body truly
makes at the point's tracked position (the velocity a flow sees where the track is: a track that has drifted to
another part of its body but moves with it scores 0 here and not in the step error, which a rolling body's drift in
orientation fills); how many training intervals the body was tracked through; the share of them in which a
motion was fitted (the others carried at rest or at constant velocity); and how many chains the tracker made for it
and how alike its points look from frame to frame in the one it kept (its own check, which reads no truth).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from pidg.config_tools import apply_overrides
from pidg.data import dataset_layout, load_scene
from pidg.data.motion_gt import MotionGroundTruth, read_motion_gt
from pidg.flow.preprocess import open_flow_cache
from pidg.flow.rigid_tracks import RigidTrackConfig, RigidTracks, rigid_fit, track_rigid_bodies
from pidg.training.config import TrainConfig, apply_preset

RIGID_KINDS = ("rigid", "kinematic")
"""Object kinds of ``motion_gt/meta.json`` that move rigidly (their vertices' Kabsch fit is their motion)."""


@dataclass
class BodyScore:
    """One tracked body against the truth."""

    body: int
    object: str  # the true object most of its points lie on ("" when none they lie on moves rigidly)
    points: int
    on_object: float  # share of its points whose nearest true vertex is on that object
    tracked_intervals: int  # intervals it was tracked through (of the run's training intervals)
    fitted: float  # share of those in which a motion was fitted (not carried at rest or constant velocity)
    chains: int  # chains the tracker made for it (more than 1 where its first went wrong: RigidTrackConfig.attempts)
    look: float | None  # how alike its kept chain's points look from frame to frame (chain_look's mean; None: unseen)
    error: float | None  # mean position error over the tracked frames, world units
    relative: float | None  # pooled error / pooled true travel from the first frame
    step_relative: float | None  # pooled error of the frame-to-frame moves / pooled true moves
    move_relative: float | None  # pooled error of the moves against the body's true move at the tracked positions /
    # pooled true moves there
    error_by_frame: list[float | None] = field(default_factory=list)  # mean position error at each training frame
    # (world units; None where the body is not tracked or not scored)
    worst_interval: int | None = None  # the interval k (frame k to k + 1) in which that error grows most
    worst_growth: float | None = None  # how much it grows there (world units)
    worst_fitted: bool | None = None  # whether the tracker fitted a motion in that interval


@dataclass
class TrackBenchResult:
    dataset: str
    intervals: int
    seconds: float  # the tracking's wall time on this machine
    relative: float | None  # over every scored point and tracked frame
    step_relative: float | None  # over every scored point and tracked interval
    move_relative: float | None  # over every scored point and tracked interval
    tracked_share: float  # share of (point, frame) entries tracked
    bodies: list[BodyScore] = field(default_factory=list)
    not_scored: list[str] = field(default_factory=list)  # objects of non-rigid kinds


def true_poses(tracks: RigidTracks, truth: MotionGroundTruth) -> tuple[Tensor, Tensor, Tensor]:
    """The object index of each tracked point [P] (its nearest true vertex's at the first training frame), and its
    object's true motion from the first training frame to each one, rotations [T, P, 3, 3] and shifts [T, P, 3]
    (the Kabsch fit of the object's vertices: exact for a rigid or keyframed object; NaN for objects of other
    kinds)."""
    vertices = truth.vertices
    samples = [vertices.index_of(float(t)) for t in tracks.times]
    first = torch.as_tensor(vertices.positions[samples[0]], dtype=torch.float64)
    objects = truth.vertex_objects(unowned=0)[torch.cdist(tracks.positions[0], first).argmin(1)]
    rotations = torch.full((len(truth.objects), len(samples), 3, 3), float("nan"), dtype=torch.float64)
    shifts = torch.full((len(truth.objects), len(samples), 3), float("nan"), dtype=torch.float64)
    for index, obj in enumerate(truth.objects):
        if obj.kind not in RIGID_KINDS:
            continue
        own = slice(obj.first_vertex, obj.first_vertex + obj.n_vertices)
        for k, sample in enumerate(samples):
            later = torch.as_tensor(vertices.positions[sample][own], dtype=torch.float64)
            rotations[index, k], shifts[index, k] = rigid_fit(first[own], later)
    return objects, rotations[objects].transpose(0, 1), shifts[objects].transpose(0, 1)


def true_positions(tracks: RigidTracks, rotation: Tensor, shift: Tensor) -> Tensor:
    """[T, P, 3]: where the true motion (:func:`true_poses`' rotations and shifts) carries each tracked point from
    the first training frame (world units; NaN for points nearest a non-rigid object)."""
    return (rotation @ tracks.positions[0, :, :, None])[..., 0] + shift


def true_moves(tracks: RigidTracks, rotation: Tensor, shift: Tensor) -> Tensor:
    """[T - 1, P, 3]: the move the body of each tracked point truly makes from training frame k to k + 1 (from
    :func:`true_poses`' rotations and shifts) at the point's tracked position at frame k (world units; NaN for points
    nearest a non-rigid object)."""
    step = rotation[1:] @ rotation[:-1].transpose(-1, -2)  # frame k to k + 1: x' = step x + (t_{k+1} - step t_k)
    carried = (step @ tracks.positions[:-1, ..., None])[..., 0] + shift[1:] - (step @ shift[:-1, ..., None])[..., 0]
    return carried - tracks.positions[:-1]


def _share(error: Tensor, truth: Tensor) -> float | None:
    """sum(error) / sum(truth), None when the truth sums to 0."""
    total = float(truth.sum())
    return float(error.sum()) / total if total > 0 else None


def score_tracks(
    tracks: RigidTracks, truth: MotionGroundTruth,
) -> tuple[float | None, float | None, float | None, list[BodyScore], list[str]]:
    """(pooled relative position error, pooled relative step error, pooled relative move error, per-body scores,
    objects not scored) of ``tracks`` against ``truth``."""
    objects, rotation, shift = true_poses(tracks, truth)
    expected = true_positions(tracks, rotation, shift)
    error = (tracks.positions - expected).norm(dim=-1)
    travel = (expected - expected[0]).norm(dim=-1)
    scored = tracks.known & torch.isfinite(error)
    step_error = ((tracks.positions[1:] - tracks.positions[:-1]) - (expected[1:] - expected[:-1])).norm(dim=-1)
    step = (expected[1:] - expected[:-1]).norm(dim=-1)
    step_scored = scored[1:] & scored[:-1]
    truly = true_moves(tracks, rotation, shift)
    move_error = ((tracks.positions[1:] - tracks.positions[:-1]) - truly).norm(dim=-1)
    move = truly.norm(dim=-1)
    bodies = []
    for bi in range(int(tracks.body.max()) + 1):
        rows = tracks.body == bi
        counts = torch.bincount(objects[rows], minlength=len(truth.objects))
        main = int(counts.argmax())
        mask = scored[:, rows]
        body_error, body_travel = error[:, rows][mask], travel[:, rows][mask]
        tracked = int(tracks.known[:, rows].all(dim=1).sum()) - 1
        by_frame = [float(error[k, rows][mask[k]].mean()) if bool(mask[k].any()) else None for k in range(len(mask))]
        growth = [(after - before, k) for k, (before, after) in enumerate(zip(by_frame[:-1], by_frame[1:]))
                  if before is not None and after is not None]
        largest = max(growth, default=None)
        worst_growth, worst = largest if largest is not None and largest[0] > 0 else (None, None)
        bodies.append(BodyScore(
            body=bi, object=truth.objects[main].name if truth.objects[main].kind in RIGID_KINDS else "",
            points=int(rows.sum()), on_object=float(counts[main]) / max(int(rows.sum()), 1), tracked_intervals=tracked,
            fitted=float(tracks.found[:tracked, bi].float().mean()) if tracked > 0 else 0.0,
            chains=int(tracks.chains[bi]), look=None if math.isnan(float(tracks.look[bi])) else float(tracks.look[bi]),
            error=float(body_error.mean()) if len(body_error) else None,
            relative=_share(body_error, body_travel),
            step_relative=_share(step_error[:, rows][step_scored[:, rows]], step[:, rows][step_scored[:, rows]]),
            move_relative=_share(move_error[:, rows][step_scored[:, rows]], move[:, rows][step_scored[:, rows]]),
            error_by_frame=by_frame, worst_interval=worst, worst_growth=worst_growth,
            worst_fitted=None if worst is None else bool(tracks.found[worst, bi]),
        ))
    not_scored = [o.name for o in truth.objects if o.kind not in RIGID_KINDS]
    return (_share(error[scored], travel[scored]), _share(step_error[step_scored], step[step_scored]),
            _share(move_error[step_scored], move[step_scored]), bodies, not_scored)


def run_rigid_tracks_bench(dataset: Path, seed: int = 42, out: Path | None = None) -> TrackBenchResult:
    """Track the dataset's rigid bodies as a run with ``--optim.motion_start rigid_tracks --optim.seed SEED`` does
    and score the tracks against its ground truth; print a table, write ``out`` (JSON) when given."""
    config = apply_overrides(TrainConfig(), {"data.path": str(dataset)})
    config = apply_preset(config, "auto", dataset_layout(Path(dataset)))
    config = apply_overrides(config, {"flow.kind": "lpfm", "device": "cpu"})
    truth = read_motion_gt(dataset)
    scene = load_scene(config.data)
    cache = open_flow_cache(scene, config.flow, Path("outputs/bench/flow_cache"))  # beside the dataset when writable
    began = time.perf_counter()
    tracks = track_rigid_bodies(cache, RigidTrackConfig(), torch.Generator().manual_seed(seed))
    seconds = time.perf_counter() - began
    relative, step_relative, move_relative, bodies, not_scored = score_tracks(tracks, truth)
    result = TrackBenchResult(str(dataset), len(tracks.times) - 1, seconds, relative, step_relative, move_relative,
                              float(tracks.known.float().mean()), bodies, not_scored)
    print(format_result(result))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(asdict(result), indent=2))
    return result


def _worst(body: BodyScore) -> str:
    """'interval k (+growth, fitted|carried)', or '-' where the body is not scored or its error never grows."""
    if body.worst_interval is None:
        return "-"
    how = "fitted" if body.worst_fitted else "carried"
    return f"interval {body.worst_interval} ({body.worst_growth:+.3f}, {how})"


def format_result(result: TrackBenchResult) -> str:
    def num(x: float | None, digits: int = 3) -> str:
        return "-" if x is None else f"{x:.{digits}f}"

    lines = [f"rigid-body tracks of {result.dataset}: {len(result.bodies)} bodies, {result.intervals} training "
             f"intervals, {result.seconds:.0f} s; relative position error {num(result.relative)}, step error "
             f"{num(result.step_relative)}, move error {num(result.move_relative)} (0 = the truth, 1 = no better "
             f"than standing still), {100 * result.tracked_share:.0f} % of (point, frame) entries tracked",
             "| body | object | points | on it | tracked intervals | fitted | chains | look | error (world) | relative | "
             "step | move | error (world) grows most in |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for b in result.bodies:
        lines.append(f"| {b.body} | {b.object or '(not rigid)'} | {b.points} | {100 * b.on_object:.0f} % | "
                     f"{b.tracked_intervals}/{result.intervals} | {100 * b.fitted:.0f} % | {b.chains} | {num(b.look)} | "
                     f"{num(b.error)} | "
                     f"{num(b.relative)} | {num(b.step_relative)} | {num(b.move_relative)} | {_worst(b)} |")
    if result.not_scored:
        lines.append("not scored (not rigid): " + ", ".join(result.not_scored))
    return "\n".join(lines)
