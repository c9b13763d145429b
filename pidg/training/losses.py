"""The training loss as a sum of small terms, each saying when it is active and owning its own state.

A term sees one :class:`StepInputs` (the frame, the scene model and the Gaussians at the frame's time) and may ask
for extra per-Gaussian channels in the step's render (the flow term renders its Gaussian and velocity flows in the
same pass as the image). The trainer sums the active terms' losses in their order; each returns its weighted loss
and the scalars it logs. A term with state (the flow term's target cache, the physics term's sampler) saves it in
checkpoints through ``state_dict``. Adding a term means writing one class here and listing it in
:func:`build_loss_terms`.

Terms, in the order they are summed (NOTES.md section 9):
  photometric     (1 - lambda_c) L1 + lambda_c D-SSIM, with the 3DGS zero-padded SSIM
  smoothness      the deformation's own regulariser (Grid4D), on the frame-t pass
  depth           lambda_depth * relative depth error against the dataset's depth maps (``--optim.lambda_depth``)
  cmr             lambda_cmr * L_CMR at the deformed positions (``--physics cmr``)
  lpfm            lambda_lpfm * L_LPFM of the rendered flows against the motion-flow target (``--flow lpfm``)
  tracks          lambda_tracks * the deformation's position error on the motion start's tracks (``--optim.lambda_tracks``)
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.flow import (
    FlowCache,
    FlowConfig,
    FlowPair,
    FlowTarget,
    depth_from_render,
    flow_camera_t1,
    flow_target_for_pair,
    model_flow_target,
    sample_tiles,
    supervised_flow_channels,
    supervised_flow_loss,
)
from pidg.metrics import ssim
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.physics import (
    PhysicsConfig,
    cmr_loss,
    particle_step_velocity,
    particle_velocity,
    sample_rows,
    velocity_mismatch,
)
from pidg.render import OPAQUE_ALPHA, PreparedRender, RenderOutput
from pidg.training.config import TrainConfig
from pidg.training.fused_ssim import fused_ssim
from pidg.training.motion_start import TrackTargets, identity_rows

logger = logging.getLogger(__name__)


def l1_loss(pred: Tensor, gt: Tensor) -> Tensor:
    return (pred - gt).abs().mean()


def ssim_kernel(backend: str, device: torch.device) -> bool:
    """Whether the photometric loss's SSIM runs as the numba kernel: on CPU tensors, unless ``--backend torch``
    asks for the pure-torch path (the one CUDA runs)."""
    return device.type == "cpu" and backend != "torch"


def photometric_loss(
    pred: Tensor, gt: Tensor, lambda_dssim: float = 0.2, kernel: bool | None = None
) -> tuple[Tensor, dict[str, float]]:
    """(1 - lambda) * L1 + lambda * (1 - SSIM) on [H, W, 3] images; also returns the parts for logging.

    SSIM: the numba kernel with its analytic backward (~2x faster than autograd) when ``kernel`` (CPU tensors only;
    None: whenever the tensors are on the CPU), the torch reference (zero-padded, 3DGS) otherwise; the two agree."""
    l1 = l1_loss(pred, gt)
    if lambda_dssim > 0:
        use_kernel = pred.device.type == "cpu" if kernel is None else kernel
        value = fused_ssim(pred, gt) if use_kernel else ssim(pred, gt, padding="zeros")
        d_ssim = 1.0 - value
        total = (1.0 - lambda_dssim) * l1 + lambda_dssim * d_ssim
    else:
        d_ssim = torch.zeros((), dtype=pred.dtype, device=pred.device)
        total = l1
    return total, {"l1": float(l1.detach()), "dssim": float(d_ssim.detach())}


@dataclass
class StepInputs:
    """What one training step gives every loss term."""

    step: int
    frame: Frame
    model: DynamicGaussians
    state: DeformedGaussians  # the Gaussians at frame.time (canonical during a static warm-up)
    deforming: bool  # whether the deformation ran (after the static warm-up)
    # the step's render of ``state`` in the frame's camera, projected but not yet composited (None outside a training
    # step; a term that needs it then prepares its own)
    screen: PreparedRender | None = None


class LossTerm:
    """One term of the training loss. Subclasses set ``name`` and ``phase`` (the step timer's phase its work counts
    to) and implement :meth:`loss`; the other hooks have neutral defaults."""

    name = "term"
    phase = "loss"

    def active(self, step: int) -> bool:
        """Whether the term takes part in this step."""
        return True

    def prepare(self, inputs: StepInputs) -> None:
        """Work before the render that the term caches across steps (the flow term's target); the trainer times it
        as its own phase, ``{phase}_target``, so a benchmark shows what a cache refresh costs."""

    def render_features(self, inputs: StepInputs) -> Tensor | None:
        """Extra per-Gaussian channels [N, C] the term needs composited in the step's render (None: none)."""
        return None

    def feature_pixels(self) -> Tensor | None:
        """The pixels [H, W] (bool) at which the term reads the channels it asked for this step (None: anywhere)."""
        return None

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        """The weighted loss and the scalars to log; ``features`` is the term's own slice of ``render.features``."""
        raise NotImplementedError

    def observe(self, inputs: StepInputs, render: RenderOutput) -> None:
        """See the step's render (of ``inputs.frame`` at its time) and keep what later steps can reuse (the flow term:
        the frame's depth, the target's input when the frame is a pair's t+1)."""

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass


class PhotometricLoss(LossTerm):
    """(1 - lambda_c) L1 + lambda_c D-SSIM of the render against the frame (3DGS); the SSIM's implementation follows
    the rasterizer ``backend`` (see :func:`ssim_kernel`)."""

    name = "photometric"

    def __init__(self, lambda_dssim: float, backend: str = "auto") -> None:
        self.lambda_dssim = lambda_dssim
        self.backend = backend

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        kernel = ssim_kernel(self.backend, render.rgb.device)
        return photometric_loss(render.rgb, inputs.frame.image, self.lambda_dssim, kernel)


class DeformationSmoothness(LossTerm):
    """The deformation field's own regulariser (Grid4D's smoothness term), from the frame-t pass; active once the
    deformation runs (after ``start`` steps of static warm-up)."""

    name = "smoothness"

    def __init__(self, start: int = 0) -> None:
        self.start = start

    def active(self, step: int) -> bool:
        return step >= self.start

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        reg = inputs.state.regularization
        reg = reg if reg is not None else render.rgb.new_zeros(())
        return reg, {"deform_reg": float(reg.detach())}


def relative_depth_error(render: RenderOutput, depth_gt: Tensor, min_alpha: float = OPAQUE_ALPHA) -> Tensor:
    """Mean |d - d_gt| / d_gt of the rendered expected depth d (depth / alpha) over the pixels with a measured depth
    (d_gt > 0, finite); pixels the render leaves (nearly) empty (alpha < ``min_alpha``) count with d = 0, an error
    of 1, so the loss also pulls Gaussians onto measured surfaces (zero when no pixel has a depth)."""
    valid = torch.isfinite(depth_gt) & (depth_gt > 0)
    if not bool(valid.any()):
        return render.depth.new_zeros(())
    d_gt = depth_gt[valid]
    d = render.opaque_depth(min_alpha)[valid]  # 0 where the render leaves the pixel (nearly) empty: error exactly 1
    return ((d - d_gt).abs() / d_gt).mean()


class DepthLoss(LossTerm):
    """lambda_depth * :func:`relative_depth_error` of the render against the frame's depth map (datasets with
    ``depth/``; ``--optim.lambda_depth``)."""

    name = "depth"

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        depth_gt = inputs.frame.depth
        if depth_gt is None:  # a frame without a map (the trainer checks that some have one)
            return render.rgb.new_zeros(()), {}
        error = relative_depth_error(render, depth_gt.to(render.depth.device))
        return self.weight * error, {"depth_rel": float(error.detach())}


class _PhysicsParticleTerm(LossTerm):
    """A physics term on random particle subsets: its settings and its own generator, saved in checkpoints so a
    resumed run draws the same subsets."""

    phase = "physics"

    def __init__(self, config: PhysicsConfig, seed: int) -> None:
        self.config = config
        self.generator = torch.Generator().manual_seed(seed)  # CPU: the same subsets on any device

    def state_dict(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])


