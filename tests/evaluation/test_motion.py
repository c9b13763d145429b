"""Scoring the learned motion against ground-truth motion: known answers on a model whose deformation is a known
translation, the unit conversion of the material field's v, coverage, and ``pidg eval --motion-gt`` end to end."""
from __future__ import annotations

import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import json
import math
import re
import shutil
from xml.etree import ElementTree

import numpy as np
import pytest
import torch
from PIL import Image
from torch import Tensor, nn

from pidg.data.motion_gt import FrameFlow, MotionObject, VertexMotion, read_motion_gt, write_frame_flow, write_motion_gt
from pidg.data.scene import DatasetError, Frame
from pidg.evaluation.images import TITLE_STRIP_PX
from pidg.evaluation.motion import (
    MODEL_MIN_ALPHA,
    RADIUS_FRACTION,
    SEEN_MIN_WEIGHT,
    SPIN_FLOOR_DEG,
    _follow_matches,
    _spin_scores,
    _tracking_text,
    best_rotation,
    default_radius,
    evaluate_flow_target,
    evaluate_motion,
    model_flows,
    positions_between,
    rendered_weights,
    rotation_angle_deg,
    seen_gaussians,
    target_flow_sums,
    velocity_per_dataset_time,
)
from pidg.flow import FlowCache, FlowConfig, FlowTarget
from pidg.models.deformation.base import DeformationModel, DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModel
from pidg.models.time_axis import TimeAxis
from pidg.physics import particle_velocity
from pidg.render import Camera

W, H, Z = 40, 32, 2.0  # image size; the Gaussians lie on the plane z = 2 in front of the camera
VELOCITY = torch.tensor([0.3, -0.2, 0.0])  # world units per unit of dataset time, parallel to the image plane
S = 7.0  # physics time units per unit of dataset time
DT = 0.125  # ground-truth frame interval (dataset time)


def test_velocity_conversion_from_physics_to_dataset_time():
    v = torch.tensor([[1.0, -2.0, 0.5]])
    # default time axis: one physics unit per training-frame interval (here 0.25 of the recording) -> x4
    axis = TimeAxis.from_times([0.0, 0.25, 0.5, 0.75, 1.0])
    assert axis.physics_per_dataset == pytest.approx(4.0)
    torch.testing.assert_close(velocity_per_dataset_time(v, axis), v * 4.0)
    # an explicit scale: tau = 10 t, so dx/dt = 10 dx/dtau
    torch.testing.assert_close(velocity_per_dataset_time(v, TimeAxis.from_times([0.0, 0.5, 1.0], 10.0)), v * 10.0)
    # consistent with the axis: v (physics) x a span in physics units = v (dataset) x the span in dataset time
    moved = v * axis.to_physics(0.1)
    torch.testing.assert_close(velocity_per_dataset_time(v, axis) * 0.1, moved)


# ---------------------------------------------------------------------------------------------------------------
# a model with a known motion
# ---------------------------------------------------------------------------------------------------------------
class Translation(DeformationModel):
    """Every Gaussian moves by ``velocity * t`` (world units per unit of dataset time)."""

    def __init__(self, velocity: Tensor) -> None:
        super().__init__()
        self.register_buffer("velocity", velocity.clone())

    def deform(self, means, quats, log_scales, times, regularize=False) -> DeformedGaussians:
        return DeformedGaussians(means + times.unsqueeze(-1) * self.velocity, quats, log_scales)


class ConstantField(nn.Module):
    """A material field whose velocity is ``v`` everywhere (world units per physics time unit), stress 0."""

    def __init__(self, v: Tensor) -> None:
        super().__init__()
        self.v = v

    def forward(self, means: Tensor, t, index: Tensor) -> tuple[Tensor, Tensor]:
        return self.v.to(means).expand(len(means), 3), means.new_zeros(len(means), 6)


class FrontTranslation(Translation):
    """Gaussians in front of the plane z = ``depth`` move by ``velocity * t``; those behind it stand still."""

    def __init__(self, velocity: Tensor, depth: float) -> None:
        super().__init__(velocity)
        self.depth = depth

    def deform(self, means, quats, log_scales, times, regularize=False) -> DeformedGaussians:
        front = (means[:, 2:] < self.depth).to(means)
        return DeformedGaussians(means + front * times.unsqueeze(-1) * self.velocity, quats, log_scales)


def plane_model(field_velocity: Tensor | None, behind: float | None = None) -> DynamicGaussians:
    """Opaque Gaussians on a grid in the plane z = Z covering the view (and beyond), translating with VELOCITY.
    ``behind``: a second such grid at z = Z + behind, hidden by the first, that stands still."""
    xs = torch.linspace(-1.2, 1.2, 49)
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((gx.numel(),), Z)], dim=-1)
    if behind is not None:
        means = torch.cat([means, means + torch.tensor([0.0, 0.0, behind])])
    n = len(means)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    gaussians = GaussianModel(means, quats, torch.full((n, 3), math.log(0.04)), torch.full((n,), 4.0),
                              torch.rand(n, 1, 3, generator=torch.Generator().manual_seed(0)), torch.zeros(n, 0, 3), sh_degree=0)
    field = None if field_velocity is None else ConstantField(field_velocity)
    deformation = Translation(VELOCITY) if behind is None else FrontTranslation(VELOCITY, Z + 0.5 * behind)
    return DynamicGaussians(gaussians, deformation, field, TimeAxis(S, 1.0 / S), torch.zeros(3), backend="cpu")


def test_motion_velocity_is_the_central_difference_and_particle_velocity_its_physics_units():
    model = plane_model(None)
    torch.testing.assert_close(model.motion_velocity(0.5, 0.1), VELOCITY.expand(model.num_gaussians, 3))
    torch.testing.assert_close(model.motion_velocity(0.0, 0.1), VELOCITY.expand(model.num_gaussians, 3))  # one-sided
    rows = torch.tensor([3, 0, 3])
    torch.testing.assert_close(model.motion_velocity(1.0, 0.2, rows), VELOCITY.expand(3, 3))
    with pytest.raises(ValueError, match="h must be > 0"):
        model.motion_velocity(0.5, 0.0)
    # per physics time unit: tau = S t, so dx/dtau = VELOCITY / S (the loss's target, over half a frame either side)
    torch.testing.assert_close(particle_velocity(model, 0.5, rows), (VELOCITY / S).expand(3, 3))


CAMERA = Camera(torch.eye(4), 30.0, 30.0, W / 2, H / 2, W, H)
EXPECTED_PX = (CAMERA.fx * VELOCITY[0] * DT / Z, CAMERA.fy * VELOCITY[1] * DT / Z)  # same for every Gaussian


def write_truth(root, times=(0.25, 0.5), shift=(0.0, 0.0), scale=1, extra_vertex=False, v_gt=VELOCITY, second_speed=None,
                behind=None):
    """Ground truth for the plane model: a constant flow (+ ``shift``) at ``scale`` x the image size, with a NaN
    band (no surface) and a band that is not dynamic; vertices at the Gaussians' positions (+ one far away).
    ``second_speed``: the second half of the vertices is a second object whose vertices move at that multiple of
    VELOCITY (the flows stay the first object's). ``behind``: at the Gaussians of ``plane_model(..., behind)``, both
    grids (their vertices all move with VELOCITY)."""
    model = plane_model(None, behind)
    canonical = model.canonical().means.detach()[::5]
    if extra_vertex:
        canonical = torch.cat([canonical, torch.tensor([[0.0, 0.0, 50.0]])])
    half = len(canonical) // 2
    speed = torch.ones(len(canonical), 1)
    if second_speed is not None:
        speed[half:] = second_speed
    positions = np.stack([(canonical + t * speed * VELOCITY).numpy() for t in times]).astype(np.float32)
    velocities = np.broadcast_to(v_gt.numpy(), positions.shape).astype(np.float32)
    motion = VertexMotion(np.asarray(times, np.float64), positions, velocities, np.zeros((0, 3), np.int64))
    objects = [MotionObject("plane", "rigid", 0, len(canonical))] if second_speed is None else [
        MotionObject("first", "rigid", 0, half), MotionObject("second", "rigid", half, len(canonical) - half)]
    write_motion_gt(root, DT, objects, motion)
    frames = []
    for i, t in enumerate(times):
        flow = np.empty((H * scale, W * scale, 2), np.float32)
        flow[..., 0], flow[..., 1] = (EXPECTED_PX[0] + shift[0]) * scale, (EXPECTED_PX[1] + shift[1]) * scale
        flow[: 4 * scale] = np.nan  # top rows: background in the truth
        dynamic = np.ones(flow.shape[:2], bool)
        dynamic[:, : 5 * scale] = False  # left columns: static in the truth
        name = f"test/r_{i:04d}"
        write_frame_flow(root, name, FrameFlow(flow, dynamic, t, t + DT))
        frames.append(Frame(CAMERA, t, torch.zeros(H, W, 3, dtype=torch.uint8), name=name))
    return read_motion_gt(root), frames


