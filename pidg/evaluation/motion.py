"""The learned motion scored against a dataset's ground-truth motion (:mod:`pidg.data.motion_gt`), not only pixels.

**Flow (pixels).** For each frame of a split, with its camera held fixed, from its time t to t' = the ground-truth
flow's ``next_time`` (t + the dataset's ``frame_interval``; one training-frame interval on the procedural scene):

* *motion flow*: each Gaussian's projected centre displacement between the deformation at t and at t',
  composited with the colour weights (:func:`pidg.data.motion_gt.composited_flow`, the definition the ground
  truth is made with);
* *velocity flow* (runs with a material field): each centre's projected displacement by v (converted from the
  field's physics time to dataset time by the model's :class:`TimeAxis`) times (t' - t), v taken by the run's
  ``FlowConfig.velocity_integration`` (:func:`pidg.flow.interval_velocity`: the paper's v(x, t), or the midpoint
  rule's v at the end of a half step);
* *Gaussian flow*: the affine flow LPFM trains (:mod:`pidg.flow.gaussian_flow`), in the JSON only.

End-point error (EPE) = mean |flow - flow_gt| in pixels over the *scored pixels*: ground-truth dynamic, a surface in
the ground truth (finite flow) and covered by the model (alpha > 0.5), pooled over the frames. The zero-motion EPE
(= mean |flow_gt| there) gives it a scale. Ground-truth flows are resized to the run's images
(:func:`pidg.data.motion_gt.resize_flow`). Frames whose t' lies after the recording (t' > 1) are skipped.
*Per object*: where the frames have depth maps and the truth has triangles, each scored pixel is labelled with the
ground-truth object it shows (:func:`pixel_objects`: its depth lifted to 3D, the object of the nearest point on the
true triangles at the frame's time, none beyond the matching radius below), and the EPEs are also pooled per object:
which bodies carry the error (a fast one's share of the error is larger than its share of the pixels).

**3D velocity.** At each frame time that has a ground-truth vertex sample: every vertex is matched to the nearest
Gaussian deformed to t, if one lies within ``radius`` (world units; default 2 % of the diagonal of the box around
all ground-truth vertex positions); coverage = matched / all vertex samples. Compared with the vertex's velocity
(world units per unit of dataset time): the deformation's central difference (means at t +- h, h = half the
ground-truth frame interval, one-sided at 0 and 1) and the material field's v converted to the same units
(:func:`velocity_per_dataset_time`). Reported: mean |v - v_gt| (per unit of dataset time, and x frame_interval: per
frame), the mean relative error |v - v_gt| / |v_gt| over matched vertices with |v_gt| > 0 and at least
``speed_floor`` (default 10 % of the mean true speed), and the zero-velocity baseline (mean |v_gt|; relative error 1).
Each error is also split along the ray from the frame's camera to the vertex and across it (mean magnitudes): a flow
seen by that camera constrains only the part across its rays, so on the training split the part along them is what
2D flow matching cannot teach. And the first-order floor of the velocity flow: the true velocity's own flow,
x + v_gt(t) (t' - t) projected, against the true displacement x(t') (mean pixels over every vertex in front of the
frame's camera at the times that have a sample at t' too); a curved path makes it non-zero, and no learned v can
go below it by that definition. Beside it the same with the trapezoid (v_gt(t) + v_gt(t')) / 2, a second-order
step like ``--flow.velocity_integration midpoint``'s: what is left of that floor with a second-order rule.

**What the training times determine (given ``train_times``).** A model can be right at every training image's time
and still wrong between them. The floor of that: the true vertex positions known only at the training times, carried
to t and t' by interpolation between them (:func:`positions_between`: linear between the two around each time, or the
cubic through the four nearest), their flow against the true displacement (mean pixels over every vertex in front of
the frame's camera, as the first-order floor; 0 on the training views, and None where t or t' lies outside the
training times). A view whose floor is low is decided by the training images; its error is the model's, not the
split's. Where it lies, at the matched vertices whose Gaussian the view sees (:func:`seen_gaussians`): the model's
motion over [t, t'] against the truth's, projected (px), and its two parts (:func:`_training_times_split`): at the
training times (both motions replaced by their linear interpolation between the training times around t and t')
and between them (the rest: how the model's path bends between training times against the truth's). A model right
at the training times that moves straight between them scores the linear floor in the second part.

**3D tracking (identity over the recording).** At each scored frame's time that has a vertex sample (the anchor),
every vertex is matched to its nearest Gaussian as above; those Gaussians are then followed through every other
ground-truth sample time in [0, 1], and their displacement since the anchor is compared with their vertex's:
error = mean |(g(t) - g(t_a)) - (x(t) - x(t_a))|, travel = mean |x(t) - x(t_a)| (world units; travel is a
standing-still model's error), relative = the pooled error / travel (0: the Gaussians carry the surface along; 1: no
better than standing still), also per ground-truth object, and over the matches whose Gaussian the anchor's view
sees (its compositing weight summed over the image at least :data:`SEEN_MIN_WEIGHT` pixels, :func:`seen_gaussians`):
the nearest Gaussian to a vertex may be one no view shows at that time (behind the surface, or hidden under
others), which neither the pixels nor a flow loss constrain there. Per-frame flow and velocity see a few frame intervals at
most; a model that rebuilds a moving object from other Gaussians as it goes (the positions right, the particles'
identity lost) scores well there and only fails here.

**Spin (rigid objects).** From each scored view's time t that has a vertex sample at t and t + ``frame_interval``
(at most 1, as for the flows): every ground-truth object whose vertices move rigidly over that interval (the best
rigid fit leaves an RMS residual of at most :data:`RIGID_TOLERANCE` of the object's size) and turn at least
:data:`SPIN_FLOOR_DEG` degrees is scored:
its true rotation R (:func:`best_rotation` of its vertices at t onto t + interval) against the rotation R_m of the
distinct Gaussians matched to its vertices at t (the 3D velocity's matching), deformed to t and t + interval; error
= the angle of R_m R^T (degrees; a model whose Gaussians do not turn scores the true angle). Reported: the mean true,
learned and error angles per interval, relative = pooled error / pooled true angle (0: the particles spin with the
body; 1: no better than not turning), also per object. A model that draws a body with a relay of Gaussians (each
carried a short way, then handed on) moves the texture without turning it, and fails here.

**The flow target (training pairs).** What LPFM pulls the model's flows towards, the motion-flow target of each
training pair (:func:`pidg.flow.model_flow_target`: the optical flow minus the camera flow of frame t+1's depth, the
dataset's or the model's own render, inside the motion mask), scored against the true flow of frame t on the pixels
it supervises that the truth calls dynamic: the best the flow loss alone can teach (:func:`evaluate_flow_target`).
Beside it the model's motion and velocity flows over the same pairs, against that target (how closely the model
follows what it is taught) and against the truth, on those pixels and on the true dynamic surface the target leaves
out: a flow error splits into the target's and the model's distance from it. Pairs whose t+1 is not t +
``frame_interval`` (a held-out image between them) are skipped.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as nn_functional
from torch import Tensor

from pidg.data.motion_gt import MotionGroundTruth, VertexMotion, composited_flow, projected_displacement, resize_flow
from pidg.data.scene import DatasetError, Frame
from pidg.evaluation.charts import svg_chart
from pidg.flow import FlowCache, FlowConfig, FlowTarget, VelocityIntegration, interval_velocity, model_flow_target
from pidg.flow.decomposition import backproject
from pidg.flow.gaussian_flow import decode_flows, gaussian_flow_features
from pidg.flow.rigid_tracks import rigid_fit, rotation_angle
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.time_axis import TimeAxis
from pidg.render import Camera

RADIUS_FRACTION = 0.02
"""Default matching radius: this fraction of the diagonal of the ground-truth vertices' bounding box."""
SPEED_FLOOR_FRACTION = 0.1
"""Default speed floor of the relative error: this fraction of the mean true speed."""
RIGID_TOLERANCE = 0.01
"""An object moves rigidly over an interval when its best rigid fit's RMS residual is at most this fraction of the
diagonal of its vertices' bounding box (a generator's rigid body fits to float precision; cloth does not)."""
SPIN_FLOOR_DEG = 1.0
"""Intervals in which a rigid object turns less than this (degrees) are not scored for spin: there is no rotation to
learn, and the scatter of the matched Gaussians would make the error a measure of noise."""
MODEL_MIN_ALPHA = 0.5
"""A pixel is covered by the model where its accumulated alpha exceeds this."""
_TIME_TOL = 1e-6


