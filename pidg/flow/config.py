"""Settings of Lagrangian particle flow matching (LPFM): optical-flow preprocessing, motion decomposition, loss.

Plain field types only, so the project's dataclass <-> command-line tool exposes every field as ``--flow.NAME``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, Range, validate_config

FlowKind = Literal["none", "lpfm"]
FlowTargetKind = Literal["motion", "total"]
EstimatorName = Literal["dis", "deepflow", "tvl1", "raft"]
DisPreset = Literal["ultrafast", "fast", "medium"]
VelocityIntegration = Literal["euler", "midpoint"]
FlowDirections = Literal["forward", "both"]


@dataclass
class FlowConfig:
    """Optical-flow supervision (paper Sec. 4.3 and supp. B; NOTES.md sections 6-8).

    Loss: ``lambda_lpfm * (lambda_gaussian * L1(flow_g, flow_gt) + lambda_velocity * L1(flow_v, flow_gt))``,
    applied on every step from ``start`` on (the reference code's 1%-of-steps schedule is a defect).
    """

    kind: FlowKind = "none"
    """lpfm adds Lagrangian particle flow matching against preprocessed optical flow (the full PIDG); none leaves it out."""
    lambda_lpfm: Annotated[float, NON_NEGATIVE] = 0.01
    """Weight of L_LPFM in the total loss (paper: 0.01)."""
    lambda_gaussian: Annotated[float, NON_NEGATIVE] = 0.5
    """lambda_g: weight of the Gaussian flow's L1 error inside L_LPFM (paper: 0.5)."""
    lambda_velocity: Annotated[float, NON_NEGATIVE] = 0.5
    """lambda_v: weight of the velocity flow's L1 error inside L_LPFM (paper: 0.5)."""
    lambda_depth_change: Annotated[float, NON_NEGATIVE] = 0.0
    """Weight, inside L_LPFM beside each flow's L1 error, of its depth-change error (an extension, not in the paper;
    0 = off): a 2D flow constrains only the motion across camera t's rays, so the velocity's component along them is
    left free. Its target is the surface's camera-t depth change from t to t+1 (frame t's and t+1's depth maps and
    the optical flow; ``pidg.flow.decomposition.depth_change_target``), in pixel-equivalents (fx / z x world units),
    matched by the Gaussians' and the advected velocities' composited depth changes. Needs the dataset's depth maps
    and the motion target."""
    velocity_integration: VelocityIntegration = "euler"
    """How the velocity flow carries a particle through the material field over a pair's interval dt (dataset time;
    where it multiplies v, in the field's physics time units, ``TimeAxis.to_physics``). euler (the paper):
    x + v(x, t) dt, first order. midpoint (an extension): x + v(x + v(x, t) dt / 2, t + dt / 2) dt, the explicit
    midpoint rule, second order, for one more field evaluation per flow Gaussian. Where an object turns or
    accelerates, the true velocity does not match a displacement to first order (on the generated kinematic scene its
    first-order flow is 0.84 px from the true motion, its second-order one 0.04 px: docs/motion.md), so a first-order
    flow loss teaches v each interval's chord rather than the particles' velocity. Evaluation (``pidg eval
    --motion-gt``) scores the velocity flow with the run's own rule."""
    directions: FlowDirections = "forward"
    """Which pair a step's frame k is matched with. forward (the paper): the flow to frame k+1. both (an extension):
    half the steps, drawn at random, the pair back to frame k-1 instead (its cached backward flow, on frame k's
    pixels; the interval runs backwards, dt < 0), so each interval is supervised from both of its frames, on the
    surfaces each of them sees; the first and the last frame use the pair they have. Same cost per step."""
    min_pair_coverage: Annotated[float, Range(0, 1)] = 0.0
    """Share of frame t's moving pixels (its motion mask) on which a pair's forward flow must pass the
    forward-backward check for the flow loss to use the pair (an extension; 0 = every pair, the paper). Where the
    optical flow fails on most of a moving surface (fast motion, and the two-interval pairs that span a held-out
    image), the few pixels that still pass the check are no evidence of the motion, yet the loss, a mean over the
    supervised pixels, gives them a whole pair's weight. On the generated kinematic scene the pair from r_0019 to
    r_0020 passes on 146 of its 2213 moving pixels and its target is 20 px off the truth there; the pairs around the
    worst held-out images pass on 9-14 % (docs/motion.md, "Pairs whose flow failed"). Pairs of frames without a motion
    mask are always used. On the generated rigid and soft scenes 0.5 made the val views worse: their pairs at 36-47 %
    still carry the motion of a collision; ``weigh_by_coverage`` is the rule the issue-16 rigid-body setting uses."""
    weigh_by_coverage: bool = False
    """Weigh each pair's flow loss by its coverage: the share of frame t's moving pixels (its motion mask) on which
    its forward flow passed the forward-backward check (an extension; off: every pair weighs the same, the paper).
    The loss of a pair is a mean over its supervised pixels, so a pair whose flow failed on most of a moving surface
    gives its few remaining pixels a whole pair's weight; weighed, it counts about as the mean over the moving pixels
    would, those without a target counting 0. A softer rule than ``min_pair_coverage``, which leaves such pairs out;
    pairs of frames without a motion mask weigh 1."""
    start: Annotated[int, NON_NEGATIVE] = 0
    """First training step that uses LPFM (then every step)."""
    target: FlowTargetKind = "motion"
    """What the rendered flows are matched to. motion (the paper, after MotionGS): the camera-compensated motion flow,
    built with frame t+1's depth (the dataset's, else the model's own render), against flows rendered in camera t at
    both times. total (after GaussianFlow): the optical flow itself, against flows of the Gaussians at t seen by
    camera t and at t+1 (or advected by v) seen by camera t+1; the camera's motion is then part of the rendered
    flow, so the flow supervises where the model puts the surface (its depth) as well as how it moves, and the
    target needs no depth. Both supervise the pixels of the dilated motion mask where the dataset has masks; total
    supervises every consistent pixel where it has none."""

    # optical flow estimation (preprocessing)
    estimator: EstimatorName = "dis"
    """Optical-flow estimator: OpenCV DIS (fast), DeepFlow, Dual TV-L1, or RAFT from local weights."""
    dis_preset: DisPreset = "medium"
    """OpenCV DIS preset (speed against accuracy)."""
    upsample: Annotated[int, AT_LEAST_ONE] = 4
    """Factor the images are enlarged by (bicubic) before an OpenCV estimator runs (RAFT runs at the images' size);
    its flow is averaged back onto the images' pixels and divided by it. DIS matches fixed 8-pixel patches, which on
    small images straddle an object's edge and smooth its motion into the background's: 2 cut the motion-flow
    target's error against the true motion by 40-45 % on the demo and generated scenes, 4 by another 6-32 % on the
    generated ones, and the full method's velocity flow on the generated scenes' val views was closer to the truth at 4 than at 2 in 9 of 10
    runs (docs/motion.md). On this project's 2-core machine a 400x400 flow takes ~0.45 s at 4, ~0.1 s at 2 and ~0.01
    s at 1, once (the flows are cached): ~2 minutes for a 150-frame scene at 4; 1 is the images' own resolution."""
    raft_weights: Path | None = None
    """Local RAFT weights (.pt2 export, TorchScript, or a torchvision state dict); nothing is downloaded."""
    consistency_alpha: Annotated[float, NON_NEGATIVE] = 0.01
    """Forward-backward check |f(p) + b(p + f(p))|^2 < alpha (|f(p)|^2 + |b(p + f(p))|^2) + beta: alpha."""
    consistency_beta: Annotated[float, NON_NEGATIVE] = 0.5
    """The same check's beta, in pixels^2."""
    cache_dir: str = "flow_cache"
    """Where the optical flow is cached: relative to the dataset folder, or an absolute path."""

    # ground-truth motion flow
    mask_dilation: Annotated[int, NON_NEGATIVE] = 3
    """Pixels the motion mask of frame t is dilated by (square structuring element)."""
    motion_threshold: Annotated[float, NON_NEGATIVE] = 1.0
    """Pixels of camera-compensated flow above which a pixel counts as moving (datasets without motion masks)."""
    min_alpha: Annotated[float, Range(0, 1, hi_open=True)] = 0.05
    """Rendered alpha below which a pixel's rendered flow is not supervised."""
    # flow_gt needs frame t+1's depth as the model renders it. Training renders every frame once per epoch, so that
    # depth is usually at hand from frame t+1's own step; otherwise it costs a no-grad deformation and render
    # (~30 ms at 400x400 on a 2-core CPU, against ~3 ms for the decomposition). The depth of a converging model
    # changes slowly.
    target_refresh_steps: Annotated[int, AT_LEAST_ONE] = 300
    """Most steps the rendered depth behind a pair's flow target may be old: the target is rebuilt from frame t+1's
    latest training render when that is younger, else from a render of its own."""
    max_view_change: Annotated[float, Range(0, 180)] = 30.0
    """Degrees: the flow loss is refused on data whose consecutive training views (by time) turn by more than this at
    the median. Optical flow between two views is motion only when they are close: a video's camera turns a few
    degrees a frame (the generated orbits ~6), D-NeRF's synthetic captures jump (median 65-74 degrees), where the
    flow target is hundreds of pixels of noise (training PSNR ~16 on bouncingballs) and the paper trains without
    LPFM. 180 turns the check off."""
    tile_fraction: Annotated[float, Range(0, 1, lo_open=True)] = 1.0
    """Share of the 16x16 pixel tiles holding supervised pixels that the loss reads at a step, drawn at random each
    step (1: every tile). The loss is the mean over the drawn tiles' pixels, a sample of the full one, and only the
    Gaussians that reach them get the t+1 deformation, velocities and flow channels: the flow term's cost falls with
    the share (as L_CMR samples particles rather than taking all)."""

    def __post_init__(self) -> None:
        validate_config(self)
        if not self.cache_dir:
            raise ValueError("FlowConfig.cache_dir must not be empty")
        if self.lambda_depth_change > 0 and self.target != "motion":
            raise ValueError(f"--flow.lambda_depth_change {self.lambda_depth_change} needs --flow.target motion "
                             f"(the depth change is camera t's), got {self.target!r}")

    @property
    def enabled(self) -> bool:
        return self.kind == "lpfm"

    def active(self, step: int) -> bool:
        """Whether LPFM applies at training step ``step``."""
        return self.enabled and step >= self.start
