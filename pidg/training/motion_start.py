"""Where the deformation field starts: at rest (the identity, as the paper), or fitted to 3D trajectories before
step 0 (``optim.motion_start``). ``pidg bench motion-fit`` fits a fresh field with the same functions."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from pidg.flow.preprocess import FlowCache
from pidg.flow.rigid_tracks import RigidTrackConfig, track_rigid_bodies
from pidg.models.deformation import DeformationModel
from pidg.training.config import TrainConfig
from pidg.training.optim import ScheduledOptimizer, deformation_optimizer

logger = logging.getLogger(__name__)


def identity_rows(n: int, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor]:
    """Unit quaternions [n, 4] and zero log-scales [n, 3] on ``device``: points deformed as Gaussians without shape."""
    quats = torch.zeros(n, 4, device=device)
    quats[:, 0] = 1.0
    return quats, torch.zeros(n, 3, device=device)


@dataclass
class TrackTargets:
    """Points and where the deformation should carry them: ``start`` [P, 3] (canonical = the first training frame's
    positions, world units) to ``positions`` [T, P, 3] at ``times`` [T] (dataset time), where ``known`` [T, P]."""

    start: Tensor
    positions: Tensor
    times: Tensor
    known: Tensor

    def to(self, device: torch.device | str) -> "TrackTargets":
        return TrackTargets(self.start.to(device), self.positions.to(device), self.times.to(device), self.known.to(device))


def fit_field(
    model: DeformationModel, start: Tensor, targets: Tensor, times: Tensor, optimizer: ScheduledOptimizer, steps: int,
    generator: torch.Generator, known: Tensor | None = None,
) -> float:
    """Fit ``model`` with ``optimizer`` (:func:`pidg.training.optim.deformation_optimizer`) so that it carries
    ``start`` [P, 3] to ``targets`` [T, P, 3] at ``times`` [T] in ``steps`` steps: each step one time drawn at random,
    the mean absolute position error (world units) of the points ``known`` [T, P] there (all without it), plus the
    field's own regulariser. Returns the last step's loss."""
    quats, log_scales = identity_rows(len(start), start.device)  # the trainer's start fits on the run's device
    loss = torch.zeros(())
    model.train()
    for step in range(steps):
        k = int(torch.randint(len(times), (1,), generator=generator))
        out = model.deform(start, quats, log_scales, times[k].expand(len(start)), regularize=True)
        error = (out.means - targets[k]).abs()
        loss = error.mean() if known is None else error[known[k]].mean()
        if out.regularization is not None:
            loss = loss + out.regularization
        optimizer.zero_grad()
        loss.backward()
        optimizer.step(step)
    return float(loss.detach())


def fit_config(train_config: TrainConfig, steps: int) -> TrainConfig:
    """The run's config for a fit of ``steps`` steps: its rates and decay over that length, no static warm-up (a
    direct fit has no Gaussians to settle first)."""
    return replace(train_config, optim=replace(train_config.optim, iterations=steps, static_warmup=0))


def start_from_rigid_tracks(field: DeformationModel, cache: FlowCache, config: TrainConfig) -> TrackTargets:
    """Fit ``field`` to the rigid bodies tracked through ``cache`` (:mod:`pidg.flow.rigid_tracks`, the dataset's depth
    and motion masks), each point while its body is tracked, and to the first frame's still surface held still, over
    ``optim.motion_start_steps`` steps at the run's rates (the training's own optimizer then starts afresh). A body
    lost before half the training intervals is left out: a field fitted to the start of a path leaves the rest of it
    anywhere (the kinematic head, lost at interval 16 of 44 by the first tracker, which followed the flow alone: far
    worse than a start at rest), while a body lost late still gives most of its path (docs/motion.md, "A start from
    rigid-body tracks"). ValueError when every body is lost that early. Returns what was fitted (``optim.lambda_tracks``
    keeps training near it)."""
    began = time.perf_counter()
    generator = torch.Generator().manual_seed(config.optim.seed)
    tracks = track_rigid_bodies(cache, RigidTrackConfig(), generator)
    intervals = len(tracks.times) - 1
    tracked_to = tracks.known.sum(dim=0) - 1  # [P] the last frame each point's body is tracked to
    use = 2 * tracked_to >= intervals
    n_bodies, kept = int(tracks.body.max()) + 1, len(torch.unique(tracks.body[use]))
    if kept == 0:
        raise ValueError(f"every body was lost before half the training intervals (neither the flow nor the next "
                         f"frame's depth placed it for more than one interval; the last by interval "
                         f"{int(tracked_to.max())} of {intervals}): train from rest")
    steps = config.optim.motion_start_steps
    moving, still = tracks.positions[:, use].float(), tracks.static.float()
    device = next(field.parameters()).device
    targets = TrackTargets(
        start=torch.cat([moving[0], still]),
        positions=torch.cat([moving, still.expand(len(moving), -1, -1)], dim=1),
        times=tracks.times.float(),
        known=torch.cat([tracks.known[:, use], torch.ones(len(moving), len(still), dtype=torch.bool)], dim=1),
    ).to(device)
    optimizer = deformation_optimizer(field, fit_config(config, steps), scene_extent=1.0)
    loss = fit_field(field, targets.start, targets.positions, targets.times, optimizer, steps, generator, targets.known)
    logger.info("motion start: %d of %d rigid bodies fitted (%d points; %d tracked through all %d intervals; a motion "
                "fitted on %.0f%% of the body-intervals, carried at rest or constant velocity on the others; %d chained "
                "again where the first chain went wrong), with %d still points, in %d steps (last loss %.4f world "
                "units), %.0f s", kept, n_bodies, int(use.sum()), len(torch.unique(tracks.body[tracks.known[-1]])),
                intervals, 100.0 * float(tracks.found.float().mean()), int((tracks.chains > 1).sum()), len(still),
                steps, loss, time.perf_counter() - began)
    return targets