def velocity_per_dataset_time(v: Tensor, time_axis: TimeAxis) -> Tensor:
    """A material field's velocity, world units per *physics* time unit, in world units per unit of *dataset*
    time: tau = t * S, so dx/dt = dx/dtau * S with S = ``time_axis.physics_per_dataset``."""
    return v * time_axis.physics_per_dataset


# ---- results ------------------------------------------------------------------------------------------------------
@dataclass
class FlowScores:
    """End-point errors in pixels, pooled over the scored pixels of every scored frame."""

    frames: int
    pixels: int
    motion_flow_epe: float | None
    velocity_flow_epe: float | None  # None without a material field
    gaussian_flow_epe: float | None
    zero_motion_epe: float | None  # mean |flow_gt| on the scored pixels
    skipped: list[str] = field(default_factory=list)  # frames whose t + frame_interval lies after the recording
    velocity_integration: VelocityIntegration = "euler"  # how the velocity flow carried the particles over t' - t
    #: per ground-truth object (:func:`pixel_objects`; "(none)": pixels no object's surface lies near): its scored
    #: pixels and their motion / velocity / zero-motion EPE (px), pooled over the frames with a depth map; empty
    #: without depth maps or triangles
    per_object: dict[str, dict[str, float | int | None]] = field(default_factory=dict)


@dataclass
class VelocityScores:
    """3D velocity of the Gaussians nearest to the ground-truth vertices (units: world units per unit of dataset
    time; ``*_per_frame``: x frame_interval, world units per frame interval)."""

    times: int
    vertex_samples: int
    matched: int
    coverage: float | None
    radius: float
    fd_step: float
    speed_floor: float | None
    relative_samples: int  # matched samples with |v_gt| >= speed_floor
    match_distance: float | None  # mean distance from a matched vertex to its Gaussian (world units)
    deformation_mae: float | None
    deformation_mae_per_frame: float | None
    deformation_rel: float | None
    field_mae: float | None  # None without a material field
    field_mae_per_frame: float | None
    field_rel: float | None
    zero_mae: float | None  # the zero-velocity baseline: mean |v_gt| of the matched vertices
    zero_mae_per_frame: float | None
    zero_rel: float | None
    # mean |error| along / across the ray from the frame's camera to each vertex (same units; zero: |v_gt|'s parts)
    deformation_along_ray: float | None = None
    deformation_across_ray: float | None = None
    field_along_ray: float | None = None
    field_across_ray: float | None = None
    zero_along_ray: float | None = None
    zero_across_ray: float | None = None
    truth_velocity_flow_px: float | None = None  # the true velocity's first-order flow vs the true displacement (px)
    # the same with the trapezoid of the true velocities at t and t' (second order, as the midpoint rule)
    truth_velocity_flow_second_order_px: float | None = None
    # the true positions known at the training times only, interpolated to t and t' linearly / by the cubic through
    # the four nearest: their flow vs the true displacement (px; None without training times)
    training_times_linear_flow_px: float | None = None
    training_times_cubic_flow_px: float | None = None
    # the model's motion over [t, t'] at the matched vertices its view sees, against the truth's (px): the whole error,
    # its part at the training times and its part between them (how the paths bend between the training times)
    seen_flow_px: float | None = None
    seen_flow_at_training_times_px: float | None = None
    seen_flow_between_training_times_px: float | None = None
    # |v - the deformation's velocity| / |v_gt| at the matched vertices (as the *_rel): how far the material field's v
    # is from the particles it should move with, whatever the truth (docs/motion.md, "The material field's v lags the
    # motion"); None without a material field
    field_lag_rel: float | None = None


@dataclass
class TrackingScores:
    """Long-range 3D motion (world units): the Gaussians matched to the vertices at the anchor times, followed
    through every ground-truth sample time (see the module docstring)."""

    anchors: int
    samples: int  # (anchor, other time, matched vertex) triples
    coverage: float | None  # matched vertices / vertices, at the anchors
    error: float | None  # mean |(g(t) - g(t_a)) - (x(t) - x(t_a))|
    travel: float | None  # mean |x(t) - x(t_a)|: the error of Gaussians that stand still
    relative: float | None  # pooled error / travel
    per_object: dict[str, float | None] = field(default_factory=dict)  # relative, per ground-truth object
    seen_share: float | None = None  # share of the matches whose Gaussian the anchor's view sees (SEEN_MIN_WEIGHT)
    seen_relative: float | None = None  # relative, over those matches only


@dataclass
class SpinScores:
    """Rigid objects' rotation over one ground-truth frame interval, true against learned (degrees per interval; see
    the module docstring)."""

    intervals: int  # (view time, rigid object) pairs scored
    true_deg: float | None  # mean true rotation angle
    learned_deg: float | None  # mean rotation angle of the matched Gaussians
    error_deg: float | None  # mean angle of R_learned R_true^T
    relative: float | None  # pooled error / pooled true angle
    per_object: dict[str, float | None] = field(default_factory=dict)  # relative, per scored object


@dataclass
class TargetScores:
    """The training pairs' motion-flow target against the true flow of their first frame (pixels), pooled over the
    scored pairs. Scored pixels: supervised by the target, and a dynamic surface in the truth."""

    pairs: int
    pixels: int
    depth: str  # whose depth compensated the camera's motion: "dataset" or "model" (the run's own render at t+1)
    target_epe: float | None  # mean |target - flow_gt| on the scored pixels
    zero_motion_epe: float | None  # mean |flow_gt| there
    coverage: float | None  # scored pixels / true dynamic surface pixels of the scored pairs
    off_dynamic_pixels: int  # supervised pixels the truth calls static or background
    off_dynamic_flow: float | None  # mean |target| on them (the truth there: 0 or no surface)
    skipped: list[str] = field(default_factory=list)  # pairs (first frame) spanning more than one frame interval
    #: per scored pair: first frame's name and dataset time, its scored pixels and their target / zero-motion EPE in
    #: pixels (None: no pixel scored): where in the recording the optical flow misleads the flow loss (a collision, a
    #: fast phase); and the model's motion / velocity flow against the target there (motion_vs_target_epe,
    #: velocity_vs_target_epe): where the model does not follow what it is taught
    per_pair: list[dict[str, Any]] = field(default_factory=list)
    # The model's flows over the same pairs (t to t+1 in camera t, the run's velocity rule). Its error against the truth
    # on the scored pixels is at most target_epe + its distance from the target: the two parts apart, and the true
    # dynamic surface the target leaves out (where only the images and the other terms teach the motion).
    model_pixels: int = 0  # scored pixels the model covers (alpha > MODEL_MIN_ALPHA)
    motion_vs_target_epe: float | None = None  # mean |motion flow - target| there
    velocity_vs_target_epe: float | None = None  # mean |velocity flow - target| there (None: no material field)
    motion_epe: float | None = None  # mean |motion flow - flow_gt| there
    velocity_epe: float | None = None  # mean |velocity flow - flow_gt| there
    unsupervised_pixels: int = 0  # true dynamic surface the target does not supervise and the model covers
    motion_unsupervised_epe: float | None = None  # mean |motion flow - flow_gt| there
    velocity_unsupervised_epe: float | None = None  # mean |velocity flow - flow_gt| there


