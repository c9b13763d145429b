"""The flows of a scene model: Gaussian- and velocity-flow channels for a render, and motion-flow targets built
with the model's own depth. The LPFM loss term uses them while training; evaluation and pictures use them after.

All flows are in pixels of frame t's camera, from dataset time t to t+1 (``FlowPair.dt`` apart).
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.flow.config import FlowConfig
from pidg.flow.decomposition import FlowTarget
from pidg.flow.gaussian_flow import decode_flows, gaussian_flow_features
from pidg.flow.lpfm import LPFMResult, depth_from_render, flow_target_for_pair, lpfm_loss
from pidg.flow.preprocess import FlowPair
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render import Camera, RenderOutput


def flow_channels(
    model: DynamicGaussians, camera: Camera, state_t: DeformedGaussians, state_t1: DeformedGaussians, t: float, dt: float
) -> Tensor:
    """Per-Gaussian flow channels [N, 8] ([N, 6] without a material field) for a render in ``camera`` (frame t's):
    the Gaussians at t and t+1 (``state_t``, ``state_t1``), and their velocities at t advected over ``dt`` (dataset
    time, converted to the field's physics time units by the model's time axis)."""
    v = model.velocities(t, state_t.means) if model.material_field is not None else None
    return gaussian_flow_features(
        camera, state_t.means, state_t.quats, state_t.log_scales.exp(), model.gaussians.opacities,
        state_t1.means, state_t1.quats, state_t1.log_scales.exp(), v, model.time_axis.to_physics(dt),
    )


@torch.no_grad()
def rendered_depth(model: DynamicGaussians, state: DeformedGaussians, camera: Camera) -> Tensor:
    """The model's expected depth [H, W] (camera z, world units; 0 = unknown) of Gaussians placed at some time."""
    detached = DeformedGaussians(state.means.detach(), state.quats.detach(), state.log_scales.detach())
    return depth_from_render(model.render_state(detached, camera))


def model_flow_target(
    model: DynamicGaussians, pair: FlowPair, state_t1: DeformedGaussians, config: FlowConfig
) -> tuple[FlowTarget, Tensor | None]:
    """flow_gt of a pair, and the rendered depth it used (None when the dataset's): frame t+1's depth is the
    dataset's depth map when it has one, else the model's own render at t+1 in camera t+1."""
    if pair.frame1.depth is not None:
        return flow_target_for_pair(pair, pair.frame1.depth, config), None
    depth = rendered_depth(model, state_t1, pair.frame1.camera)
    return flow_target_for_pair(pair, depth, config), depth


@torch.no_grad()
def render_pair_flows(model: DynamicGaussians, pair: FlowPair, config: FlowConfig) -> tuple[RenderOutput, FlowTarget, LPFMResult]:
    """Frame t of a pair rendered with its flow channels, the pair's target, and the flow loss and errors."""
    state_t, state_t1 = model.at(pair.frame0.time), model.at(pair.frame1.time)
    camera = pair.frame0.camera
    out = model.render_state(state_t, camera, flow_channels(model, camera, state_t, state_t1, pair.frame0.time, pair.dt))
    target, _ = model_flow_target(model, pair, state_t1, config)
    flow_g, flow_v, _ = decode_flows(out.features, out.alpha)
    return out, target, lpfm_loss(flow_g, flow_v, target, out.alpha, config)
