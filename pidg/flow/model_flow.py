"""The flows of a scene model: Gaussian- and velocity-flow channels for a render, and motion-flow targets built
with the model's own depth. The LPFM loss term uses them while training; evaluation and pictures use them after.

All flows are in pixels of frame t's camera, from dataset time t to t+1 (``FlowPair.dt`` apart).
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.flow.config import FlowConfig, VelocityIntegration
from pidg.flow.decomposition import FlowTarget
from pidg.flow.gaussian_flow import (
    DECODE_MIN_ALPHA,
    decode_depth_changes_at,
    decode_flows,
    decode_flows_at,
    flow_channel_count,
    gaussian_flow_features,
)
from pidg.flow.lpfm import LPFMResult, depth_from_render, flow_target_for_pair, lpfm_loss
from pidg.flow.lpfm_cpu import flow_l1_at_pixels_cpu
from pidg.flow.preprocess import FlowPair
from pidg.kernel_math import select_distinct_rows
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render import Camera, RenderOutput
from pidg.render.api import PreparedRender, gaussians_reaching


def interval_velocity(
    model: DynamicGaussians, t: float, dt: float, means: Tensor, rows: Tensor | None = None,
    integration: VelocityIntegration = "euler",
) -> Tensor:
    """The constant velocity [N, 3] (world units per physics time unit) that carries each particle from ``means``
    at dataset time t to where the material field moves it over ``dt`` (dataset time) by ``integration``
    (``FlowConfig.velocity_integration``): euler, v(x, t); midpoint, v at the end of an Euler half step,
    v(x + v(x, t) dt / 2, t + dt / 2), so that x + (that velocity) * dt is the explicit midpoint rule (dt in physics
    time there, ``TimeAxis.to_physics``). ``rows``: as in :meth:`DynamicGaussians.velocities` (``means`` are then
    those Gaussians')."""
    if integration not in ("euler", "midpoint"):
        raise ValueError(f"velocity integration must be 'euler' or 'midpoint', got {integration!r}")
    v = model.velocities(t, means, rows=rows)
    if integration == "euler":
        return v
    half_step = 0.5 * model.time_axis.to_physics(dt)
    return model.velocities(t + 0.5 * dt, means + half_step * v, rows=rows)


def flow_channels(
    model: DynamicGaussians, camera: Camera, state_t: DeformedGaussians, state_t1: DeformedGaussians, t: float, dt: float,
    camera_t1: Camera | None = None, integration: VelocityIntegration = "euler",
) -> Tensor:
    """Per-Gaussian flow channels [N, 8] ([N, 6] without a material field) for a render in ``camera`` (frame t's):
    the Gaussians at t and t+1 (``state_t``, ``state_t1``), and their velocities at t advected over ``dt`` (dataset
    time, converted to the field's physics time units by the model's time axis; by ``integration``, see
    :func:`interval_velocity`). ``camera_t1``: None for the motion flow (camera t at both times), frame t+1's camera
    for the total flow."""
    v = interval_velocity(model, t, dt, state_t.means, integration=integration) if model.material_field is not None else None
    return gaussian_flow_features(
        camera, state_t.means, state_t.quats, state_t.log_scales.exp(), model.gaussians.opacities,
        state_t1.means, state_t1.quats, state_t1.log_scales.exp(), v, model.time_axis.to_physics(dt), camera_t1,
        model.backend,
    )


def flow_camera_t1(pair: FlowPair, config: FlowConfig) -> Camera | None:
    """The camera that sees the Gaussians at t+1 in the rendered flows: frame t+1's for the total-flow target,
    None (frame t's: the motion flow) for the paper's motion-flow target."""
    return pair.frame1.camera if config.target == "total" else None


def supervised_flow_channels(
    model: DynamicGaussians,
    screen: PreparedRender,
    state_t: DeformedGaussians,
    t: float,
    t1: float,
    dt: float,
    supervised: Tensor,
    deforming: bool = True,
    camera_t1: Camera | None = None,
    depth_change: bool = False,
    integration: VelocityIntegration = "euler",
) -> Tensor:
    """:func:`flow_channels` [N, C] for a loss that reads the rendered flows only at ``supervised`` pixels [H, W]
    of camera t, to be composited into ``screen``, the render of ``state_t`` in camera t (``prepare_render``): rows
    of Gaussians that add nothing there are zero (:func:`pidg.render.api.gaussians_reaching`, on the render's own
    projection and tile lists: on the cpu backend those the compositor gives no weight at any of them, hidden or
    too faint; elsewhere those whose footprint misses them all), so the deformation to t+1 (``t1``), the velocities
    and the flow channels are computed, and differentiated, for the others only. The loss and its gradients are
    those of the full channels.
    ``deforming`` False (a static warm-up): the Gaussians at t+1 are the canonical ones. ``camera_t1``: as in
    :func:`flow_channels`. ``depth_change``: with the depth-change channels (:mod:`pidg.flow.gaussian_flow`).
    ``integration``: how the velocity flow carries the particles (:func:`interval_velocity`)."""
    n = state_t.means.shape[0]
    has_field = model.material_field is not None
    channels = flow_channel_count(has_field, depth_change)
    camera = screen.camera
    rows = gaussians_reaching(screen, supervised).nonzero().squeeze(1)
    out = state_t.means.new_zeros(n, channels)
    if rows.numel() == 0:
        return out
    invariant = state_t.invariant_of(rows)
    sub_t = DeformedGaussians(*(x.index_select(0, rows) for x in (state_t.means, state_t.quats, state_t.log_scales)),
                              invariant=invariant)
    if deforming:
        sub_t1 = model.at(t1, rows=rows, reuse=sub_t)
    else:
        p = model.gaussians.params
        sub_t1 = DeformedGaussians(*(p[name].index_select(0, rows) for name in ("means", "quats", "log_scales")))
    v = interval_velocity(model, t, dt, sub_t.means, rows, integration) if has_field else None
    sub = gaussian_flow_features(
        camera, sub_t.means, sub_t.quats, sub_t.log_scales.exp(), model.gaussians.opacities.index_select(0, rows),
        sub_t1.means, sub_t1.quats, sub_t1.log_scales.exp(), v, model.time_axis.to_physics(dt), camera_t1,
        model.backend, depth_change,
    )
    return out.index_copy(0, rows, sub.to(out.dtype))


def supervised_flow_loss(
    features: Tensor, alpha: Tensor, target: FlowTarget, config: FlowConfig, kernel: bool | None = None
) -> LPFMResult:
    """:func:`pidg.flow.lpfm.lpfm_loss` of a render's flow channels [H, W, C] (alpha [H, W]) against ``target``,
    decoding and scoring only the target's valid pixels: the loss reads nothing else, and they are a few % of
    the image (moving objects, a share of the tiles). The same loss, diagnostics and gradients as decoding the
    whole render with :func:`pidg.flow.gaussian_flow.decode_flows`. ``kernel``: decode and score in one numba
    pass each way (:mod:`pidg.flow.lpfm_cpu`; the default for float32 CPU channels without depth-change ones) or,
    False, with the torch functions (any device; the reference the tests compare with)."""
    index = target.valid.reshape(-1).nonzero().squeeze(1)  # row-major pixel indices y * W + x
    width = target.valid.shape[1]
    features = select_distinct_rows(features.reshape(-1, features.shape[-1]), index)
    alpha = select_distinct_rows(alpha.reshape(-1, 1), index).squeeze(1)
    x, y = index % width, torch.div(index, width, rounding_mode="floor")
    centers = torch.stack([x, y], dim=-1).to(features.dtype) + 0.5
    at = target.at(index)
    if kernel is None:
        kernel = features.device.type == "cpu" and features.dtype == torch.float32 and features.shape[-1] in (6, 8)
    if kernel:
        loss, count, epe_g, epe_v, size = flow_l1_at_pixels_cpu(
            features, alpha, centers, at.flow.to(features.dtype), at.valid, DECODE_MIN_ALPHA, config.min_alpha,
            config.lambda_gaussian, config.lambda_velocity,
        )
        return LPFMResult(loss, epe_g, epe_v, count, size)
    flow_g, flow_v, _ = decode_flows_at(features, alpha, centers)
    depth_changes = decode_depth_changes_at(features, alpha) if target.depth_change is not None else None
    return lpfm_loss(flow_g, flow_v, at, alpha, config, depth_changes)


@torch.no_grad()
def rendered_depth(model: DynamicGaussians, state: DeformedGaussians, camera: Camera) -> Tensor:
    """The model's expected depth [H, W] (camera z, world units; 0 = unknown) of Gaussians placed at some time."""
    detached = DeformedGaussians(state.means.detach(), state.quats.detach(), state.log_scales.detach())
    return depth_from_render(model.render_state(detached, camera))


def model_flow_target(
    model: DynamicGaussians, pair: FlowPair, state_t1: DeformedGaussians | None, config: FlowConfig
) -> tuple[FlowTarget, Tensor | None]:
    """flow_gt of a pair, and the rendered depth it used (None when the dataset's, or none was needed): frame t+1's
    depth is the dataset's depth map when it has one, else the model's own render of ``state_t1`` (the Gaussians at
    t+1; None: ``model.at(t+1)``) in camera t+1. The total-flow target (``config.target``) needs no depth."""
    if config.target == "total" or pair.frame1.depth is not None:
        return flow_target_for_pair(pair, pair.frame1.depth, config), None
    if state_t1 is None:
        with torch.no_grad():
            state_t1 = model.at(pair.frame1.time)
    depth = rendered_depth(model, state_t1, pair.frame1.camera)
    return flow_target_for_pair(pair, depth, config), depth


@torch.no_grad()
def render_pair_flows(model: DynamicGaussians, pair: FlowPair, config: FlowConfig) -> tuple[RenderOutput, FlowTarget, LPFMResult]:
    """Frame t of a pair rendered with its flow channels, the pair's target, and the flow loss and errors (motion or
    total flows, as ``config.target``)."""
    state_t, state_t1 = model.at(pair.frame0.time), model.at(pair.frame1.time)
    camera = pair.frame0.camera
    channels = flow_channels(model, camera, state_t, state_t1, pair.frame0.time, pair.dt, flow_camera_t1(pair, config),
                             config.velocity_integration)
    out = model.render_state(state_t, camera, channels)
    target, _ = model_flow_target(model, pair, state_t1, config)
    flow_g, flow_v, _ = decode_flows(out.features, out.alpha)
    return out, target, lpfm_loss(flow_g, flow_v, target, out.alpha, config)