@dataclass
class MotionEvaluation:
    """Everything :func:`evaluate_motion` measured (``to_dict`` -> RUN/eval_SPLIT/motion_gt.json)."""

    split: str
    dataset: str
    frame_interval: float
    flow: FlowScores
    velocity: VelocityScores
    per_frame: list[dict[str, Any]]
    units: dict[str, str] = field(default_factory=lambda: dict(UNITS))
    target: TargetScores | None = None  # the training pairs' flow target (:func:`evaluate_flow_target`)
    tracking: TrackingScores | None = None  # None: fewer than two vertex sample times
    spin: SpinScores | None = None  # None: no rigidly moving object turned in a scored interval

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def columns(self) -> dict[str, float | None]:
        """The figures a benchmark table shows (keys prefixed ``gt_``)."""
        return {
            "gt_motion_flow_epe": self.flow.motion_flow_epe,
            "gt_velocity_flow_epe": self.flow.velocity_flow_epe,
            "gt_zero_motion_epe": self.flow.zero_motion_epe,
            "gt_velocity_rel_deformation": self.velocity.deformation_rel,
            "gt_velocity_rel_field": self.velocity.field_rel,
            "gt_coverage": self.velocity.coverage,
            "gt_track_rel": None if self.tracking is None else self.tracking.relative,
            "gt_track_rel_seen": None if self.tracking is None else self.tracking.seen_relative,
            "gt_spin_rel": None if self.spin is None else self.spin.relative,
            "gt_target_flow_epe": None if self.target is None else self.target.target_epe,
        }

    def summary(self) -> str:
        """One line: the flow EPEs against zero motion, and the 3D velocity errors against zero velocity."""
        f, v = self.flow, self.velocity
        rule = "" if f.velocity_integration == "euler" else f" ({f.velocity_integration} rule)"
        return (
            f"motion vs ground truth ({self.split}, {f.frames} frames, {f.pixels} px): motion-flow EPE {_px(f.motion_flow_epe)}, "
            f"velocity-flow EPE {_px(f.velocity_flow_epe)}{rule}, zero motion {_px(f.zero_motion_epe)}"
            + (f" ({_objects_text(f)})" if len(f.per_object) > 1 else "") + "; 3D velocity "
            f"(coverage {_pct(v.coverage)} within {v.radius:.3g} world units): relative error deformation {_num(v.deformation_rel)}, "
            f"field v {_num(v.field_rel)} ({_num(v.field_lag_rel)} off the deformation's), zero {_num(v.zero_rel)}; "
            f"along / across the camera rays (world units per unit of dataset time): deformation "
            f"{_num(v.deformation_along_ray)} / {_num(v.deformation_across_ray)}, field v {_num(v.field_along_ray)} / "
            f"{_num(v.field_across_ray)}, zero {_num(v.zero_along_ray)} / {_num(v.zero_across_ray)}; the true "
            f"velocity's own first-order flow {_px(v.truth_velocity_flow_px)} (second order "
            f"{_px(v.truth_velocity_flow_second_order_px)}) from the true displacement"
            + ("" if v.training_times_linear_flow_px is None else
               f"; the truth known at the training times only, interpolated linearly "
               f"{_px(v.training_times_linear_flow_px)} (cubic {_px(v.training_times_cubic_flow_px)})")
            + ("" if v.seen_flow_px is None else
               f"; the model's motion at the seen matched vertices {_px(v.seen_flow_px)} off, at the training times "
               f"{_px(v.seen_flow_at_training_times_px)}, between them {_px(v.seen_flow_between_training_times_px)}")
            + ("" if self.tracking is None else f"; {_tracking_text(self.tracking)}")
            + ("" if self.spin is None else f"; {_spin_text(self.spin)}")
            + ("" if self.target is None else f"; {_target_text(self.target)}")
        )

    def per_frame_chart(self) -> str:
        """The flow errors of every scored frame against its dataset time, as an SVG line chart (EPE in px): where
        in the recording the learned motion goes wrong (a collision, a fast phase), beside zero motion's error, the
        floor of what the training times determine (the truth known there only, linear between them) and, where
        scored, the flow target's error on the training pairs (where the flow loss itself teaches wrong)."""
        names = {FLOW_KEYS["motion"]: "motion flow (deformation)", FLOW_KEYS["velocity"]: "velocity flow (field v)",
                 FLOW_KEYS["zero"]: "zero motion", "training_times_linear_px": "truth known at training times (linear)"}
        rows = sorted((r for r in self.per_frame if r.get(FLOW_KEYS["zero"]) is not None), key=lambda r: r["time"])
        series = {label: [(r["time"], r[key]) for r in rows if r.get(key) is not None] for key, label in names.items()}
        if self.target is not None:
            pairs = sorted((r for r in self.target.per_pair if r["target_epe"] is not None), key=lambda r: r["time"])
            series["flow target (training pairs)"] = [(r["time"], r["target_epe"]) for r in pairs]
            series["v flow from its target (training pairs)"] = [
                (r["time"], r["velocity_vs_target_epe"]) for r in pairs if r.get("velocity_vs_target_epe") is not None]
        return svg_chart({k: v for k, v in series.items() if v}, f"dataset time ({self.split} views)", "end-point error (px)",
                         y_floor=0.0, empty_note="no view was scored")

    def tracking_chart(self) -> str:
        """The 3D tracking of every anchor (a scored view's time) as an SVG line chart in world units: how far its
        Gaussians miss their vertices' displacement over the recording, beside that displacement (standing still's
        error). Where the two lines meet, the Gaussians there do not follow the surface."""
        rows = sorted((r for r in self.per_frame if r.get("track_error") is not None), key=lambda r: r["time"])
        series = {"tracking error (Gaussians)": [(r["time"], r["track_error"]) for r in rows],
                  "travel (standing still)": [(r["time"], r["track_travel"]) for r in rows]}
        return svg_chart({k: v for k, v in series.items() if v}, f"anchor time ({self.split} views)",
                         "mean distance (world units)", y_floor=0.0, empty_note="no vertex was matched")


UNITS = {
    "flow": "pixels of the run's images, from t to t + frame_interval, camera held fixed",
    "velocity": "world units per unit of dataset time (x frame_interval: *_per_frame, world units per frame interval)",
    "radius": "world units",
    "relative": "velocity.*_rel (field_lag_rel too): a share of the true speed |v_gt| (0: right; 1: as far off as "
                "standing still)",
}


def _objects_text(f: FlowScores) -> str:
    key = "velocity_flow_epe" if f.velocity_flow_epe is not None else "motion_flow_epe"
    parts = [f"{name} {_px(o[key])} on {_pct(o['pixels'] / f.pixels if f.pixels else None)}"
             for name, o in f.per_object.items()]
    return f"by object, {key.split('_')[0]} flow on its share of the pixels: " + ", ".join(parts)


def _tracking_text(t: TrackingScores) -> str:
    objects = "".join(f"; {name} {_num(rel)}" for name, rel in t.per_object.items()) if len(t.per_object) > 1 else ""
    return (f"3D tracking from the {t.anchors} view times through the recording: error {_num(t.error)} vs travel "
            f"{_num(t.travel)} world units (relative {_num(t.relative)}{objects}; the {_pct(t.seen_share)} whose "
            f"Gaussian the view sees: {_num(t.seen_relative)})")


def _target_text(t: TargetScores) -> str:
    model = (f"; the model from it: motion {_px(t.motion_vs_target_epe)}, velocity {_px(t.velocity_vs_target_epe)} "
             f"(from the truth there: {_px(t.motion_epe)}, {_px(t.velocity_epe)}); on the {t.unsupervised_pixels} true "
             f"dynamic px it leaves out: motion {_px(t.motion_unsupervised_epe)}, velocity "
             f"{_px(t.velocity_unsupervised_epe)}") if t.model_pixels or t.unsupervised_pixels else ""
    return (f"flow target (train pairs, {t.depth} depth): EPE {_px(t.target_epe)} vs zero {_px(t.zero_motion_epe)}, "
            f"covering {_pct(t.coverage)}{model}")


def _spin_text(s: SpinScores) -> str:
    objects = "".join(f"; {name} {_num(rel)}" for name, rel in s.per_object.items()) if len(s.per_object) > 1 else ""
    return (f"rigid spin over {s.intervals} object intervals: true {_num(s.true_deg)}°, learned {_num(s.learned_deg)}°, "
            f"error {_num(s.error_deg)}° a frame interval (relative {_num(s.relative)}{objects})")


def _px(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f} px"


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def ratio_or_none(total: float | None, count: float) -> float | None:
    """total / count, or None where nothing was counted (a mean over no pixels, samples or vertices) or the total is
    None (a flow the model does not have)."""
    return total / count if count and total is not None else None


def _mean(x: Tensor) -> float | None:
    return float(x.mean()) if x.numel() else None


def _times(x: float | None, k: float) -> float | None:
    return None if x is None else x * k


# ---- flows --------------------------------------------------------------------------------------------------------
@dataclass
class ModelFlows:
    """A model's flows [H, W, 2] in pixels in one camera from t to t' (NaN where alpha < 0.5), and its alpha."""

    motion: Tensor
    velocity: Tensor | None
    gaussian: Tensor
    alpha: Tensor