class MomentumResidualLoss(_PhysicsParticleTerm):
    """lambda_cmr * L_CMR on a random subset of the Gaussians at their deformed positions (``--physics cmr``)."""

    name = "cmr"

    def active(self, step: int) -> bool:
        return self.config.active(step)

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        model = inputs.model
        if model.material_field is None:
            raise RuntimeError("the momentum residual needs a material field: build the model with one")
        cmr = cmr_loss(
            model.material_field, inputs.state.means, inputs.frame.time, model.gaussians.particle_index, self.config,
            model.time_axis, self.generator,
        )
        return self.config.lambda_cmr * cmr.loss, {"cmr": float(cmr.loss.detach()), **{f"cmr_{k}": float(v) for k, v in cmr.stats.items()}}


class ParticleVelocityLoss(_PhysicsParticleTerm):
    """lambda_kinematic * L_kin (``pidg.physics.consistency``): the material field's v at random particles against
    the deformation's velocity there (``PhysicsConfig.kinematic_target``: central difference, or the move over the
    next training interval), so v follows the particles everywhere, not only where the flow loss sees them (an
    extension; off by default)."""

    name = "kinematic"

    def active(self, step: int) -> bool:
        return self.config.active(step) and self.config.lambda_kinematic > 0

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        model = inputs.model
        field = model.material_field
        if field is None:
            raise RuntimeError("the particle-velocity term needs a material field: build the model with one")
        moving = model.dynamic_mask  # once decoupled, static particles do not move and have v = 0 by definition
        candidates = torch.arange(model.num_gaussians) if moving is None else moving.cpu().nonzero().squeeze(1)
        if not inputs.deforming or candidates.numel() == 0:
            return render.rgb.new_zeros(()), {}
        picked = sample_rows(candidates.numel(), self.config.samples, self.generator)
        rows = (candidates if picked is None else candidates[picked]).to(inputs.state.means.device)
        t, means = self._sample_time(inputs, rows)
        with torch.no_grad():
            if self.config.kinematic_target == "forward":
                target = particle_step_velocity(model, t, means, rows)
            else:
                target = particle_velocity(model, t, rows)
        v = model.velocities(t, means=means, rows=rows)
        mismatch = velocity_mismatch(v, target, model.time_axis, field.normalize.half_extent)
        return self.config.lambda_kinematic * mismatch, {"kinematic": float(mismatch.detach())}

    def _sample_time(self, inputs: StepInputs, rows: Tensor) -> tuple[float | Tensor, Tensor]:
        """The dataset time this step teaches v at and the particles ``rows`` there (detached): the frame's time,
        or with ``kinematic_time_jitter`` a time drawn around it (``PhysicsConfig.kinematic_time_jitter``), or with
        ``kinematic_times recording`` a time [M] per particle drawn over the whole recording."""
        if self.config.kinematic_times == "recording":
            means = inputs.state.means
            times = torch.rand(len(rows), generator=self.generator, dtype=torch.float64).to(means.device, means.dtype)
            with torch.no_grad():
                return times, inputs.model.at(times, rows=rows).means
        t, jitter = inputs.frame.time, self.config.kinematic_time_jitter
        if jitter > 0:
            offset = (float(torch.rand((), generator=self.generator)) - 0.5) * jitter * inputs.model.time_axis.frame_interval
            drawn = min(max(t + offset, 0.0), 1.0)
            if drawn != t:
                with torch.no_grad():
                    return drawn, inputs.model.at(drawn, rows=rows).means
        return t, inputs.state.means.detach()[rows]


