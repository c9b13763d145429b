"""Pictures of what a trained run has learnt beyond colour: velocity and stress of the material field, the three
flows of the flow loss side by side, the learned flows beside the true motion, and the static/dynamic split. Used
by ``pidg render`` and ``pidg eval --motion-gt``.

Everything is rendered through the ordinary rasterizer with extra per-Gaussian feature channels, so a pixel shows
the compositing-weighted average over the Gaussians it sees (divided by alpha).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.evaluation.flow_vis import flow_quiver, flow_rgb_tensor
from pidg.evaluation.images import colorize_scalar
from pidg.evaluation.motion import FrameFlows
from pidg.flow import FlowConfig, FlowPair, decode_flows, render_pair_flows
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.material_field import stress_magnitude

MIN_ALPHA = 0.5  # pixels less opaque than this show no field value (they mix surface and background)


@dataclass
class FieldImages:
    """[H, W, 3] float images in [0, 1] of one view at one time, and the scalars their colour scales used."""

    velocity: Tensor  # projected velocity (pixels per unit of dt) on the flow colour wheel
    quiver: Tensor  # the same as arrows over the rendered image, the largest scaled to 0.9x the arrow spacing
    stress: Tensor  # Frobenius norm of sigma, colour ramp
    max_velocity_px: float
    max_stress: float


def _per_pixel(features: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    valid = alpha > MIN_ALPHA
    return torch.where(valid.unsqueeze(-1), features / alpha.clamp_min(1e-6).unsqueeze(-1), 0.0), valid


@torch.no_grad()
def material_field_images(
    model: DynamicGaussians, frame: Frame, dt: float, max_velocity_px: float | None = None, max_stress: float | None = None
) -> FieldImages:
    """Velocity and stress of the material field at the Gaussians' positions at ``frame.time``, seen from its camera
    (the velocity as the model defines it: static Gaussians, once decoupled, have none).

    The projected velocity of a Gaussian is proj(x + v dt) - proj(x) in pixels (``dt`` in the field's physics time
    units, see :class:`pidg.models.time_axis.TimeAxis`); pass the same ``max_*`` for every frame of a video so
    colours mean the same thing over time.
    """
    state = model.at(frame.time)
    means = state.means
    v = model.velocities(frame.time, means)  # 0 on static Gaussians once decoupled: they do not move
    sigma = model.field_values(means, frame.time)[1]
    uv, _ = frame.camera.project_points(means)
    uv_next, _ = frame.camera.project_points(means + v * dt)
    features = torch.cat([uv_next - uv, stress_magnitude(sigma).unsqueeze(-1)], dim=-1)
    out = model.render_state(state, frame.camera, features)
    values, valid = _per_pixel(out.features, out.alpha)
    flow, stress_img = values[..., :2], values[..., 2]
    vmax = max_velocity_px if max_velocity_px is not None else float(flow[valid].norm(dim=-1).max()) if valid.any() else 1.0
    smax = max_stress if max_stress is not None else float(stress_img[valid].max()) if valid.any() else 1.0
    rgb = out.rgb.clamp(0, 1)
    step = max(8, frame.width // 24)
    # arrows drawn so that the largest velocity spans 90 % of the arrow spacing (sub-pixel motion stays visible)
    quiver = flow_quiver(
        flow, rgb, step=step, scale=0.9 * step / max(vmax, 1e-6), valid=valid, max_magnitude=vmax, min_magnitude=0.05 * vmax
    )
    return FieldImages(
        velocity=flow_rgb_tensor(flow, max(vmax, 1e-6), valid),
        quiver=torch.from_numpy(quiver.copy()).float() / 255.0,
        stress=colorize_scalar(stress_img, valid=valid, lo=0.0, hi=max(smax, 1e-12)),
        max_velocity_px=vmax,
        max_stress=smax,
    )


@torch.no_grad()
def flow_comparison(
    model: DynamicGaussians, pair: FlowPair, config: FlowConfig, max_magnitude: float | None = None
) -> tuple[Tensor, dict[str, float]]:
    """[H, 3W, 3]: motion flow (flow_gt, black where unsupervised) | Gaussian flow | velocity flow, all on frame t's
    pixels and one colour scale; and the end-point errors of the rendered flows on the supervised pixels."""
    out, target, result = render_pair_flows(model, pair, config)
    flow_g, flow_v, drawn = decode_flows(out.features, out.alpha)
    scale = max_magnitude if max_magnitude is not None else float(target.flow[target.valid].norm(dim=-1).max()) if target.valid.any() else 1.0
    scale = max(scale, 1e-6)
    panels = [
        flow_rgb_tensor(target.flow, scale, target.valid),
        flow_rgb_tensor(flow_g, scale, drawn),
        flow_rgb_tensor(flow_v, scale, drawn),
    ]
    errors = {"gaussian_flow_epe": result.epe_gaussian, "velocity_flow_epe": result.epe_velocity or float("nan")}
    return torch.cat(panels, dim=1), errors


def truth_flow_comparison(flows: FrameFlows) -> tuple[Tensor, float]:
    """[H, 4W, 3]: the true motion flow | the model's motion flow | its velocity flow (black without a material
    field) | the end-point error of the velocity flow (of the motion flow without one), dark blue (0) to yellow, on
    the scored pixels only (black elsewhere: no true dynamic surface, or not covered by the model). The flows share
    one colour wheel saturated at the largest true motion on the scored pixels, and the error ramp tops out there
    too; that magnitude (pixels) is returned."""
    truth, scored, model = flows.truth.cpu(), flows.scored.cpu(), flows.model
    scale = max(float(truth[scored].norm(dim=-1).max()), 1e-6) if bool(scored.any()) else 1.0
    learned = (model.velocity if model.velocity is not None else model.motion).cpu()
    error = (learned - truth).norm(dim=-1).nan_to_num(0.0)
    velocity = flow_rgb_tensor(model.velocity, scale, scored) if model.velocity is not None else torch.zeros(*scored.shape, 3)
    panels = [flow_rgb_tensor(truth, scale, scored), flow_rgb_tensor(model.motion, scale, scored), velocity,
              colorize_scalar(error, scored, lo=0.0, hi=scale)]
    return torch.cat(panels, dim=1), scale


def truth_flow_titles(flows: FrameFlows, scale: float) -> list[str]:
    """Titles of :func:`truth_flow_comparison`'s four panels (``scale``: the px its error ramp tops out at), for
    :func:`pidg.evaluation.images.with_titles`."""
    has_velocity = flows.model.velocity is not None
    learned = "velocity" if has_velocity else "motion"
    return ["true motion flow", "model's motion flow", "velocity flow" if has_velocity else "no material field",
            f"{learned}-flow error, 0-{scale:.1f} px"]


@torch.no_grad()
def dynamic_split_image(model: DynamicGaussians, frame: Frame) -> Tensor:
    """The render tinted by the decoupling: dynamic Gaussians red, static ones blue (weighted per pixel)."""
    if model.dynamic_mask is None:
        raise ValueError("this model has no static/dynamic split (decoupling runs when the data has motion masks)")
    state = model.at(frame.time)
    out = model.render_state(state, frame.camera, model.dynamic_mask.to(state.means.dtype).unsqueeze(-1))
    share, _ = _per_pixel(out.features, out.alpha)
    tint = torch.stack([share[..., 0], torch.zeros_like(share[..., 0]), 1.0 - share[..., 0]], dim=-1)
    weight = (out.alpha > 0.05).to(tint.dtype).unsqueeze(-1) * 0.5
    gray = out.rgb.clamp(0, 1).mean(-1, keepdim=True).expand(-1, -1, 3)
    return gray * (1.0 - weight) + tint * weight