@torch.no_grad()
def model_flows(
    model: DynamicGaussians, camera: Camera, t: float, t1: float, integration: VelocityIntegration = "euler"
) -> ModelFlows:
    """The model's motion, velocity and Gaussian flows from dataset time t to t1 in ``camera`` (held fixed), in
    one rasterizer pass: [Gaussian-flow channels | centre displacement | velocity displacement] as features; the
    velocity by ``integration`` (:func:`pidg.flow.interval_velocity`)."""
    state_t, state_t1 = model.at(t), model.at(t1)
    means = state_t.means
    channels = [
        gaussian_flow_features(camera, means, state_t.quats, state_t.log_scales.exp(), model.gaussians.opacities,
                               state_t1.means, state_t1.quats, state_t1.log_scales.exp()),
        projected_displacement(camera, means, state_t1.means),
    ]
    if model.material_field is not None:
        v = velocity_per_dataset_time(interval_velocity(model, t, t1 - t, means, integration=integration), model.time_axis)
        channels.append(projected_displacement(camera, means, means + v * (t1 - t)))
    out = model.render_state(state_t, camera, torch.cat(channels, dim=-1))
    assert out.features is not None
    gaussian = decode_flows(out.features[..., :6], out.alpha)[0]
    centre = composited_flow(out.features[..., 6:], out.alpha, MODEL_MIN_ALPHA)
    gaussian = torch.where(torch.isfinite(centre[..., :1]), gaussian, torch.full_like(gaussian, float("nan")))
    velocity = centre[..., 2:4] if model.material_field is not None else None
    return ModelFlows(centre[..., :2], velocity, gaussian, out.alpha)


def _epe_sum(flow: Tensor | None, gt: Tensor, mask: Tensor) -> float | None:
    return None if flow is None else float((flow - gt).norm(dim=-1)[mask].double().sum())


# ---- the flow target --------------------------------------------------------------------------------------------
def target_flow_sums(target: FlowTarget, flow_gt: Tensor, dynamic: Tensor) -> dict[str, float]:
    """Sums over one pair: |target - flow_gt| and |flow_gt| on the scored pixels (supervised, true dynamic surface),
    their count, the true dynamic surface's count, and |target| and the count of supervised pixels off it.
    ``flow_gt`` [H, W, 2] (NaN: no surface) and ``dynamic`` [H, W] at the target's size."""
    surface = dynamic & torch.isfinite(flow_gt).all(-1)
    scored = target.valid & surface
    off = target.valid & ~surface
    return {
        "error": float((target.flow - flow_gt).norm(dim=-1)[scored].double().sum()),
        "zero": float(flow_gt.norm(dim=-1)[scored].double().sum()),
        "pixels": float(scored.sum()),
        "dynamic": float(surface.sum()),
        "off_flow": float(target.flow.norm(dim=-1)[off].double().sum()),
        "off_pixels": float(off.sum()),
    }


def model_target_sums(flows: ModelFlows, target: FlowTarget, flow_gt: Tensor, dynamic: Tensor) -> dict[str, float | None]:
    """Sums over one pair of the model's flows (``flows``, t to t+1 in camera t) on the true dynamic surface it covers:
    where the target supervises, |flow - target| and |flow - flow_gt| and their count; where it does not,
    |flow - flow_gt| and their count. Velocity sums are None without a material field."""
    surface = dynamic & torch.isfinite(flow_gt).all(-1) & (flows.alpha > MODEL_MIN_ALPHA)
    supervised, left = surface & target.valid, surface & ~target.valid
    return {
        "pixels": float(supervised.sum()),
        "motion_vs_target": _epe_sum(flows.motion, target.flow, supervised),
        "velocity_vs_target": _epe_sum(flows.velocity, target.flow, supervised),
        "motion": _epe_sum(flows.motion, flow_gt, supervised),
        "velocity": _epe_sum(flows.velocity, flow_gt, supervised),
        "left_pixels": float(left.sum()),
        "motion_left": _epe_sum(flows.motion, flow_gt, left),
        "velocity_left": _epe_sum(flows.velocity, flow_gt, left),
    }


def _add_sums(total: dict[str, float | None], sums: dict[str, float | None]) -> None:
    """Adds ``sums`` into ``total`` key by key (None stays None: a flow the model does not have)."""
    for key, value in sums.items():
        total[key] = None if value is None else total.get(key, 0.0) + value


@torch.no_grad()
def evaluate_flow_target(model: DynamicGaussians, cache: FlowCache, config: FlowConfig, truth: MotionGroundTruth) -> TargetScores | None:
    """The motion-flow target of every training pair of ``cache`` (built as training builds it, from frame t+1's
    dataset depth or this model's render) against the truth, and the model's flows over those pairs (the velocity by
    ``config.velocity_integration``) against the target and the truth (:func:`model_target_sums`); None for the
    total-flow target (``config.target``), which holds the camera's motion too."""
    if config.target != "motion":
        return None
    sums = dict.fromkeys(("error", "zero", "pixels", "dynamic", "off_flow", "off_pixels"), 0.0)
    model_sums: dict[str, float | None] = {}
    skipped, depth, per_pair = [], "dataset", []
    for k in range(len(cache)):
        pair = cache.pair(k)
        gt = truth.frame_flow(pair.frame0.name)
        if abs(gt.next_time - pair.frame1.time) > _TIME_TOL:
            skipped.append(pair.frame0.name)
            continue
        target, rendered = model_flow_target(model, pair, None, config)
        depth = "model" if rendered is not None else depth
        flow_gt, dynamic = resize_flow(torch.from_numpy(gt.flow), torch.from_numpy(gt.dynamic), (pair.frame0.width, pair.frame0.height))
        flow_gt, dynamic = flow_gt.to(target.flow.device), dynamic.to(target.flow.device)
        pair_sums = target_flow_sums(target, flow_gt, dynamic)
        for key, value in pair_sums.items():
            sums[key] += value
        flows = model_flows(model, pair.frame0.camera, pair.frame0.time, pair.frame1.time, config.velocity_integration)
        pair_model = model_target_sums(flows, target, flow_gt, dynamic)
        _add_sums(model_sums, pair_model)
        m, covered = pair_sums["pixels"], pair_model["pixels"]
        per_pair.append({"frame": pair.frame0.name, "time": pair.frame0.time, "pixels": int(m),
                         "target_epe": ratio_or_none(pair_sums["error"], m), "zero_motion_epe": ratio_or_none(pair_sums["zero"], m),
                         "motion_vs_target_epe": ratio_or_none(pair_model["motion_vs_target"], covered),
                         "velocity_vs_target_epe": ratio_or_none(pair_model["velocity_vs_target"], covered)})
    n, covered, left = sums["pixels"], model_sums.get("pixels") or 0.0, model_sums.get("left_pixels") or 0.0
    return TargetScores(
        pairs=len(per_pair), pixels=int(n), depth=depth,
        target_epe=ratio_or_none(sums["error"], n), zero_motion_epe=ratio_or_none(sums["zero"], n),
        coverage=ratio_or_none(n, sums["dynamic"]), off_dynamic_pixels=int(sums["off_pixels"]),
        off_dynamic_flow=ratio_or_none(sums["off_flow"], sums["off_pixels"]), skipped=skipped, per_pair=per_pair,
        model_pixels=int(covered), motion_vs_target_epe=ratio_or_none(model_sums.get("motion_vs_target"), covered),
        velocity_vs_target_epe=ratio_or_none(model_sums.get("velocity_vs_target"), covered),
        motion_epe=ratio_or_none(model_sums.get("motion"), covered), velocity_epe=ratio_or_none(model_sums.get("velocity"), covered),
        unsupervised_pixels=int(left), motion_unsupervised_epe=ratio_or_none(model_sums.get("motion_left"), left),
        velocity_unsupervised_epe=ratio_or_none(model_sums.get("velocity_left"), left),
    )


# ---- 3D velocity --------------------------------------------------------------------------------------------------
def nearest_gaussians(points: Tensor, means: Tensor, max_elements: int = 1 << 24) -> tuple[Tensor, Tensor]:
    """For points [V, 3]: the index [V] of the nearest of ``means`` [N, 3] and its distance [V], in chunks of at
    most ``max_elements`` distances (memory stays bounded for any N)."""
    chunk = max(1, max_elements // max(len(means), 1))
    idx = torch.cat([torch.cdist(points[i : i + chunk], means).argmin(dim=1) for i in range(0, len(points), chunk)])
    return idx, (points - means[idx]).norm(dim=-1)


def default_radius(truth: MotionGroundTruth) -> float:
    """:data:`RADIUS_FRACTION` of the diagonal of the box around every ground-truth vertex position."""
    p = truth.vertices.positions.reshape(-1, 3)
    return RADIUS_FRACTION * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) if len(p) else 0.0