SCORED_PIXELS = 2 * (H - 4) * (W - 5)  # two frames; every remaining pixel is covered by the model


def test_matching_truth_gives_zero_error_and_zero_motion_gives_the_flow_size(tmp_path):
    truth, frames = write_truth(tmp_path)
    model = plane_model(VELOCITY / S)  # v in physics units that is exactly the deformation's motion
    result = evaluate_motion(model, frames, truth)
    size = math.hypot(*EXPECTED_PX)
    assert size > 0.5
    f = result.flow
    assert (f.frames, f.pixels, f.skipped) == (2, SCORED_PIXELS, [])
    assert f.motion_flow_epe == pytest.approx(0.0, abs=1e-4)
    assert f.velocity_flow_epe == pytest.approx(0.0, abs=1e-4)
    assert f.gaussian_flow_epe == pytest.approx(0.0, abs=1e-2)  # off-axis projection changes the 2D shapes a little
    assert f.zero_motion_epe == pytest.approx(size, rel=1e-5)
    v = result.velocity
    assert v.coverage == 1.0 and v.matched == v.vertex_samples == 2 * len(truth.vertices.positions[0])
    assert v.deformation_mae == pytest.approx(0.0, abs=1e-4) and v.field_mae == pytest.approx(0.0, abs=1e-5)
    assert v.deformation_rel == pytest.approx(0.0, abs=1e-4) and v.field_rel == pytest.approx(0.0, abs=1e-5)
    assert v.field_lag_rel == pytest.approx(0.0, abs=1e-4)
    assert v.zero_mae == pytest.approx(float(VELOCITY.norm()), rel=1e-5) and v.zero_rel == 1.0
    assert v.zero_mae_per_frame == pytest.approx(v.zero_mae * DT)
    assert v.match_distance == pytest.approx(0.0, abs=1e-5) and v.fd_step == DT / 2
    # typed results -> json, with the units
    data = json.loads(json.dumps(result.to_dict()))
    assert data["flow"]["pixels"] == SCORED_PIXELS and "world units per unit of dataset time" in data["units"]["velocity"]
    assert "share of the true speed" in data["units"]["relative"]
    assert [r["view"] for r in data["per_frame"]] == ["test/r_0000", "test/r_0001"]
    assert set(result.columns()) == {"gt_motion_flow_epe", "gt_velocity_flow_epe", "gt_zero_motion_epe",
                                     "gt_velocity_rel_deformation", "gt_velocity_rel_field", "gt_coverage",
                                     "gt_target_flow_epe", "gt_track_rel", "gt_track_rel_seen", "gt_spin_rel"}
    assert result.target is None and result.columns()["gt_target_flow_epe"] is None
    track = result.tracking  # each anchor against the other sample time, 0.25 of dataset time away
    assert (track.anchors, track.samples, track.coverage) == (2, 2 * len(truth.vertices.positions[0]), 1.0)
    assert track.error == pytest.approx(0.0, abs=1e-5) and track.relative == pytest.approx(0.0, abs=1e-5)
    assert track.travel == pytest.approx(0.25 * float(VELOCITY.norm()), rel=1e-5)
    assert data["per_frame"][0]["track_travel"] == pytest.approx(track.travel, rel=1e-5)
    assert result.spin is None and result.columns()["gt_spin_rel"] is None  # a translating plane has no spin to score
    assert "motion-flow EPE 0.000 px" in result.summary()


@pytest.mark.parametrize("follows", [0.0, 0.5, 2.0])
def test_tracking_error_is_the_share_of_the_true_displacement_the_gaussians_miss(tmp_path, follows):
    """Gaussians that move at ``follows`` x the true velocity miss |1 - follows| of every displacement since the
    anchor, whichever Gaussian each vertex is matched to; standing still (0) scores the travel itself."""
    truth, frames = write_truth(tmp_path, times=(0.25, 0.5, 0.75))
    model = plane_model(None)
    model.deformation = Translation(follows * VELOCITY)
    track = evaluate_motion(model, frames, truth).tracking
    assert track.anchors == 3 and track.coverage > 0.9  # vertices that moved off the plane's edge have no Gaussian
    # mean |t - t_a| over the pairs is 1/3 (each anchor's pairs weighted by its matched vertices: close to it)
    assert track.travel == pytest.approx(float(VELOCITY.norm()) / 3, rel=2e-3)
    assert track.relative == pytest.approx(abs(1.0 - follows), rel=1e-4)
    assert track.error == pytest.approx(abs(1.0 - follows) * track.travel, rel=1e-4)
    assert track.per_object == {"plane": pytest.approx(track.relative, rel=1e-9)}  # the truth's one object


def test_rendered_weights_are_each_gaussians_share_of_the_image():
    """Summed over the Gaussians, the weights are the render's alpha summed over its pixels; a Gaussian behind an
    opaque layer, or outside the view, has (nearly) none, and so the view does not see it."""
    model = plane_model(None, behind=0.5)
    state = model.canonical()
    weights = rendered_weights(model, state, CAMERA)
    alpha = model.render_state(state, CAMERA).alpha.detach()
    assert float(weights.sum()) == pytest.approx(float(alpha.sum()), rel=1e-4)
    half = model.num_gaussians // 2
    front, back = weights[:half], weights[half:]
    assert float(back.max()) < 0.01 and float(front.max()) > 0.5  # ~0.56 px each where the front grid is in view
    moved = state.means.detach().clone()
    moved[0] = torch.tensor([5.0, 0.0, Z])  # far to the right of the view (its edge is at x = (W / 2) / fx x Z)
    away = rendered_weights(model, DeformedGaussians(moved, state.quats, state.log_scales), CAMERA)
    assert float(away[0]) == 0.0 and float(away.sum()) == pytest.approx(float(weights.sum() - weights[0]), rel=1e-3)
    seen = seen_gaussians(model, state, CAMERA)
    assert torch.equal(seen, weights >= SEEN_MIN_WEIGHT) and not seen[half:].any()


def test_tracking_of_the_seen_gaussians_leaves_out_those_behind_the_surface(tmp_path):
    """The front grid follows its vertices, the hidden one behind it stands still while its vertices move: the
    tracking over all matches misses the hidden grid's half of the travel, over the seen ones nothing."""
    truth, frames = write_truth(tmp_path, times=(0.25, 0.5, 0.75), behind=0.5)
    track = evaluate_motion(plane_model(None, behind=0.5), frames, truth).tracking
    assert track.seen_relative == pytest.approx(0.0, abs=1e-5)
    assert 0.3 < track.seen_share < 0.5  # the front grid's matches in view (its rows past the image's edges are not)
    assert track.relative == pytest.approx(0.5, abs=0.03)  # half the matches, the hidden grid's, miss all their travel
    assert "whose Gaussian the view sees: 0.000" in _tracking_text(track)


def test_tracking_is_also_scored_per_object(tmp_path):
    truth, frames = write_truth(tmp_path, second_speed=2.0)  # the model follows the first object, at half the second's speed
    result = evaluate_motion(plane_model(None), frames, truth)
    per_object = result.tracking.per_object
    assert per_object["first"] == pytest.approx(0.0, abs=1e-4) and per_object["second"] == pytest.approx(0.5, rel=1e-3)
    assert 0.0 < result.tracking.relative < 0.5
    assert "first 0.000; second 0.500" in result.summary()