#: Tracked points the tracks term deforms a step (of ~10,000 on the generated rigid and kinematic scenes, still
#: surface included): a deformation pass on them costs a few ms on a 2-core CPU, a small share of a step.
TRACK_POINTS_PER_STEP = 4096


class TrackHoldLoss(LossTerm):
    """lambda_tracks * the mean absolute position error (world units) of the deformation carrying the tracked points
    (:class:`pidg.training.motion_start.TrackTargets`, what ``optim.motion_start rigid_tracks`` fitted it to) to their
    tracks at the step frame's time, on a random subset of the points known there. The start's long-range 3D
    correspondence, kept through training: the image losses see each time from one view only and move what it does
    not see. The targets are saved in checkpoints (a resumed run does not track again)."""

    name = "tracks"

    def __init__(self, weight: float, targets: TrackTargets | None, seed: int) -> None:
        self.weight = weight
        self.targets = targets  # None until a checkpoint's state is loaded (a resumed run)
        self.generator = torch.Generator().manual_seed(seed)

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        zero = render.rgb.new_zeros(())
        targets = self.targets
        if targets is None or not inputs.deforming:
            return zero, {}
        device = inputs.state.means.device
        if targets.start.device != device:  # restored from a checkpoint (on the CPU)
            self.targets = targets = targets.to(device)
        k = int(torch.argmin((targets.times - inputs.frame.time).abs()))
        if abs(float(targets.times[k]) - inputs.frame.time) > 1e-6:  # not one of the tracked frames' times
            return zero, {}
        known = targets.known[k].nonzero().squeeze(1)
        if known.numel() == 0:  # every point lost by then (the still surface is always known: not in practice)
            return zero, {}
        picked = sample_rows(known.numel(), TRACK_POINTS_PER_STEP, self.generator)
        rows = known if picked is None else known[picked.to(known.device)]
        deformation = inputs.model.deformation
        quats, log_scales = identity_rows(len(rows), rows.device)
        t = torch.full((len(rows),), inputs.frame.time, device=rows.device)
        carried = deformation.deform(targets.start[rows], quats, log_scales, t, regularize=False).means
        error = (carried - targets.positions[k, rows]).abs().mean()
        return self.weight * error, {"tracks": float(error.detach())}

    def state_dict(self) -> dict[str, Any]:
        targets = None if self.targets is None else dataclasses.asdict(self.targets.to("cpu"))
        return {"targets": targets, "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["targets"] is not None:  # moved to the run's device at the first step that reads them
            self.targets = TrackTargets(**state["targets"])
        self.generator.set_state(state["generator"])


@dataclass
class _CachedTarget:
    """A pair's flow_gt, the step it was built at, and frame t+1's rendered depth (None: the dataset's depth map)."""

    step: int
    depth: Tensor | None
    target: FlowTarget | None


def _target_key(pair: FlowPair) -> str:
    """Where a pair's target is cached (and saved): a forward pair by its first frame's name, a reversed one
    (``FlowConfig.directions`` both) by that name marked with the frame it runs back to."""
    return pair.frame0.name if pair.dt >= 0 else f"{pair.frame0.name}<{pair.frame1.name}"


#: dtype of the depths the flow term keeps from training renders (and saves in checkpoints: 150 frames at 400x400
#: are 48 MB in float16)
KEPT_DEPTH_DTYPE = torch.float16


class FlowMatchingLoss(LossTerm):
    """lambda_lpfm * L_LPFM (``--flow lpfm``): the Gaussian and velocity flows of frame t, rendered as extra channels
    of the step's render, against the pair's motion-flow target.

    The target needs frame t+1's depth: the dataset's depth map when it has one, otherwise the model's own (a
    no-grad render at t+1 in camera t+1). That rendered depth is reused while younger than
    ``FlowConfig.target_refresh_steps`` and goes into checkpoints, so a resumed run builds the same targets as an
    uninterrupted one. Every training step renders its frame's depth anyway: the term keeps it (``observe``), and a
    target due for a rebuild uses frame t+1's kept depth when it is young enough, so the render of its own is needed
    only until frame t+1 has been trained (the first epoch). The target is known before the render, so only the
    Gaussians whose footprint reaches one of its supervised pixels get flow channels
    (:func:`pidg.flow.supervised_flow_channels`: the same loss and gradients for the cost of those Gaussians).
    Steps whose frame starts no flow pair (the last frame), or whose target supervises no pixel, have no flow term.
    With ``FlowConfig.directions`` both, "t+1" is the frame the step's pair runs to, ahead or back in time."""

    name = "lpfm"
    phase = "flow"

    def __init__(self, config: FlowConfig, cache: FlowCache, seed: int = 0) -> None:
        self.config = config
        self.cache = cache
        # the tiles drawn per step (FlowConfig.tile_fraction) and, with both directions, the pair's direction
        self.generator = torch.Generator().manual_seed(seed)
        self._targets: dict[str, _CachedTarget] = {}  # _target_key(pair) -> flow_gt and what it came from
        self._pending: tuple[FlowPair, FlowTarget] | None = None  # this step's pair and target
        self._depths: dict[str, tuple[int, Tensor]] = {}  # frame name -> (step, its depth in that step's render)
        if config.min_pair_coverage > 0 or config.weigh_by_coverage:
            self._log_coverage()

    def active(self, step: int) -> bool:
        return self.config.active(step)

    def prepare(self, inputs: StepInputs) -> None:
        self._pending = None
        pair = self.pair_for(inputs.frame)
        if pair is None:
            return
        target = self.target(inputs.model, pair, inputs.step, inputs.deforming)
        # this step reads a random share of the tiles (the cached target stays whole; a share of 1 keeps them all)
        target = dataclasses.replace(target, valid=sample_tiles(target.valid, self.config.tile_fraction, self.generator))
        if bool(target.valid.any()):
            self._pending = (pair, target)

    def pair_for(self, frame: Frame) -> FlowPair | None:
        """The pair this step's frame is matched with (``FlowConfig.directions``); None if it has none, or if its
        flow covers too little of the frame's moving pixels (``FlowConfig.min_pair_coverage``)."""
        ahead = self.cache.pair_starting_at(frame)
        if self.config.directions == "forward":
            pair = ahead
        else:
            back = self.cache.pair_back_from(frame)
            if ahead is None or back is None:
                pair = ahead or back
            else:
                pair = back if bool(torch.rand((), generator=self.generator) < 0.5) else ahead
        return pair if pair is None or self.trusted(pair) else None

    def pair_weight(self, pair: FlowPair) -> float:
        """The pair's weight in the flow loss: its coverage of frame t's moving pixels with
        ``FlowConfig.weigh_by_coverage`` (1 where the frame has no mask), else 1."""
        coverage = pair.moving_coverage() if self.config.weigh_by_coverage else None
        return 1.0 if coverage is None else coverage

    def _log_coverage(self) -> None:
        """Say which pairs the coverage options leave out or weigh down (those under a half), with their coverage."""
        pairs = [self.cache.pair(k) for k in range(len(self.cache))]
        pairs += [p.reversed() for p in pairs] if self.config.directions == "both" else []
        covered = [(p, p.moving_coverage()) for p in pairs]
        low = ", ".join(f"{p.frame0.name}->{p.frame1.name} {c:.2f}" for p, c in covered if c is not None and c < 0.5)
        left_out = sum(not self.trusted(p) for p in pairs)
        logger.info("flow loss: %d of %d pairs left out (--flow.min_pair_coverage %g), weighed by their coverage of "
                    "frame t's moving pixels: %s (--flow.weigh_by_coverage); pairs under 0.5: %s", left_out, len(pairs),
                    self.config.min_pair_coverage, "yes" if self.config.weigh_by_coverage else "no", low or "none")

    def trusted(self, pair: FlowPair) -> bool:
        """Whether the pair's flow passed the consistency check on enough of frame t's moving pixels
        (``FlowConfig.min_pair_coverage``; always with 0, or where the frame has no motion mask)."""
        if self.config.min_pair_coverage == 0:
            return True
        coverage = pair.moving_coverage()
        return coverage is None or coverage >= self.config.min_pair_coverage

    def render_features(self, inputs: StepInputs) -> Tensor | None:
        if self._pending is None:
            return None
        pair, target = self._pending
        screen = inputs.screen if inputs.screen is not None else inputs.model.prepare_render(inputs.state, inputs.frame.camera)
        return supervised_flow_channels(
            inputs.model, screen, inputs.state, inputs.frame.time, pair.frame1.time, pair.dt, target.valid,
            inputs.deforming, flow_camera_t1(pair, self.config), target.depth_change is not None,
            integration=self.config.velocity_integration,
        )

    def feature_pixels(self) -> Tensor | None:
        return None if self._pending is None else self._pending[1].valid  # the loss reads the flows there only

    def loss(self, inputs: StepInputs, render: RenderOutput, features: Tensor | None) -> tuple[Tensor, dict[str, float]]:
        if self._pending is None or features is None:
            return render.rgb.new_zeros(()), {}
        (pair, target), self._pending = self._pending, None
        result = supervised_flow_loss(features, render.alpha, target, self.config)
        weight = self.config.lambda_lpfm * self.pair_weight(pair)
        return weight * result.loss, {k if k == "lpfm" else f"lpfm_{k}": v for k, v in result.scalars().items()}

    def observe(self, inputs: StepInputs, render: RenderOutput) -> None:
        if not self._renders_depth(inputs.frame):
            return
        step, refresh = inputs.step, self.config.target_refresh_steps
        self._depths = {name: kept for name, kept in self._depths.items() if step - kept[0] < refresh}
        # kept in half precision (relative error 5e-4: 0.015 px on a 30 px camera flow), as checkpoints save them
        self._depths[inputs.frame.name] = (step, depth_from_render(render).to(KEPT_DEPTH_DTYPE))

    def _renders_depth(self, frame: Frame) -> bool:
        """Whether targets need the model's depth of ``frame`` (the motion-flow target, where the data has none)."""
        return self.config.target == "motion" and frame.depth is None

    def target(self, model: DynamicGaussians, pair: FlowPair, step: int, deforming: bool = True) -> FlowTarget:
        """The pair's flow_gt, rebuilt when its depth is ``target_refresh_steps`` old. Frame t+1's depth: the
        dataset's; else the one kept from frame t+1's latest training render when younger than that; else a no-grad
        render of the model at t+1 (canonical while ``deforming`` is False). The total-flow target is built once."""
        cached = self._targets.get(_target_key(pair))
        fixed = self.config.target == "total"  # the optical flow itself: it never changes
        refresh = self.config.target_refresh_steps
        if cached is not None and (fixed or step - cached.step < refresh):
            if cached.target is None:  # restored from a checkpoint (on the CPU): rebuild from the saved depth
                depth = pair.frame1.depth if cached.depth is None else cached.depth.to(pair.forward.device, torch.float32)
                cached.target = flow_target_for_pair(pair, depth, self.config)
            return cached.target
        kept = self._depths.get(pair.frame1.name) if self._renders_depth(pair.frame1) else None
        if kept is not None and step - kept[0] < refresh:  # aged from its render, as a depth rendered here would be
            built_at, depth = kept
            target = flow_target_for_pair(pair, depth.to(pair.forward.device, torch.float32), self.config)
        else:
            state_t1 = None
            if self._renders_depth(pair.frame1):
                with torch.no_grad():
                    state_t1 = model.at(pair.frame1.time) if deforming else model.canonical()
            built_at = step
            target, depth = model_flow_target(model, pair, state_t1, self.config)
        self._targets[_target_key(pair)] = _CachedTarget(built_at, depth, target)
        return target

    def state_dict(self) -> dict[str, Any]:
        # the rendered depths behind cached flow targets (the targets are rebuilt from them on resume) and the kept
        # depths of recent renders; a target built from a kept depth holds the same tensor, saved once
        return {"depths": {k: (c.step, c.depth) for k, c in self._targets.items()}, "frame_depths": dict(self._depths),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._targets = {k: _CachedTarget(step, depth, None) for k, (step, depth) in state["depths"].items()}
        self._depths = {k: (step, depth) for k, (step, depth) in state.get("frame_depths", {}).items()}
        if "generator" in state:  # checkpoints before tile sampling have none (and drew no tiles)
            self.generator.set_state(state["generator"])


def build_loss_terms(config: TrainConfig, flow_cache: FlowCache | None, tracks: TrackTargets | None = None) -> list[LossTerm]:
    """The terms a run config asks for, in summation order; ``tracks``: what the motion start fitted (None on a
    resumed run: the tracks term reads its targets from the checkpoint)."""
    terms: list[LossTerm] = [PhotometricLoss(config.optim.lambda_dssim, config.backend), DeformationSmoothness(config.optim.static_warmup)]
    if config.optim.lambda_depth > 0:
        terms.append(DepthLoss(config.optim.lambda_depth))
    if config.physics.enabled:
        terms.append(MomentumResidualLoss(config.physics, config.optim.seed + 1))
        if config.physics.lambda_kinematic > 0:
            terms.append(ParticleVelocityLoss(config.physics, config.optim.seed + 2))
    if config.flow.enabled:
        if flow_cache is None:
            raise ValueError("the flow loss needs the scene's optical flow (a FlowCache)")
        terms.append(FlowMatchingLoss(config.flow, flow_cache, config.optim.seed + 3))
    if config.optim.lambda_tracks > 0:
        terms.append(TrackHoldLoss(config.optim.lambda_tracks, tracks, config.optim.seed + 4))
    return terms