@torch.no_grad()
def _velocity_at(model: DynamicGaussians, t: float, means: Tensor, points: Tensor, radius: float, h: float) -> dict[str, Tensor]:
    """Matched-vertex mask, the matched Gaussians and their distances, and the two model velocities (dataset time)
    at the matched vertices; ``means``: the Gaussians' centres at t."""
    idx, dist = nearest_gaussians(points, means)
    hit = dist <= radius
    idx = idx[hit]
    out = {"hit": hit, "gaussians": idx, "distance": dist[hit], "deformation": model.motion_velocity(t, h)[idx]}
    if model.material_field is not None:
        out["field"] = velocity_per_dataset_time(model.velocities(t, means)[idx], model.time_axis)
    return out


# ---- the whole evaluation -----------------------------------------------------------------------------------------
FLOW_KEYS = {"motion": "motion_flow_epe", "velocity": "velocity_flow_epe", "gaussian": "gaussian_flow_epe", "zero": "zero_motion_epe"}


@dataclass
class FrameFlows:
    """One scored frame's flows at the run's image size, for pictures: the true motion flow [H, W, 2] (pixels; NaN
    where the truth has no surface), the model's flows, and the scored pixels [H, W] (bool) the errors average over."""

    frame: Frame
    truth: Tensor
    model: ModelFlows
    scored: Tensor


def _frame_flows(
    model: DynamicGaussians, frame: Frame, flow: np.ndarray, dynamic: np.ndarray, t1: float, integration: VelocityIntegration
) -> FrameFlows:
    """The truth and the model's flows of one frame, and its scored pixels."""
    flow_gt, dyn = resize_flow(torch.from_numpy(flow), torch.from_numpy(dynamic), (frame.width, frame.height))
    flow_gt, dyn = flow_gt.to(model.device), dyn.to(model.device)
    flows = model_flows(model, frame.camera, frame.time, t1, integration)
    return FrameFlows(frame, flow_gt, flows, dyn & torch.isfinite(flow_gt).all(-1) & (flows.alpha > MODEL_MIN_ALPHA))


MESH_SAMPLES = 50_000
"""About this many points are sampled on the ground-truth triangles to label a frame's pixels by object."""
NO_OBJECT = "(none)"


def surface_samples(truth: MotionGroundTruth, t: float) -> tuple[Tensor, Tensor] | None:
    """Points [S, 3] (world units) on the ground-truth triangles at dataset time ``t``, a barycentric grid on each
    (about :data:`MESH_SAMPLES` in all), and the index in ``truth.objects`` of each one's object [S]; None without
    triangles or a vertex sample at ``t``."""
    vertices = truth.vertices
    if not len(vertices.faces) or not _has_sample(truth, t):
        return None
    faces = torch.as_tensor(vertices.faces, dtype=torch.long)
    corners = torch.as_tensor(vertices.positions[vertices.index_of(t, _TIME_TOL)], dtype=torch.float64)[faces]
    steps = max(1, int(math.sqrt(2 * MESH_SAMPLES / len(faces))) - 1)  # (steps + 1)(steps + 2) / 2 per triangle
    i, j = torch.meshgrid(torch.arange(steps + 1), torch.arange(steps + 1), indexing="ij")
    a, b = (i[i + j <= steps] / steps).double(), (j[i + j <= steps] / steps).double()
    weights = torch.stack([1 - a - b, a, b], dim=1)  # [Q, 3] barycentric
    points = torch.einsum("qk,fkd->fqd", weights, corners).reshape(-1, 3)
    return points, truth.vertex_objects()[faces[:, 0]].repeat_interleave(len(weights))


def pixel_objects(frame: Frame, truth: MotionGroundTruth, pixels: Tensor, radius: float) -> Tensor | None:
    """The ground-truth object (index in ``truth.objects``; -1 where no object's surface lies within ``radius`` world
    units) of each of ``frame``'s ``pixels`` [H, W] (bool) in row-major order [K]: the pixel's depth lifted to 3D
    (:func:`pidg.flow.decomposition.backproject`), labelled by the nearest of :func:`surface_samples`. None
    where the frame has no depth map, or the truth no triangles or no vertex sample at the frame's time."""
    samples = None if frame.depth is None else surface_samples(truth, frame.time)
    if samples is None:
        return None
    points, objects = samples
    lifted = backproject(frame.depth.cpu().double(), frame.camera.to("cpu"))[pixels.cpu()]
    nearest, distance = nearest_gaussians(lifted, points)
    return torch.where(distance <= radius, objects[nearest], torch.full_like(nearest, -1))


def _pixel_errors(flows: FrameFlows) -> dict[str, Tensor | None]:
    """|flow - flow_gt| (px, float64, CPU) at each of one frame's scored pixels [K] per flow (None: the model has no
    such flow), and ``zero``: |flow_gt| there."""
    flow_gt, mask, m = flows.truth[flows.scored], flows.scored, flows.model
    errors = {key: None if flow is None else (flow[mask] - flow_gt).norm(dim=-1).double().cpu()
              for key, flow in (("motion", m.motion), ("velocity", m.velocity), ("gaussian", m.gaussian))}
    errors["zero"] = flow_gt.norm(dim=-1).double().cpu()
    return errors


def _object_flow_sums(errors: dict[str, Tensor | None], labels: Tensor) -> dict[int, dict[str, float | None]]:
    """Per object label of the scored pixels (:func:`pixel_objects`): their number ("pixels") and the sums of their
    errors (:func:`_pixel_errors`) per flow (None: the model has no such flow)."""
    out = {}
    for label in labels.unique().tolist():
        rows = labels == label
        out[label] = {"pixels": float(rows.sum()),
                      **{key: None if e is None else float(e[rows].sum()) for key, e in errors.items()}}
    return out


def _object_means(sums: dict[int, dict[str, float | None]], names: list[str]) -> dict[str, dict[str, float | int | None]]:
    """Per object name (label -1: :data:`NO_OBJECT`, last): its pixels and mean EPEs (px) from
    :func:`_object_flow_sums`' sums."""
    out = {}
    for label, s in sorted(sums.items(), key=lambda item: (item[0] < 0, item[0])):
        n = s["pixels"]
        out[names[label] if label >= 0 else NO_OBJECT] = {
            "pixels": int(n), **{FLOW_KEYS[key]: None if s[key] is None or not n else s[key] / n
                                 for key in ("motion", "velocity", "zero")}}
    return out


def _frame_flow_sums(errors: dict[str, Tensor | None]) -> tuple[dict[str, float | None], int]:
    """Sums of one frame's errors (:func:`_pixel_errors`) over its scored pixels per flow (None: the model has no
    such flow), and their number."""
    return {key: None if e is None else float(e.sum()) for key, e in errors.items()}, len(errors["zero"])