def test_shifted_truth_gives_the_shift_as_error(tmp_path):
    truth, frames = write_truth(tmp_path, shift=(0.3, -0.4))
    f = evaluate_motion(plane_model(VELOCITY / S), frames, truth).flow
    assert f.motion_flow_epe == pytest.approx(0.5, rel=1e-4) and f.velocity_flow_epe == pytest.approx(0.5, rel=1e-4)
    assert f.zero_motion_epe == pytest.approx(math.hypot(EXPECTED_PX[0] + 0.3, EXPECTED_PX[1] - 0.4), rel=1e-5)


def test_a_wrong_field_velocity_shows_in_the_velocity_errors_only(tmp_path):
    truth, frames = write_truth(tmp_path)
    result = evaluate_motion(plane_model(2 * VELOCITY / S), frames, truth)  # twice the true speed
    assert result.flow.motion_flow_epe == pytest.approx(0.0, abs=1e-4)
    assert result.flow.velocity_flow_epe == pytest.approx(math.hypot(*EXPECTED_PX), rel=1e-4)
    v = result.velocity
    assert v.deformation_rel == pytest.approx(0.0, abs=1e-4)
    assert v.field_rel == pytest.approx(1.0, rel=1e-5) and v.field_mae == pytest.approx(float(VELOCITY.norm()), rel=1e-5)
    assert v.field_mae_per_frame == pytest.approx(v.field_mae * DT)
    assert v.field_lag_rel == pytest.approx(1.0, rel=1e-4)  # v is off the particles by their true speed
    assert "field v 1.000 (1.000 off the deformation's)" in result.summary()
    # without a material field there is no velocity flow and no field error
    bare = evaluate_motion(plane_model(None), frames, truth)
    assert bare.flow.velocity_flow_epe is None and bare.velocity.field_rel is None and bare.flow.motion_flow_epe is not None
    assert bare.velocity.field_lag_rel is None


def test_a_field_that_follows_a_wrong_deformation_is_wrong_but_does_not_lag(tmp_path):
    """The lag compares v with the deformation's velocity, not with the truth: vertices truly moving at twice the
    speed the model's motion (and v with it) has make both errors a half, and no lag."""
    truth, frames = write_truth(tmp_path, v_gt=2 * VELOCITY)
    v = evaluate_motion(plane_model(VELOCITY / S), frames, truth).velocity
    assert v.deformation_rel == pytest.approx(0.5, rel=1e-3) and v.field_rel == pytest.approx(0.5, rel=1e-3)
    assert v.field_lag_rel == pytest.approx(0.0, abs=1e-4)


def two_faces_truth(root, shift=(0.3, -0.4), gap=0.1, times=(0.25, 0.5)):
    """Two rectangles (two triangles each) on the plane of :func:`plane_model`, "left" up to ``gap`` left of the
    line x = 0 and "right" from ``gap`` right of it, translating with VELOCITY; frames with depth maps (the plane,
    z = Z). The truth's flow is the plane's motion, ``shift`` px more on every pixel right of the gap's middle."""
    corners = np.array([[-1.2, -1.2], [-gap, -1.2], [-gap, 1.2], [-1.2, 1.2], [gap, -1.2], [1.2, -1.2], [1.2, 1.2], [gap, 1.2]])
    canonical = torch.tensor(np.concatenate([corners, np.full((8, 1), Z)], axis=1), dtype=torch.float32)
    positions = np.stack([(canonical + t * VELOCITY).numpy() for t in times]).astype(np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int64)
    motion = VertexMotion(np.asarray(times, np.float64), positions, np.zeros_like(positions), faces)
    write_motion_gt(root, DT, [MotionObject("left", "rigid", 0, 4), MotionObject("right", "rigid", 4, 4)], motion)
    frames = []
    for i, t in enumerate(times):
        x = (np.arange(W) + 0.5 - CAMERA.cx) / CAMERA.fx * Z  # each pixel column's x on the plane
        flow = np.empty((H, W, 2), np.float32)
        flow[..., 0], flow[..., 1] = EXPECTED_PX
        flow[:, x > t * float(VELOCITY[0])] += np.asarray(shift, np.float32)
        name = f"test/r_{i:04d}"
        write_frame_flow(root, name, FrameFlow(flow, np.ones((H, W), bool), t, t + DT))
        frames.append(Frame(CAMERA, t, torch.zeros(H, W, 3, dtype=torch.uint8), name=name, depth=torch.full((H, W), Z)))
    return read_motion_gt(root), frames


def test_flow_errors_are_also_pooled_per_object_by_the_surface_each_pixel_shows(tmp_path):
    """Each pixel's depth lifted onto the true triangles names its object: the left face's pixels score 0 and the
    right face's the truth's 0.5 px shift; pixels in the gap between them, farther than the matching radius from
    both, are "(none)"; per object, the pixels add up to the scored ones and the errors to the pooled EPE."""
    truth, frames = two_faces_truth(tmp_path)
    result = evaluate_motion(plane_model(VELOCITY / S), frames, truth)
    f, radius = result.flow, default_radius(truth)
    assert radius < 0.1  # the gap's middle is farther than the radius from both faces
    objects = f.per_object
    assert list(objects) == ["left", "right", "(none)"]
    assert objects["left"]["velocity_flow_epe"] == pytest.approx(0.0, abs=1e-4)
    assert objects["right"]["velocity_flow_epe"] == pytest.approx(0.5, rel=1e-4)
    assert objects["right"]["motion_flow_epe"] == pytest.approx(0.5, rel=1e-4)
    assert objects["right"]["zero_motion_epe"] == pytest.approx(math.hypot(EXPECTED_PX[0] + 0.3, EXPECTED_PX[1] - 0.4), rel=1e-5)
    assert sum(o["pixels"] for o in objects.values()) == f.pixels
    for key in ("motion_flow_epe", "velocity_flow_epe", "zero_motion_epe"):
        assert sum(o["pixels"] * o[key] for o in objects.values()) / f.pixels == pytest.approx(getattr(f, key), rel=1e-5)
    # the gap is 0.2 world units wide (3 px at depth Z); the pixels within the radius of a face are that face's
    gap_px = sum(o["pixels"] for name, o in objects.items() if name == "(none)") / len(frames) / H
    assert 0.0 < gap_px <= (0.2 - 2 * radius) * CAMERA.fx / Z + 1
    assert result.per_frame[0]["objects"]["right"]["pixels"] > 0
    assert "(by object, velocity flow on its share of the pixels: left 0.000 px on" in result.summary()
    # without depth maps there is nothing to lift: no breakdown
    bare = [dataclasses.replace(frame, depth=None) for frame in frames]
    assert evaluate_motion(plane_model(VELOCITY / S), bare, truth).flow.per_object == {}