@torch.no_grad()
def evaluate_motion(
    model: DynamicGaussians,
    frames: Sequence[Frame],
    truth: MotionGroundTruth,
    split: str = "test",
    radius: float | None = None,
    fd_step: float | None = None,
    speed_floor: float | None = None,
    velocity_integration: VelocityIntegration = "euler",
    on_frame: Callable[[FrameFlows], None] | None = None,
    train_times: Sequence[float] | None = None,
) -> MotionEvaluation:
    """Score the model's motion on ``frames`` against ``truth`` (see the module docstring for every definition).

    ``radius``: vertex-to-Gaussian matching radius in world units (default :func:`default_radius`); ``fd_step``:
    the deformation's central-difference step in dataset time (default half the ground-truth frame interval);
    ``speed_floor``: smallest true speed counted in the relative error, world units per unit of dataset time
    (default :data:`SPEED_FLOOR_FRACTION` of the mean true speed at the scored times); ``velocity_integration``: the
    rule the velocity flow carries particles by, the run's ``FlowConfig.velocity_integration``; ``on_frame``: called
    with each scored frame's flows (pictures: :func:`pidg.evaluation.visualize.truth_flow_comparison`);
    ``train_times``: the run's training images' dataset times, for the floor of what they determine (the module
    docstring; skipped without them)."""
    if radius is not None and not radius > 0:
        raise ValueError(f"motion evaluation: the matching radius must be > 0 world units, got {radius}")
    radius = default_radius(truth) if radius is None else float(radius)
    h = 0.5 * truth.frame_interval if fd_step is None else float(fd_step)
    sums = dict.fromkeys(FLOW_KEYS, 0.0)
    pixels, scored, skipped, per_frame = 0, 0, [], []
    gathered: dict[str, list[Tensor]] = {
        "speed_all": [], "speed": [], "distance": [], "deformation": [], "field": [], "ray": [], "v_gt": [], "euler": [],
        "second_order": [], "training_times_linear": [], "training_times_cubic": [], "seen_flow": [],
        "seen_flow_at_training_times": [], "seen_flow_between_training_times": [],
    }
    matches: dict[float, tuple[Tensor, Tensor, Tensor]] = {}  # sample time -> matched vertices, their Gaussians, seen
    known = [x for x in train_times or () if _has_sample(truth, x)]  # the training times with a vertex sample
    object_names = [o.name for o in truth.objects]
    object_sums: dict[int, dict[str, float | None]] = {}
    for frame in frames:
        record: dict[str, Any] = {"view": frame.name, "time": frame.time}
        gt = truth.frame_flow(frame.name)
        if abs(gt.time - frame.time) > _TIME_TOL:
            raise DatasetError(truth.flow_path(frame.name), f"flow is for t = {gt.time:.6f}, the frame is at t = {frame.time:.6f}")
        if gt.next_time > 1.0 + _TIME_TOL:  # the model is not defined after its recording
            skipped.append(frame.name)
        else:
            flows = _frame_flows(model, frame, gt.flow, gt.dynamic, gt.next_time, velocity_integration)
            errors = _pixel_errors(flows)
            frame_sums, n = _frame_flow_sums(errors)
            if on_frame is not None:
                on_frame(flows)
            labels = pixel_objects(frame, truth, flows.scored, radius)
            if labels is not None:
                frame_objects = _object_flow_sums(errors, labels)
                record["objects"] = _object_means(frame_objects, object_names)
                for o, v in frame_objects.items():
                    total = object_sums.setdefault(o, dict.fromkeys(v, 0.0))
                    for key, value in v.items():
                        total[key] = None if value is None or total[key] is None else total[key] + value
            for key, total in frame_sums.items():
                sums[key] += total or 0.0
                record[FLOW_KEYS[key]] = total / n if total is not None and n else None
            record.update(next_time=gt.next_time, pixels=n)
            pixels, scored = pixels + n, scored + 1
        if frame.time not in matches and _has_sample(truth, frame.time):
            scores, matches[frame.time] = _score_vertices(model, truth, frame, radius, h, gathered, known)
            record.update(scores)
        per_frame.append(record)

    def average(key: str) -> float | None:
        return sums[key] / pixels if pixels and (key != "velocity" or model.material_field is not None) else None

    flow_scores = FlowScores(scored, pixels, average("motion"), average("velocity"), average("gaussian"), average("zero"), skipped,
                             velocity_integration, _object_means(object_sums, object_names))
    velocity = _velocity_scores(gathered, len(matches), radius, h, speed_floor, truth.frame_interval)
    matches = dict(sorted(matches.items()))
    followed = _follow_matches(model, truth, matches)
    tracking, per_anchor = _tracking_scores(truth, matches, followed)
    spin, spin_per_anchor = _spin_scores(truth, matches, followed)
    for record in per_frame:
        record.update(per_anchor.get(record["time"], {}))
        record.update(spin_per_anchor.get(record["time"], {}))
    return MotionEvaluation(split, str(truth.root.parent), truth.frame_interval, flow_scores, velocity, per_frame,
                            tracking=tracking, spin=spin)


@dataclass
class FollowedGaussians:
    """The Gaussians matched at any view time (``matches``), deformed to every ground-truth sample time in [0, 1]:
    the i-th of those times is vertex sample ``sample_of[i]``, ``means`` [T, R, 3] their centres, ``slot`` [N] a
    Gaussian's column in ``means`` (-1: matched nowhere)."""

    sample_of: list[int]
    means: Tensor
    slot: Tensor


@torch.no_grad()
def _follow_matches(
    model: DynamicGaussians, truth: MotionGroundTruth, matches: dict[float, tuple[Tensor, Tensor, Tensor]]
) -> FollowedGaussians | None:
    """One deformation per ground-truth sample time in [0, 1] of every matched Gaussian, shared by the tracking and
    the spin (None: fewer than two sample times, or no match)."""
    vertices = truth.vertices
    times = [float(t) for t in vertices.times if -_TIME_TOL <= t <= 1.0 + _TIME_TOL]
    if len(times) < 2 or not matches:
        return None
    rows = torch.unique(torch.cat([g for _, g, _ in matches.values()]))
    slot = torch.full((model.num_gaussians,), -1, dtype=torch.long, device=model.device)
    slot[rows] = torch.arange(len(rows), device=model.device)
    means = torch.stack([model.at(t, rows=rows).means for t in times])  # [T, R, 3]
    return FollowedGaussians([vertices.index_of(t, _TIME_TOL) for t in times], means, slot)


def _tracking_scores(
    truth: MotionGroundTruth, matches: dict[float, tuple[Tensor, Tensor, Tensor]], follow: FollowedGaussians | None
) -> tuple[TrackingScores | None, dict[float, dict[str, float | None]]]:
    """The 3D tracking scores (module docstring) and, per anchor time, its ``track_error`` and ``track_travel``.
    ``matches``: per anchor time, the matched vertices, their Gaussians (the 3D velocity's matching,
    :func:`_velocity_at`) and whether the anchor's view sees each (:func:`seen_gaussians`); ``follow``: those
    Gaussians at every sample time (:func:`_follow_matches`)."""
    if follow is None:
        return None, {}
    vertices = truth.vertices
    device = follow.means.device
    n_vertices = len(matches) * vertices.positions.shape[1]
    sample_of, followed, slot = follow.sample_of, follow.means, follow.slot
    truth_at = torch.from_numpy(vertices.positions[sample_of]).to(device)  # [T, V, 3]
    error_sum = travel_sum = seen_error = seen_travel = 0.0
    samples = matched = seen_matches = 0
    owner = truth.vertex_objects(unowned=0).to(device)  # vertex -> object
    object_sums = torch.zeros(len(truth.objects), 2, dtype=torch.float64, device=device)  # error, travel
    per_anchor: dict[float, dict[str, float | None]] = {}
    for t_a, (verts, gauss, seen) in matches.items():
        k = vertices.index_of(t_a, _TIME_TOL)
        others = [i for i, s in enumerate(sample_of) if s != k]
        if not len(verts) or not others:
            per_anchor[t_a] = {"track_error": None, "track_travel": None}
            continue
        a = sample_of.index(k)  # an anchor is a scored frame's time in [0, 1] with a sample
        g, x = followed[:, slot[gauss]], truth_at[:, verts]  # [T, M, 3]
        moved, true_moved = g[others] - g[a], x[others] - x[a]
        error = (moved - true_moved).norm(dim=-1).double()
        travel = true_moved.norm(dim=-1).double()
        error_sum, travel_sum = error_sum + float(error.sum()), travel_sum + float(travel.sum())
        seen_error, seen_travel = seen_error + float(error[:, seen].sum()), seen_travel + float(travel[:, seen].sum())
        seen_matches += int(seen.sum())
        object_sums.index_add_(0, owner[verts], torch.stack([error.sum(0), travel.sum(0)], dim=-1))
        samples, matched = samples + error.numel(), matched + len(verts)
        per_anchor[t_a] = {"track_error": float(error.mean()), "track_travel": float(travel.mean())}
    scores = TrackingScores(
        anchors=len(matches), samples=samples, coverage=ratio_or_none(matched, n_vertices),
        error=ratio_or_none(error_sum, samples), travel=ratio_or_none(travel_sum, samples), relative=ratio_or_none(error_sum, travel_sum),
        per_object={obj.name: ratio_or_none(e, t) for obj, (e, t) in zip(truth.objects, object_sums.tolist())},
        seen_share=ratio_or_none(seen_matches, matched), seen_relative=ratio_or_none(seen_error, seen_travel),
    )
    return scores, per_anchor


def best_rotation(source: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """The rotation R [3, 3] that best carries the points ``source`` [M, 3] onto ``target`` [M, 3], both centred on
    their means (least squares, Kabsch: from the SVD of the cross-covariance, with the sign that excludes a
    reflection: :func:`pidg.flow.rigid_tracks.rigid_fit`), and the fit's RMS residual (the points' units); float64."""
    a, b = source.double(), target.double()
    rotation, shift = rigid_fit(a, b)
    residual = ((a @ rotation.T + shift - b).square().sum(-1).mean()).sqrt()
    return rotation, residual


def rotation_angle_deg(rotation: Tensor) -> float:
    """The angle of a rotation matrix [3, 3], degrees in [0, 180]."""
    return math.degrees(rotation_angle(rotation))


def rigid_turn(x0: Tensor, x1: Tensor) -> tuple[Tensor, float] | None:
    """The true rotation [3, 3] (float64) and its angle (degrees) of an object whose vertices go from ``x0`` to ``x1``
    [V, 3], when it moves rigidly (best rigid fit's RMS residual at most :data:`RIGID_TOLERANCE` of its bounding
    box's diagonal) and turns at least :data:`SPIN_FLOOR_DEG`; None when it is not scored for spin."""
    rotation, residual = best_rotation(x0, x1)
    angle = rotation_angle_deg(rotation)
    size = float((x0.max(0).values - x0.min(0).values).norm())
    if float(residual) > RIGID_TOLERANCE * size or angle < SPIN_FLOOR_DEG:
        return None
    return rotation, angle


def _spin_scores(
    truth: MotionGroundTruth, matches: dict[float, tuple[Tensor, Tensor, Tensor]], follow: FollowedGaussians | None
) -> tuple[SpinScores | None, dict[float, dict[str, float | None]]]:
    """The spin scores (module docstring) and, per view time scored, its mean true and error angles over the objects
    (``spin_true_deg``, ``spin_error_deg``). ``matches`` and ``follow`` as :func:`_tracking_scores` takes them."""
    if follow is None:
        return None, {}
    vertices = truth.vertices
    scored: list[tuple[str, float, float, float]] = []  # per (view time, object): its true, learned and error angles
    per_anchor: dict[float, dict[str, float | None]] = {}
    for t, (verts, gauss, _) in matches.items():
        if not len(verts) or not _has_sample(truth, t + truth.frame_interval):
            continue
        k, k1 = vertices.index_of(t, _TIME_TOL), vertices.index_of(t + truth.frame_interval, _TIME_TOL)
        if k1 not in follow.sample_of:  # after the recording: the model is not defined there
            continue
        at_t, at_t1 = (follow.means[follow.sample_of.index(i)] for i in (k, k1))
        before = len(scored)
        for obj in truth.objects:
            ours = torch.unique(gauss[(verts >= obj.first_vertex) & (verts < obj.first_vertex + obj.n_vertices)])
            if len(ours) < 3:
                continue
            x0, x1 = (torch.from_numpy(vertices.positions[i, obj.first_vertex : obj.first_vertex + obj.n_vertices]) for i in (k, k1))
            turn = rigid_turn(x0, x1)
            if turn is None:
                continue
            true_rotation, true_angle = turn
            learned, _ = best_rotation(at_t[follow.slot[ours]].cpu(), at_t1[follow.slot[ours]].cpu())
            scored.append((obj.name, true_angle, rotation_angle_deg(learned), rotation_angle_deg(learned @ true_rotation.T)))
        if len(scored) > before:
            view = scored[before:]
            per_anchor[t] = {"spin_true_deg": sum(r[1] for r in view) / len(view),
                             "spin_error_deg": sum(r[3] for r in view) / len(view)}
    if not scored:
        return None, per_anchor
    true, learned, error = (sum(r[i] for r in scored) for i in (1, 2, 3))
    per_object = {obj.name: ratio_or_none(sum(r[3] for r in scored if r[0] == obj.name), sum(r[1] for r in scored if r[0] == obj.name))
                  for obj in truth.objects if any(r[0] == obj.name for r in scored)}
    scores = SpinScores(intervals=len(scored), true_deg=true / len(scored), learned_deg=learned / len(scored),
                        error_deg=error / len(scored), relative=ratio_or_none(error, true), per_object=per_object)
    return scores, per_anchor


SEEN_MIN_WEIGHT = 0.1
"""Total compositing weight (in pixels: 1 = all of one pixel's colour) from which a view sees a Gaussian: a tenth
of a pixel, so that small Gaussians on the surface count and those behind it (a few % of a pixel) do not."""


def rendered_weights(model: DynamicGaussians, state: DeformedGaussians, camera: Camera) -> Tensor:
    """Each Gaussian's compositing weight summed over the pixels of its render in ``camera`` [N] (pixels): how much
    of the image it makes (they add up to the render's alpha summed over its pixels); nearly 0 for one hidden behind
    others, 0 outside the view. The gradient of the summed render of a constant feature with respect to that feature
    (one render and its backward)."""
    detached = DeformedGaussians(state.means.detach(), state.quats.detach(), state.log_scales.detach())
    with torch.enable_grad():
        ones = detached.means.new_ones(detached.means.shape[0], 1, requires_grad=True)
        out = model.render_state(detached, camera, ones)
        (weights,) = torch.autograd.grad(out.features[..., 0].sum(), ones)
    return weights[:, 0]


def seen_gaussians(
    model: DynamicGaussians, state: DeformedGaussians, camera: Camera, min_weight: float = SEEN_MIN_WEIGHT
) -> Tensor:
    """[N] bool: the Gaussians placed at some time (``state``) that ``camera`` sees (:func:`rendered_weights` >=
    ``min_weight``). Only those shape that image, so only those can its pixels (and a flow loss on them) have taught."""
    return rendered_weights(model, state, camera) >= min_weight


def _has_sample(truth: MotionGroundTruth, t: float) -> bool:
    try:
        truth.vertices.index_of(t, _TIME_TOL)
    except KeyError:
        return False
    return True


InterpolationOrder = Literal["linear", "cubic"]


def interpolation_weights(known_times: Sequence[float], t: float, order: InterpolationOrder) -> list[tuple[float, float]] | None:
    """(known time, weight) pairs that interpolate a motion known only at ``known_times`` to dataset time ``t``:
    linear between the two known times around ``t``, or the cubic through the four nearest (Lagrange; fewer where
    fewer are known); one weight 1 at a known time. None outside the known times: nothing there is interpolation."""
    times = np.array(sorted(set(float(x) for x in known_times)))
    if len(times) == 0 or t < times[0] - _TIME_TOL or t > times[-1] + _TIME_TOL:
        return None
    exact = np.abs(times - t) <= _TIME_TOL
    if exact.any():
        return [(float(times[exact][0]), 1.0)]
    after = int(np.searchsorted(times, t))  # times[after - 1] < t < times[after]
    points = 2 if order == "linear" else min(4, len(times))
    first = min(max(after - points // 2, 0), len(times) - points)
    window = times[first:first + points]
    return [(float(t_m), float(np.prod((t - np.delete(window, m)) / (t_m - np.delete(window, m)))))
            for m, t_m in enumerate(window)]


def positions_between(vertices: VertexMotion, known_times: Sequence[float], t: float, order: InterpolationOrder) -> np.ndarray | None:
    """[V, 3] float64: the vertices' positions at dataset time ``t`` as a motion known only at ``known_times``
    (sample times of ``vertices``) puts them (:func:`interpolation_weights`); None outside the known times."""
    weights = interpolation_weights(known_times, t, order)
    if weights is None:
        return None
    return sum(w * vertices.positions[vertices.index_of(time, _TIME_TOL)].astype(np.float64) for time, w in weights)


def _training_times_floor(
    truth: MotionGroundTruth, camera: Camera, t: float, known: Sequence[float], order: InterpolationOrder, shown: Tensor,
    ahead: Tensor,
) -> Tensor | None:
    """Per vertex in front of ``camera`` (``ahead``; px): the flow of the truth known at the training times ``known``
    (vertex sample times) only, interpolated to t and t + frame_interval (:func:`positions_between`), against the
    true displacement's flow ``shown``. None where t or t + interval lies outside the known times."""
    ends = [positions_between(truth.vertices, known, time, order) for time in (t, t + truth.frame_interval)]
    if ends[0] is None or ends[1] is None:
        return None
    start, end = (torch.from_numpy(x).to(shown) for x in ends)
    return (projected_displacement(camera, start, end) - shown).norm(dim=-1)[ahead]


def _training_times_split(
    model: DynamicGaussians, truth: MotionGroundTruth, camera: Camera, t: float, known: Sequence[float], vertices: Tensor,
    gaussians: Tensor,
) -> tuple[Tensor, Tensor, Tensor] | None:
    """Per vertex (indices ``vertices``, matched to ``gaussians``), the model's motion over [t, t + frame_interval]
    against the truth's, projected into ``camera`` (px): the whole error, its part at the training times ``known``
    (both motions replaced by their linear interpolation between the training times around t and t + interval) and
    the rest, between them (how the model's path bends between training times against the truth's). The two parts
    add up to the whole as vectors. None where t or t + interval lies outside the training times."""
    ends = (t, t + truth.frame_interval)
    weights = [interpolation_weights(known, time, "linear") for time in ends]
    if weights[0] is None or weights[1] is None:
        return None
    model_means: dict[float, Tensor] = {}

    def model_at(time: float) -> Tensor:
        if time not in model_means:
            model_means[time] = model.at(time, rows=gaussians).means  # only the matched Gaussians
        return model_means[time]

    def truth_at(time: float) -> Tensor:
        return torch.from_numpy(truth.vertices.positions[truth.vertices.index_of(time, _TIME_TOL)]).to(model.device)[vertices]

    def linear_move(at: Callable[[float], Tensor]) -> Tensor:
        return sum(w * at(time) for time, w in weights[1]) - sum(w * at(time) for time, w in weights[0])

    whole = (model_at(ends[1]) - model_at(ends[0])) - (truth_at(ends[1]) - truth_at(ends[0]))
    at_training_times = linear_move(model_at) - linear_move(truth_at)
    start = truth_at(ends[0])

    def pixels(offset: Tensor) -> Tensor:
        return projected_displacement(camera, start, start + offset).norm(dim=-1)

    return pixels(whole), pixels(at_training_times), pixels(whole - at_training_times)


def _score_vertices(
    model: DynamicGaussians, truth: MotionGroundTruth, frame: Frame, radius: float, h: float, gathered: dict[str, list[Tensor]],
    known: Sequence[float] = (),
) -> tuple[dict[str, float | None], tuple[Tensor, Tensor]]:
    """Match the vertex sample at the frame's time to the model's Gaussians and add its speeds, distances, velocity
    errors, true velocities and unit rays from the frame's camera to the matched vertices to ``gathered``; the
    frame's coverage, mean true speed and mean errors, and the match (matched vertex indices, their Gaussians).
    ``known``: the training times that have a vertex sample, for the floor and split of what they determine."""
    t = frame.time
    k = truth.vertices.index_of(t, _TIME_TOL)
    points = torch.from_numpy(truth.vertices.positions[k]).to(model.device)
    v_gt = torch.from_numpy(truth.vertices.velocities[k]).to(model.device)
    state = model.at(t)
    found = _velocity_at(model, t, state.means, points, radius, h)
    speed = v_gt[found["hit"]].norm(dim=-1)
    gathered["speed_all"].append(v_gt.norm(dim=-1))
    gathered["speed"].append(speed)
    gathered["distance"].append(found["distance"])
    gathered["ray"].append(nn_functional.normalize(points[found["hit"]] - frame.camera.camera_center.to(points), dim=-1))
    gathered["v_gt"].append(v_gt[found["hit"]])
    has_next = _has_sample(truth, t + truth.frame_interval)
    parts: dict[str, Tensor | None] = {}  # the floor of the training times and the model's error split (px)
    if has_next:  # the true velocity's own flows over one interval
        k1 = truth.vertices.index_of(t + truth.frame_interval, _TIME_TOL)
        later = torch.from_numpy(truth.vertices.positions[k1]).to(points)
        v_later = torch.from_numpy(truth.vertices.velocities[k1]).to(points)
        shown = projected_displacement(frame.camera, points, later)
        ahead = frame.camera.project_points(points)[1] > frame.camera.near
        for key, v_step in (("euler", v_gt), ("second_order", 0.5 * (v_gt + v_later))):
            advected = projected_displacement(frame.camera, points, points + v_step * truth.frame_interval)
            gathered[key].append((advected - shown).norm(dim=-1)[ahead])
        if known:
            parts.update({f"training_times_{order}": _training_times_floor(truth, frame.camera, t, known, order, shown, ahead)
                          for order in ("linear", "cubic")})
    record = {"coverage": float(found["hit"].float().mean()), "gt_speed": _mean(speed)}
    for key in ("deformation", "field"):
        err = found[key] - v_gt[found["hit"]] if key in found else None
        if err is not None:
            gathered[key].append(err)
        record[f"{key}_mae"] = None if err is None else _mean(err.norm(dim=-1))
    seen = seen_gaussians(model, state, frame.camera)[found["gaussians"]]
    if known and has_next:
        split = _training_times_split(model, truth, frame.camera, t, known, found["hit"].nonzero().squeeze(1)[seen],
                                      found["gaussians"][seen])
        parts.update(zip(("seen_flow", "seen_flow_at_training_times", "seen_flow_between_training_times"), split or (None,) * 3))
    for key, part in parts.items():
        if part is not None:
            gathered[key].append(part)
        record[f"{key}_px"] = None if part is None else _mean(part)
    return record, (found["hit"].nonzero().squeeze(1), found["gaussians"], seen)


def _velocity_scores(
    gathered: dict[str, list[Tensor]], times: int, radius: float, h: float, speed_floor: float | None, frame_interval: float,
) -> VelocityScores:
    def cat(key: str) -> Tensor:
        return torch.cat(gathered[key]) if gathered[key] else torch.zeros(0)

    speed_all, speed = cat("speed_all"), cat("speed")
    vertex_samples, matched = len(speed_all), len(speed)
    floor = speed_floor if speed_floor is not None else (SPEED_FLOOR_FRACTION * float(speed_all.mean()) if len(speed_all) else None)
    counted = (speed >= floor) & (speed > 0) if floor is not None else torch.zeros(0, dtype=torch.bool)

    def errors(key: str) -> tuple[float | None, float | None, float | None]:
        if not gathered[key]:
            return None, None, None
        err = cat(key).norm(dim=-1)
        mae = _mean(err)
        rel = _mean(err[counted] / speed[counted])
        return mae, _times(mae, frame_interval), rel

    d_mae, d_frame, d_rel = errors("deformation")
    f_mae, f_frame, f_rel = errors("field")
    zero = _mean(speed)
    rays = cat("ray")

    def along_across(key: str) -> tuple[float | None, float | None]:
        if not gathered[key]:
            return None, None
        err = cat(key)
        along = (err * rays).sum(-1, keepdim=True) * rays
        return _mean(along.norm(dim=-1)), _mean((err - along).norm(dim=-1))

    d_ray, f_ray, z_ray = along_across("deformation"), along_across("field"), along_across("v_gt")  # zero: error = -v_gt
    lag = (cat("field") - cat("deformation")).norm(dim=-1) if gathered["field"] else None  # (v - v_gt) - (d - v_gt)
    return VelocityScores(
        times=times, vertex_samples=vertex_samples, matched=matched,
        coverage=ratio_or_none(matched, vertex_samples), radius=radius, fd_step=h, speed_floor=floor,
        relative_samples=int(counted.sum()), match_distance=_mean(cat("distance")),
        deformation_mae=d_mae, deformation_mae_per_frame=d_frame, deformation_rel=d_rel,
        field_mae=f_mae, field_mae_per_frame=f_frame, field_rel=f_rel,
        zero_mae=zero, zero_mae_per_frame=_times(zero, frame_interval), zero_rel=1.0 if int(counted.sum()) else None,
        deformation_along_ray=d_ray[0], deformation_across_ray=d_ray[1], field_along_ray=f_ray[0],
        field_across_ray=f_ray[1], zero_along_ray=z_ray[0], zero_across_ray=z_ray[1],
        truth_velocity_flow_px=_mean(cat("euler")),
        truth_velocity_flow_second_order_px=_mean(cat("second_order")),
        training_times_linear_flow_px=_mean(cat("training_times_linear")),
        training_times_cubic_flow_px=_mean(cat("training_times_cubic")),
        seen_flow_px=_mean(cat("seen_flow")),
        seen_flow_at_training_times_px=_mean(cat("seen_flow_at_training_times")),
        seen_flow_between_training_times_px=_mean(cat("seen_flow_between_training_times")),
        field_lag_rel=None if lag is None else _mean(lag[counted] / speed[counted]),
    )