def test_the_flow_picture_shows_truth_motion_velocity_and_error_on_the_scored_pixels(tmp_path):
    from pidg.evaluation.flow_vis import flow_rgb_tensor
    from pidg.evaluation.visualize import truth_flow_comparison, truth_flow_titles

    truth, frames = write_truth(tmp_path)
    seen = []
    evaluate_motion(plane_model(2 * VELOCITY / S), frames, truth, on_frame=seen.append)  # v twice the true speed
    assert [f.frame.name for f in seen] == [f.name for f in frames]
    flows = seen[0]
    assert int(flows.scored.sum()) == SCORED_PIXELS // 2
    panel, scale = truth_flow_comparison(flows)
    size = math.hypot(*EXPECTED_PX)
    assert tuple(panel.shape) == (H, 4 * W, 3) and scale == pytest.approx(size, rel=1e-5)
    truth_panel, motion_panel, velocity_panel, error_panel = panel.split(W, dim=1)
    off = ~flows.scored
    assert off[:4].all() and off[:, :5].all() and all(bool((p[off] == 0).all()) for p in (truth_panel, motion_panel, velocity_panel, error_panel))
    for shown, flow in ((truth_panel, flows.truth), (motion_panel, flows.model.motion), (velocity_panel, flows.model.velocity)):
        torch.testing.assert_close(shown, flow_rgb_tensor(flow, scale, flows.scored))  # one colour scale, scored pixels only
    assert float((velocity_panel - truth_panel).abs().max()) > 0.1  # twice the true motion: beyond the scale, darkened
    # the velocity flow's error is the true flow's size, the top of the ramp: the ramp's last colour everywhere
    yellow = torch.tensor([0.993, 0.906, 0.144])
    torch.testing.assert_close(error_panel[flows.scored], yellow.expand(SCORED_PIXELS // 2, 3), atol=2e-3, rtol=0)
    # the saved picture names its panels, the error's ramp with its top in px
    assert truth_flow_titles(flows, scale) == ["true motion flow", "model's motion flow", "velocity flow",
                                               f"velocity-flow error, 0-{size:.1f} px"]
    bare = []
    evaluate_motion(plane_model(None), frames, truth, on_frame=bare.append)
    assert truth_flow_titles(bare[0], 2.0)[2:] == ["no material field", "motion-flow error, 0-2.0 px"]


class HalfStepField(nn.Module):
    """Still at dataset times in [k/8, k/8 + 1/32) and moving with VELOCITY (physics units) from k/8 + 1/32 on: the
    test frames (t = 0.25, 0.5) are at rest, the midpoints of their intervals (t + DT/2) are not."""

    def forward(self, means: Tensor, t, index: Tensor) -> tuple[Tensor, Tensor]:
        t = torch.as_tensor(t, dtype=means.dtype).expand(len(means))
        moving = ((t * 8.0) % 1.0 >= 0.25 - 1e-6).to(means.dtype)[:, None]
        return moving * (VELOCITY / S).to(means), means.new_zeros(len(means), 6)


def test_the_velocity_flow_uses_the_runs_integration_rule(tmp_path):
    """euler reads v at t (here still: the velocity flow is zero motion's error); midpoint reads it half an
    interval on (here the true motion: error 0), and the summary names the rule."""
    truth, frames = write_truth(tmp_path)
    model = plane_model(None)
    model.material_field = HalfStepField()
    euler = evaluate_motion(model, frames, truth)
    midpoint = evaluate_motion(model, frames, truth, velocity_integration="midpoint")
    assert euler.flow.velocity_flow_epe == pytest.approx(math.hypot(*EXPECTED_PX), rel=1e-4)
    assert midpoint.flow.velocity_flow_epe == pytest.approx(0.0, abs=1e-4)
    assert midpoint.flow.motion_flow_epe == euler.flow.motion_flow_epe  # the deformation's flows do not change
    assert "(midpoint rule)" in midpoint.summary() and "rule" not in euler.summary().split("zero motion")[0]
    assert midpoint.to_dict()["flow"]["velocity_integration"] == "midpoint"


def test_velocity_errors_split_along_and_across_the_camera_rays(tmp_path):
    truth, frames = write_truth(tmp_path)
    depth_error = torch.tensor([0.0, 0.0, 0.5])  # v wrong along the camera's axis only (world units / dataset time)
    v = evaluate_motion(plane_model((VELOCITY + depth_error) / S), frames, truth).velocity
    points = torch.from_numpy(truth.vertices.positions).reshape(-1, 3).double()  # camera at the origin
    rays = points / points.norm(dim=-1, keepdim=True)
    cos = rays[:, 2]  # cosine between each ray and the error (along z)
    assert v.field_along_ray == pytest.approx(float((0.5 * cos).mean()), rel=1e-5)
    assert v.field_across_ray == pytest.approx(float((0.5 * (1 - cos**2).sqrt()).mean()), rel=1e-4)
    assert v.field_along_ray > 2 * v.field_across_ray  # mostly along the rays
    assert v.deformation_along_ray == pytest.approx(0.0, abs=1e-4) and v.deformation_across_ray == pytest.approx(0.0, abs=1e-4)
    along_gt = (rays @ VELOCITY.double()).abs()  # zero velocity: the error is v_gt, here nearly across the rays
    assert v.zero_along_ray == pytest.approx(float(along_gt.mean()), rel=1e-4)
    assert v.zero_across_ray == pytest.approx(float((VELOCITY.double().norm() ** 2 - along_gt**2).sqrt().mean()), rel=1e-4)
    assert "along / across the camera rays" in evaluate_motion(plane_model(None), frames, truth).summary()


def test_the_velocity_flow_floor_is_the_true_velocitys_own_first_order_error(tmp_path):
    # samples one frame interval apart, so the floor is defined at the first; positions move with VELOCITY
    exact, frames = write_truth(tmp_path / "exact", times=(0.25, 0.25 + DT))
    velocity = evaluate_motion(plane_model(None), frames, exact).velocity
    assert velocity.truth_velocity_flow_px == pytest.approx(0.0, abs=1e-5)
    assert velocity.truth_velocity_flow_second_order_px == pytest.approx(0.0, abs=1e-5)
    # a stated velocity of twice the motion: its flow overshoots by the true displacement (in-plane, constant depth)
    doubled, frames = write_truth(tmp_path / "doubled", times=(0.25, 0.25 + DT), v_gt=2 * VELOCITY)
    velocity = evaluate_motion(plane_model(None), frames, doubled).velocity
    assert velocity.truth_velocity_flow_px == pytest.approx(math.hypot(*EXPECTED_PX), rel=1e-4)
    assert velocity.truth_velocity_flow_second_order_px == pytest.approx(math.hypot(*EXPECTED_PX), rel=1e-4)
    # accelerating from rest to twice the mean speed over the interval: first order sees no motion, the trapezoid all
    accelerating, frames = write_truth(tmp_path / "accelerating", times=(0.25, 0.25 + DT))
    accelerating.vertices.velocities = np.stack([0 * VELOCITY.numpy(), 2 * VELOCITY.numpy()])[:, None].repeat(
        accelerating.vertices.positions.shape[1], axis=1)
    velocity = evaluate_motion(plane_model(None), frames, accelerating).velocity
    assert velocity.truth_velocity_flow_px == pytest.approx(math.hypot(*EXPECTED_PX), rel=1e-4)
    assert velocity.truth_velocity_flow_second_order_px == pytest.approx(0.0, abs=1e-4)
    # no sample one interval later: no floor
    apart, frames = write_truth(tmp_path / "apart")  # samples at 0.25 and 0.5, 2 intervals apart
    assert evaluate_motion(plane_model(None), frames, apart).velocity.truth_velocity_flow_px is None


def _cubic_motion(times: np.ndarray) -> VertexMotion:
    """Two vertices on known cubic paths (world units) sampled at ``times``."""
    t = np.asarray(times, np.float64)[:, None]
    first = np.concatenate([0.5 + 2 * t - 3 * t**2 + 4 * t**3, -t**2, 1 + 0 * t], axis=1)
    second = np.concatenate([t**3, 0.2 * t, 2 - t], axis=1)
    positions = np.stack([first, second], axis=1).astype(np.float32)
    return VertexMotion(t[:, 0], positions, np.zeros_like(positions), np.zeros((0, 3), np.int64))


def test_positions_between_known_times_are_exact_for_lines_and_cubics_and_none_outside():
    samples = np.array([0.0, 0.1, 0.2, 0.35, 0.5, 0.6, 0.9, 1.0])
    motion = _cubic_motion(samples)
    known = [0.0, 0.2, 0.35, 0.6, 0.9, 1.0]  # 0.1 and 0.5 held out, the spacing uneven
    for t in (0.1, 0.5):
        truth = motion.positions[motion.index_of(t)]
        np.testing.assert_allclose(positions_between(motion, known, t, "cubic"), truth, atol=1e-5)  # a cubic: exact
    # linear between the two known times a, b around t: on the quadratic y = -t^2 off by (t - a)(t - b) (closed form)
    a, b = 0.35, 0.6
    linear = positions_between(motion, known, 0.5, "linear")
    assert linear[0, 1] - motion.positions[motion.index_of(0.5), 0, 1] == pytest.approx((0.5 - a) * (0.5 - b), abs=1e-6)
    np.testing.assert_allclose(linear[1, 1:], motion.positions[motion.index_of(0.5), 1, 1:], atol=1e-6)  # lines: exact
    np.testing.assert_array_equal(positions_between(motion, known, 0.2, "linear"), motion.positions[2])  # a known time
    assert positions_between(motion, [0.2, 0.35], 0.1, "cubic") is None  # before the first known time
    assert positions_between(motion, [0.2, 0.35], 0.5, "linear") is None  # after the last
    # two known times only: the cubic falls back to the line through them
    np.testing.assert_allclose(positions_between(motion, [0.35, 0.6], 0.5, "cubic"), linear, atol=1e-9)


def test_the_floor_of_the_training_times_is_what_interpolating_the_truth_between_them_misses(tmp_path):
    times = tuple(k * DT for k in range(5))
    truth, frames = write_truth(tmp_path, times=times)
    # the true path accelerates along x in the plane z = Z: x(t) = x0 + C t^2 (world units)
    c = 2.0
    start = truth.vertices.positions[0].copy()
    truth.vertices.positions = np.stack([start + np.array([c * t**2, 0.0, 0.0], np.float32) for t in times])
    train = [times[0], times[2], times[3], times[4]]  # the view at DT held out; its next frame, 2 DT, is trained on
    velocity = evaluate_motion(plane_model(None), frames[1:2], truth, train_times=train).velocity
    # linear between 0 and 2 DT puts the start at 2 C DT^2 instead of C DT^2; the end is known: off by C DT^2 in x
    assert velocity.training_times_linear_flow_px == pytest.approx(CAMERA.fx * c * DT**2 / Z, rel=1e-4)
    assert velocity.training_times_cubic_flow_px == pytest.approx(0.0, abs=1e-4)  # a cubic through 4 holds a parabola
    assert "interpolated linearly" in evaluate_motion(plane_model(None), frames[1:2], truth, train_times=train).summary()
    # a training view's own time is known: nothing to interpolate
    on_train = evaluate_motion(plane_model(None), frames[2:3], truth, train_times=train)
    assert on_train.velocity.training_times_linear_flow_px == pytest.approx(0.0, abs=1e-6)
    assert on_train.per_frame[0]["training_times_cubic_px"] == pytest.approx(0.0, abs=1e-6)
    # the model translates uniformly and the truth is that plus C t^2 along x: over [DT, 2 DT] the model misses
    # 3 C DT^2, of which the training times (linear between 0 and 2 DT) carry 2 C DT^2 and the bend C DT^2
    truth.vertices.positions = truth.vertices.positions + np.stack(
        [np.broadcast_to(np.array([t * VELOCITY[0].item(), t * VELOCITY[1].item(), 0.0], np.float32), start.shape) for t in times])
    split = evaluate_motion(plane_model(None), frames[1:2], truth, train_times=train)
    unit = CAMERA.fx * c * DT**2 / Z  # px of C DT^2 along x at depth Z
    assert split.velocity.seen_flow_px == pytest.approx(3 * unit, rel=1e-4)
    assert split.velocity.seen_flow_at_training_times_px == pytest.approx(2 * unit, rel=1e-4)
    assert split.velocity.seen_flow_between_training_times_px == pytest.approx(unit, rel=1e-4)
    assert split.per_frame[0]["seen_flow_between_training_times_px"] == pytest.approx(unit, rel=1e-4)
    assert "between them" in split.summary()
    # without the training times (or outside them) there is no floor
    assert evaluate_motion(plane_model(None), frames[1:2], truth).velocity.training_times_linear_flow_px is None
    outside = evaluate_motion(plane_model(None), frames[1:2], truth, train_times=train[1:]).velocity
    assert outside.training_times_linear_flow_px is None and outside.training_times_cubic_flow_px is None
    assert outside.seen_flow_px is None and outside.seen_flow_between_training_times_px is None


def test_truth_at_a_larger_resolution_is_resized_to_the_images(tmp_path):
    truth, frames = write_truth(tmp_path, scale=2)
    f = evaluate_motion(plane_model(None), frames, truth).flow
    assert f.pixels == SCORED_PIXELS and f.motion_flow_epe == pytest.approx(0.0, abs=1e-4)


def test_coverage_counts_vertices_without_a_gaussian_within_the_radius(tmp_path):
    truth, frames = write_truth(tmp_path, extra_vertex=True)
    v = evaluate_motion(plane_model(None), frames, truth).velocity
    n = len(truth.vertices.positions[0])
    assert v.coverage == pytest.approx((n - 1) / n) and v.matched == 2 * (n - 1)
    p = truth.vertices.positions.reshape(-1, 3)
    assert v.radius == pytest.approx(RADIUS_FRACTION * float(np.linalg.norm(p.max(0) - p.min(0)))) == pytest.approx(default_radius(truth))
    # a radius smaller than the distance to any Gaussian: nothing is covered, the errors are unknown, not 0
    shifted, _ = write_truth(tmp_path / "far", extra_vertex=False)
    shifted.vertices.positions += np.float32(0.01)  # 1 cm off every Gaussian
    none = evaluate_motion(plane_model(None), frames, shifted, radius=0.005).velocity
    assert none.coverage == 0.0 and none.deformation_mae is None and none.deformation_rel is None
    with pytest.raises(ValueError, match="radius must be > 0"):
        evaluate_motion(plane_model(None), frames, truth, radius=0.0)


def test_speed_floor_keeps_slow_vertices_out_of_the_relative_error(tmp_path):
    truth, frames = write_truth(tmp_path, v_gt=torch.zeros(3))  # the truth stands still, the model moves
    v = evaluate_motion(plane_model(None), frames, truth).velocity
    assert v.deformation_mae == pytest.approx(float(VELOCITY.norm()), rel=1e-4)
    assert v.relative_samples == 0 and v.deformation_rel is None and v.zero_rel is None


def test_frames_past_the_recording_are_skipped_and_a_missing_flow_is_named(tmp_path):
    truth, frames = write_truth(tmp_path, times=(0.5, 0.95))
    result = evaluate_motion(plane_model(None), frames, truth)
    assert result.flow.skipped == ["test/r_0001"] and result.flow.frames == 1
    assert result.velocity.times == 2  # the 3D velocity needs no next frame
    missing = dataclasses.replace(frames[0], name="test/r_0042")
    with pytest.raises(DatasetError, match=r"flow/test/r_0042\.npz: ground-truth flow file not found"):
        evaluate_motion(plane_model(None), [missing], truth)
    moved = dataclasses.replace(frames[0], time=0.3)
    with pytest.raises(DatasetError, match="flow is for t = 0.500000, the frame is at t = 0.300000"):
        evaluate_motion(plane_model(None), [moved], truth)


# ---------------------------------------------------------------------------------------------------------------
# the flow target of the training pairs against the truth
# ---------------------------------------------------------------------------------------------------------------
def test_target_sums_count_only_supervised_true_dynamic_surface():
    flow_gt = torch.zeros(4, 5, 2)
    flow_gt[..., 0] = 2.0
    flow_gt[0] = float("nan")  # row 0: no surface in the truth
    dynamic = torch.ones(4, 5, dtype=torch.bool)
    dynamic[:, 0] = False  # column 0: static in the truth
    target_flow = flow_gt.nan_to_num(0.0) + torch.tensor([0.0, 1.5])  # off by 1.5 px along y wherever a surface is
    target_flow[0] = 3.0  # supervised flow where the truth has no surface
    valid = torch.ones(4, 5, dtype=torch.bool)
    valid[3] = False  # the target does not supervise row 3
    sums = target_flow_sums(FlowTarget(target_flow, valid), flow_gt, dynamic)
    scored = 2 * 4  # rows 1-2, columns 1-4
    assert sums["pixels"] == scored and sums["dynamic"] == 3 * 4
    assert sums["error"] == pytest.approx(1.5 * scored) and sums["zero"] == pytest.approx(2.0 * scored)
    off = 5 + 2  # row 0, and column 0 of rows 1-2
    assert sums["off_pixels"] == off
    assert sums["off_flow"] == pytest.approx(5 * math.hypot(3.0, 3.0) + 2 * math.hypot(2.0, 1.5))


def _still_camera_cache(tmp_path, flow_px, times, shift=(0.0, 0.0)):
    """Training frames seen by one still camera, with dataset depth, a constant optical flow ``flow_px`` between
    consecutive frames (so the motion-flow target is that flow), and a truth that differs from it by ``shift``."""
    frames = [Frame(CAMERA, t, torch.zeros(H, W, 3, dtype=torch.uint8), name=f"train/r_{i:04d}", depth=torch.full((H, W), Z))
              for i, t in enumerate(times)]
    k = len(frames) - 1
    forward = torch.tensor(flow_px).expand(k, H, W, 2).clone()
    cache = FlowCache(tmp_path / "cache", frames, forward, -forward, torch.ones(k, H, W, dtype=torch.bool),
                      torch.ones(k, H, W, dtype=torch.bool))
    motion = VertexMotion(np.asarray(times, np.float64), np.zeros((len(times), 1, 3), np.float32),
                          np.zeros((len(times), 1, 3), np.float32), np.zeros((0, 3), np.int64))
    write_motion_gt(tmp_path, DT, [MotionObject("plane", "rigid", 0, 1)], motion)
    for frame in frames:
        flow = np.empty((H, W, 2), np.float32)
        flow[..., 0], flow[..., 1] = flow_px[0] + shift[0], flow_px[1] + shift[1]
        write_frame_flow(tmp_path, frame.name, FrameFlow(flow, np.ones((H, W), bool), frame.time, frame.time + DT))
    return cache, read_motion_gt(tmp_path)


def test_flow_target_of_a_still_camera_is_the_optical_flow_and_scores_the_truths_offset(tmp_path):
    flow_px = (3.0, -4.0)
    cache, truth = _still_camera_cache(tmp_path, flow_px, (0.25, 0.25 + DT, 0.25 + 3 * DT), shift=(0.6, 0.8))
    config = FlowConfig(kind="lpfm", mask_dilation=0)
    scores = evaluate_flow_target(plane_model(None), cache, config, truth)
    # the second pair spans two frame intervals (a held-out image between): skipped
    assert scores.pairs == 1 and scores.skipped == ["train/r_0001"] and scores.depth == "dataset"
    # every pixel moves 5 px (> the 1 px motion threshold): the target supervises every pixel whose flow stays in the
    # image (3 columns and 4 rows leave it)
    inside = (W - 3) * (H - 4)
    assert scores.pixels == inside and scores.coverage == pytest.approx(inside / (H * W)) and scores.off_dynamic_pixels == 0
    assert scores.target_epe == pytest.approx(1.0, rel=1e-4)  # |(0.6, 0.8)|
    assert scores.zero_motion_epe == pytest.approx(math.hypot(3.6, -3.2), rel=1e-4)
    [pair] = scores.per_pair  # the scored pair alone, with the same figures
    assert pair["frame"] == "train/r_0000" and pair["time"] == pytest.approx(0.25) and pair["pixels"] == inside
    assert pair["target_epe"] == pytest.approx(1.0, rel=1e-4)
    assert pair["zero_motion_epe"] == pytest.approx(math.hypot(3.6, -3.2), rel=1e-4)
    assert evaluate_flow_target(plane_model(None), cache, FlowConfig(kind="lpfm", target="total"), truth) is None


def test_the_models_flows_against_the_target_and_the_truth_on_and_off_the_supervised_pixels(tmp_path):
    flow_px, shift = (3.0, -4.0), (0.6, 0.8)
    cache, truth = _still_camera_cache(tmp_path, flow_px, (0.25, 0.25 + DT), shift=shift)
    config = FlowConfig(kind="lpfm", mask_dilation=0)
    # the deformation moves every Gaussian EXPECTED_PX in the pair's interval, the field's v (Euler) twice that
    scores = evaluate_flow_target(plane_model(2.0 * VELOCITY / S), cache, config, truth)
    motion, velocity = torch.tensor(EXPECTED_PX), 2.0 * torch.tensor(EXPECTED_PX)
    target, gt = torch.tensor(flow_px), torch.tensor(flow_px) + torch.tensor(shift)
    # supervised where the optical flow stays in the image (3 px right, 4 px up; as the test above); scored where the
    # model covers the pixel (the plane leaves a margin of the view uncovered)
    supervised = torch.zeros(H, W, dtype=torch.bool)
    supervised[4:, : W - 3] = True
    covered = model_flows(plane_model(None), CAMERA, 0.25, 0.25 + DT).alpha > MODEL_MIN_ALPHA
    assert scores.model_pixels == int((covered & supervised).sum()) > 0
    assert scores.unsupervised_pixels == int((covered & ~supervised).sum()) > 0
    assert scores.motion_vs_target_epe == pytest.approx(float((motion - target).norm()), rel=1e-4)
    assert scores.velocity_vs_target_epe == pytest.approx(float((velocity - target).norm()), rel=1e-4)
    assert scores.motion_epe == pytest.approx(float((motion - gt).norm()), rel=1e-4)
    assert scores.velocity_epe == pytest.approx(float((velocity - gt).norm()), rel=1e-4)
    # on the true dynamic surface the target leaves out, against the truth alone
    assert scores.motion_unsupervised_epe == pytest.approx(float((motion - gt).norm()), rel=1e-4)
    assert scores.velocity_unsupervised_epe == pytest.approx(float((velocity - gt).norm()), rel=1e-4)
    # the triangle the split rests on: the model's error from the truth is at most the target's + its distance from it
    assert scores.velocity_epe <= scores.target_epe + scores.velocity_vs_target_epe + 1e-6
    [pair] = scores.per_pair
    assert pair["velocity_vs_target_epe"] == pytest.approx(scores.velocity_vs_target_epe, rel=1e-6)
    assert pair["motion_vs_target_epe"] == pytest.approx(scores.motion_vs_target_epe, rel=1e-6)
    # without a material field: no velocity figures, the motion ones as before
    still = evaluate_flow_target(plane_model(None), cache, config, truth)
    assert still.velocity_vs_target_epe is None and still.velocity_epe is None and still.velocity_unsupervised_epe is None
    assert still.motion_vs_target_epe == pytest.approx(scores.motion_vs_target_epe, rel=1e-6)
    assert still.per_pair[0]["velocity_vs_target_epe"] is None


# ---------------------------------------------------------------------------------------------------------------
# pidg eval --motion-gt on a tiny procedural run
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A procedural dataset (it carries its ground-truth motion; its depth maps removed) and a 6-step run with a material field, trained by
    the command line."""
    from pidg.cli import main
    from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset

    root = tmp_path_factory.mktemp("motion_eval")
    config = ProceduralSceneConfig(n_train=6, n_test=2, width=32, height=32, n_gaussians=800, n_init_points=300)
    data_dir = write_procedural_dataset(config, root / "data")
    shutil.rmtree(data_dir / "depth")  # as monocular RGB data: the flow target then needs the run's own depth
    assert main(["train", "--data.path", str(data_dir), "--output.dir", str(root / "run"), "--physics", "cmr",
                 "--optim.iterations", "6", "--output.progress", "false", "--output.checkpoint_every", "0",
                 "--output.preview_every", "0", "--densify.start", "1000", "--physics.samples", "64",
                 "--material.width", "16"]) == 0
    return root


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")  # 32 px images are below MS-SSIM's minimum
def test_cli_eval_motion_gt_writes_json_and_one_line(tiny_run, capsys):
    from pidg.cli import main

    run = tiny_run / "run"
    assert main(["eval", str(run), "--motion-gt", "--lpips", "none"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("motion vs ground truth")]
    assert len(lines) == 1 and str(run / "eval_test" / "motion_gt.json") in lines[0]
    data = json.loads((run / "eval_test" / "motion_gt.json").read_text())
    assert data["split"] == "test" and data["flow"]["frames"] == 2 and data["flow"]["pixels"] > 0
    assert data["frame_interval"] == pytest.approx(0.2)
    for key in ("motion_flow_epe", "velocity_flow_epe", "zero_motion_epe"):
        assert data["flow"][key] >= 0
    assert 0 <= data["velocity"]["coverage"] <= 1 and data["velocity"]["times"] == 2
    # the flow target of the 5 training pairs, compensated with the run's own depth (the scene ships none)
    assert data["target"]["pairs"] == 5 and data["target"]["depth"] == "model" and data["target"]["skipped"] == []
    assert "flow target (train pairs, model depth)" in lines[0]
    assert (run / "eval_test" / "metrics.json").is_file()
    pictures = sorted((run / "eval_test" / "motion_flow").iterdir())  # truth | motion | velocity | error per test view
    assert [p.stem for p in pictures] == sorted(r["view"].replace("/", "_") for r in data["per_frame"])
    assert all(Image.open(p).size == (4 * 32, 32 + TITLE_STRIP_PX) for p in pictures)  # four panels under their titles
    # each scored pair's target error, and their pixel-weighted mean is the pooled one
    pairs = data["target"]["per_pair"]
    assert len(pairs) == 5 and len({r["frame"] for r in pairs}) == 5
    assert sum(r["pixels"] for r in pairs) == data["target"]["pixels"]
    pooled = sum(r["target_epe"] * r["pixels"] for r in pairs if r["pixels"]) / data["target"]["pixels"]
    assert pooled == pytest.approx(data["target"]["target_epe"], rel=1e-9)
    # the model's velocity flow against the target over the same pairs: pooled, and per pair in the summary line
    fitted = sorted((r for r in pairs if r["target_epe"] is not None and r["velocity_vs_target_epe"] is not None),
                    key=lambda r: r["time"])
    assert fitted and data["target"]["model_pixels"] > 0 and data["target"]["velocity_vs_target_epe"] >= 0
    assert "the model from it: motion" in lines[0]
    # the per-frame errors drawn over time: one line per flow (and zero motion), a point per test view in time order,
    # then the target's line, a point per scored training pair, and the velocity flow's distance from the target, a
    # point per pair the model covers; the largest error at the plot's top edge, the axis from 0 px
    svg = (run / "eval_test" / "motion_gt_per_frame.svg").read_text()
    ElementTree.fromstring(svg)
    lines_xy = [[tuple(map(float, p.split(","))) for p in pts.split()] for pts in re.findall(r'points="([^"]+)"', svg)]
    assert len(lines_xy) == 5 and all(len(line) == 2 and line[0][0] < line[1][0] for line in lines_xy[:3])
    scored_pairs = [r for r in pairs if r["target_epe"] is not None]
    assert len(lines_xy[3]) == len(scored_pairs) and scored_pairs
    assert all(a[0] < b[0] for a, b in zip(lines_xy[3], lines_xy[3][1:]))  # in time order
    assert len(lines_xy[4]) == len(fitted) and all(a[0] < b[0] for a, b in zip(lines_xy[4], lines_xy[4][1:]))
    values = [r[k] for r in data["per_frame"] for k in ("motion_flow_epe", "velocity_flow_epe", "zero_motion_epe")]
    values += [r["target_epe"] for r in sorted(scored_pairs, key=lambda r: r["time"])]
    values += [r["velocity_vs_target_epe"] for r in fitted]
    ys = [y for line in lines_xy for _, y in line]
    assert ys[_flat_index(data, max(values))] == pytest.approx(12.0, abs=0.051)  # coordinates are written to 0.1
    lowest = 12 + (1 - min(values) / max(values)) * (300 - 40 - 12)  # plot top 12 px, bottom 300 - 40 px = 0 px EPE
    assert ys[_flat_index(data, min(values))] == pytest.approx(lowest, abs=0.051)
    # the 3D tracking per anchor: the Gaussians' error and the true travel, a point per test view
    svg = (run / "eval_test" / "motion_gt_tracking.svg").read_text()
    ElementTree.fromstring(svg)
    tracks = [[tuple(map(float, p.split(","))) for p in pts.split()] for pts in re.findall(r'points="([^"]+)"', svg)]
    assert len(tracks) == 2 and all(len(line) == 2 for line in tracks)
    largest = max(max(r["track_error"], r["track_travel"]) for r in data["per_frame"])
    assert min(y for line in tracks for _, y in line) == pytest.approx(12.0, abs=0.051)  # the largest at the top
    assert largest > 0 and data["tracking"]["anchors"] == 2


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")
def test_cli_eval_motion_gt_passes_the_runs_training_times(tiny_run, capsys):
    """On the training views every scored time and the next are training times: the floor of what they determine
    is 0 there (and it is only computed when the run's training times reach the evaluation)."""
    from pidg.cli import main

    run = tiny_run / "run"
    assert main(["eval", str(run), "--split", "train", "--motion-gt", "--lpips", "none"]) == 0
    data = json.loads((run / "eval_train" / "motion_gt.json").read_text())
    floors = [r["training_times_linear_px"] for r in data["per_frame"] if "training_times_linear_px" in r]
    assert floors and all(f == pytest.approx(0.0, abs=1e-6) for f in floors)
    assert data["velocity"]["training_times_cubic_flow_px"] == pytest.approx(0.0, abs=1e-6)
    # the model's error there is all at the training times, none between them
    v = data["velocity"]
    assert v["seen_flow_px"] > 0 and v["seen_flow_at_training_times_px"] == pytest.approx(v["seen_flow_px"], rel=1e-5)
    assert v["seen_flow_between_training_times_px"] == pytest.approx(0.0, abs=1e-5)
    assert "interpolated linearly 0.000 px" in capsys.readouterr().out


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")
def test_cli_eval_views_from_a_twin_scores_its_views_and_refuses_other_data(tiny_run, capsys):
    """--views-from DIR: the split of DIR, a twin of the run's dataset (here a copy with one test view dropped),
    scored into RUN/eval_SPLIT@DIR's name; a folder whose training frames are not the run's is one line naming it."""
    from pidg.cli import main

    run, twin, other = tiny_run / "run", tiny_run / "twin", tiny_run / "other"
    for folder in (twin, other):
        shutil.copytree(tiny_run / "data", folder, dirs_exist_ok=True)
    image = next((twin / "train").glob("*.png"))  # two renders of one scene may round a pixel differently
    pixels = np.array(Image.open(image))
    pixels[..., :3] = np.where(pixels[..., :3] < 255, pixels[..., :3] + 1, 254)
    Image.fromarray(pixels).save(image)
    transforms = json.loads((twin / "transforms_test.json").read_text())
    transforms["frames"] = transforms["frames"][1:]
    (twin / "transforms_test.json").write_text(json.dumps(transforms))
    assert main(["eval", str(run), "--motion-gt", "--lpips", "none", "--views-from", str(twin)]) == 0
    data = json.loads((run / "eval_test@twin" / "motion_gt.json").read_text())
    assert data["flow"]["frames"] == 1 and len(data["per_frame"]) == 1
    assert data["dataset"] == str(twin)
    assert str(run / "eval_test@twin" / "motion_gt.json") in capsys.readouterr().out
    metrics = json.loads((run / "eval_test@twin" / "metrics.json").read_text())
    assert metrics["views"] == 1 and [v["view"] for v in metrics["per_view"]] == [data["per_frame"][0]["view"]]

    image = next((other / "train").glob("*.png"))
    pixels = np.array(Image.open(image))
    h, w = pixels.shape[0] // 2, pixels.shape[1] // 2
    pixels[h, w, :3] = (pixels[h, w, :3].astype(int) + 128) % 256  # one pixel of one training image, made opaque
    pixels[h, w, 3:] = 255
    Image.fromarray(pixels).save(image)
    assert main(["eval", str(run), "--lpips", "none", "--views-from", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(other) in err[0] and "in its pixels" in err[0] and "twin" in err[0]
    assert not (run / "eval_test@other").exists()


def _flat_index(data: dict, value: float) -> int:
    """Where ``value`` sits in the chart's points (lines in the order motion, velocity, zero, flow target, velocity flow
    from the target; points in time order)."""
    frames = sorted(data["per_frame"], key=lambda r: r["time"])
    flat = [r[k] for k in ("motion_flow_epe", "velocity_flow_epe", "zero_motion_epe") for r in frames]
    pairs = sorted((r for r in data["target"]["per_pair"] if r["target_epe"] is not None), key=lambda r: r["time"])
    fitted = [r["velocity_vs_target_epe"] for r in pairs if r["velocity_vs_target_epe"] is not None]
    return (flat + [r["target_epe"] for r in pairs] + fitted).index(value)


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")
def test_cli_eval_motion_gt_without_truth_is_one_line_naming_the_file(tiny_run, capsys):
    from pidg.cli import main

    truth, hidden = tiny_run / "data" / "motion_gt", tiny_run / "data" / "motion_gt_hidden"
    truth.rename(hidden)
    try:
        assert main(["eval", str(tiny_run / "run"), "--split", "test", "--motion-gt", "--lpips", "none"]) == 2
    finally:
        hidden.rename(truth)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "motion_gt/meta.json" in err[0] and "no ground-truth motion" in err[0]


# ---------------------------------------------------------------------------------------------------------------
# spin: rigid objects' rotation over one frame interval
# ---------------------------------------------------------------------------------------------------------------
def rodrigues(axis: Tensor, degrees: float) -> Tensor:
    """The rotation by ``degrees`` about ``axis``, by Rodrigues' formula (float64): the independent closed form."""
    k = axis.double() / axis.double().norm()
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    theta = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(theta) * cross + (1 - math.cos(theta)) * cross @ cross


@pytest.mark.parametrize("degrees", [0.5, 10.0, 90.0, 179.0])
def test_best_rotation_recovers_a_known_rotation_and_its_angle(degrees):
    g = torch.Generator().manual_seed(3)
    points = torch.randn(40, 3, generator=g, dtype=torch.float64)
    rotation = rodrigues(torch.tensor([0.3, -1.0, 0.5]), degrees)
    moved = points @ rotation.T + torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)  # turned, then carried off
    found, residual = best_rotation(points, moved)
    torch.testing.assert_close(found, rotation, atol=1e-9, rtol=0)
    assert float(residual) < 1e-9 and rotation_angle_deg(found) == pytest.approx(degrees, abs=1e-6)
    # a flat point set (where the unconstrained fit is a reflection) still gives the rotation, det +1
    flat = points.clone()
    flat[:, 2] = 0
    found_flat, _ = best_rotation(flat, flat @ rotation.T)
    assert float(torch.linalg.det(found_flat)) == pytest.approx(1.0)
    torch.testing.assert_close(flat @ found_flat.T, flat @ rotation.T, atol=1e-9, rtol=0)
    # a motion that is not rigid leaves a residual: the points scaled by 1.1 about their mean
    _, stretched = best_rotation(points, 1.1 * (points - points.mean(0)))
    assert float(stretched) > 0.05


class Spin(DeformationModel):
    """Every Gaussian turns about ``centre`` (axis z) by ``rate`` degrees per unit of dataset time."""

    def __init__(self, centre: Tensor, rate: float) -> None:
        super().__init__()
        self.register_buffer("centre", centre.clone())
        self.rate = rate

    def deform(self, means, quats, log_scales, times, regularize=False) -> DeformedGaussians:
        theta = torch.deg2rad(self.rate * times)
        c, s = torch.cos(theta), torch.sin(theta)
        x, y = means[:, 0] - self.centre[0], means[:, 1] - self.centre[1]
        turned = torch.stack([self.centre[0] + c * x - s * y, self.centre[1] + s * x + c * y, means[:, 2]], dim=-1)
        return DeformedGaussians(turned, quats, log_scales)


def spinning_truth(root, rate: float, stretch: float = 0.0):
    """A ring of vertices (one object) turning about (0.2, 0.1, Z) at ``rate`` degrees per unit of dataset time,
    sampled at 0.25 and 0.25 + DT; ``stretch``: it also grows by that fraction per unit of dataset time (not rigid)."""
    angles = torch.linspace(0, 2 * math.pi, 13)[:-1]
    ring = torch.stack([0.2 + 0.4 * torch.cos(angles), 0.1 + 0.3 * torch.sin(angles), torch.full_like(angles, Z)], -1)
    centre = torch.tensor([0.2, 0.1, Z])
    times = (0.25, 0.25 + DT)
    positions = []
    for t in times:
        turned = Spin(centre, rate).deform(ring, torch.zeros(12, 4), torch.zeros(12, 3), torch.full((12,), t)).means
        positions.append((centre + (1 + stretch * t) * (turned - centre)).numpy())
    motion = VertexMotion(np.asarray(times), np.stack(positions).astype(np.float32), np.zeros((2, 12, 3), np.float32),
                          np.zeros((0, 3), np.int64))
    write_motion_gt(root, DT, [MotionObject("ring", "rigid", 0, 12)], motion)
    return read_motion_gt(root), ring, centre


def ring_model(ring: Tensor, deformation: DeformationModel) -> DynamicGaussians:
    n = len(ring)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    gaussians = GaussianModel(ring.clone(), quats, torch.full((n, 3), math.log(0.02)), torch.full((n,), 4.0),
                              torch.rand(n, 1, 3, generator=torch.Generator().manual_seed(0)), torch.zeros(n, 0, 3), sh_degree=0)
    return DynamicGaussians(gaussians, deformation, None, TimeAxis(S, 1.0 / S), torch.zeros(3), backend="cpu")


def ring_spin(model: DynamicGaussians, truth, t: float = 0.25):
    """The spin scores with each vertex at t matched to the Gaussian at the same place (as the 3D velocity's matching
    does), followed as :func:`evaluate_motion` follows them."""
    points = torch.from_numpy(truth.vertices.positions[truth.vertices.index_of(t)])
    gauss = torch.cdist(points, model.at(t).means.detach()).argmin(dim=1)
    matches = {t: (torch.arange(len(points)), gauss, torch.ones(len(points), dtype=torch.bool))}
    return _spin_scores(truth, matches, _follow_matches(model, truth, matches))


def test_spin_is_zero_error_for_gaussians_that_turn_with_the_body_and_the_whole_angle_for_a_translation(tmp_path):
    rate = 80.0  # degrees per unit of dataset time: 10 degrees over one frame interval
    truth, ring, centre = spinning_truth(tmp_path / "motion_gt", rate)
    carried = ring_model(Spin(centre, rate).deform(ring, torch.zeros(12, 4), torch.zeros(12, 3), torch.zeros(12)).means,
                         Spin(centre, rate))
    spin, per_anchor = ring_spin(carried, truth)
    assert spin.intervals == 1 and spin.true_deg == pytest.approx(rate * DT, abs=1e-3)
    assert spin.learned_deg == pytest.approx(rate * DT, abs=1e-3) and spin.error_deg == pytest.approx(0.0, abs=1e-3)
    assert spin.relative == pytest.approx(0.0, abs=1e-4) and spin.per_object == {"ring": pytest.approx(0.0, abs=1e-4)}
    assert per_anchor[0.25]["spin_true_deg"] == pytest.approx(rate * DT, abs=1e-3)
    # Gaussians that follow the body's centre but do not turn: the error is the whole true angle, relative 1
    translated = ring_model(ring, Translation(torch.zeros(3)))
    spin, _ = ring_spin(translated, truth)
    assert spin.learned_deg == pytest.approx(0.0, abs=1e-4) and spin.error_deg == pytest.approx(rate * DT, abs=1e-3)
    assert spin.relative == pytest.approx(1.0, abs=1e-4)
    # turning the other way: twice the angle
    backwards = ring_model(ring, Spin(centre, -rate))
    spin, _ = ring_spin(backwards, truth)
    assert spin.error_deg == pytest.approx(2 * rate * DT, abs=1e-3) and spin.relative == pytest.approx(2.0, abs=1e-3)


def test_spin_leaves_out_bodies_that_barely_turn_or_are_not_rigid(tmp_path):
    slow = SPIN_FLOOR_DEG / DT / 2  # half a floor over one interval
    truth, ring, _ = spinning_truth(tmp_path / "slow", slow)
    model = ring_model(ring, Translation(torch.zeros(3)))
    assert ring_spin(model, truth) == (None, {})
    truth, ring, _ = spinning_truth(tmp_path / "stretching", 80.0, stretch=0.5)  # turns 10 degrees and grows 6 %
    model = ring_model(ring, Translation(torch.zeros(3)))
    assert ring_spin(model, truth) == (None, {})


def test_cli_bench_motion_fit_fits_a_fresh_field_beside_the_trained_one(tiny_run, tmp_path, capsys):
    """`pidg bench motion-fit` on a procedural run (a truth of points, no triangles): the table's two rows and the JSON;
    the fitted fields, taught the truth directly, end nearer to it than the run's 6-step fields (the deformation and,
    the run having one, the material field's v)."""
    from pidg.cli import main

    out = tmp_path / "fit.json"
    assert main(["bench", "motion-fit", str(tiny_run / "run"), "--steps", "150", "--points", "200",
                 "--static-points", "50", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "a fresh field fitted to the true 3D motion in 150 steps" in printed
    assert any(line.startswith("fitted ") for line in printed.splitlines())
    assert any(line.startswith("trained ") for line in printed.splitlines())
    data = json.loads(out.read_text())
    assert data["steps"] == 150 and data["surface_points"] == 200
    assert data["fitted"]["position_relative"] < data["trained"]["position_relative"]
    assert data["fitted_velocity"]["relative"] < data["trained_velocity"]["relative"]
    assert len(data["fitted_velocity"]["relative_by_time"]) == len(data["trained_velocity"]["relative_by_time"]) > 1
    assert "material field v, share of the true speed off: fitted" in printed
    assert main(["bench", "motion-fit", str(tiny_run / "run"), "--points", "2"]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0  # one line
