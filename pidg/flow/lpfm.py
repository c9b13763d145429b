"""The Lagrangian particle flow matching loss (paper eq. L_LPFM; NOTES.md section 8).

    L_LPFM = lambda_g * L1(flow_g, flow_gt) + lambda_v * L1(flow_v, flow_gt)

L1 is the per-pixel L1 norm |dx| + |dy| in pixels, averaged over the supervised pixels: flow_gt valid (motion
mask, consistent flows, valid depth) and rendered alpha above ``FlowConfig.min_alpha``. With
``FlowConfig.lambda_depth_change`` = c > 0 (an extension) each flow's term gains c x its depth-change error
|dz - dz_gt| in pixel-equivalents, averaged over the supervised pixels whose depth change is known. Flows are never clamped
or rescaled, and every field is [H, W, 2] (rows, columns, xy) -- checked, so a [2, H, W] tensor is an error.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.flow.config import FlowConfig
from pidg.flow.decomposition import FlowTarget, depth_change_target, dilate_mask, motion_flow_target
from pidg.flow.preprocess import FlowPair
from pidg.render.api import TILE_SIZE, RenderOutput
from pidg.render.projection import tiles_touched
from pidg.render.output import OPAQUE_ALPHA


@dataclass
class LPFMResult:
    """The loss (a scalar tensor, not yet multiplied by ``lambda_lpfm``) and detached diagnostics."""

    loss: Tensor
    epe_gaussian: float  # mean end-point error of the Gaussian flow on supervised pixels (pixels)
    epe_velocity: float | None  # same for the velocity flow (None without one)
    valid_pixels: int
    mean_target_px: float  # mean |flow_gt| on supervised pixels, to read the EPEs against
    depth_change_error: float | None = None  # mean |dz_v - dz_gt| (|dz - dz_gt| without v), pixel-equivalents

    def scalars(self) -> dict[str, float]:
        out = {"lpfm": float(self.loss.detach()), "epe_gaussian": self.epe_gaussian,
               "valid_pixels": float(self.valid_pixels), "target_px": self.mean_target_px}
        if self.epe_velocity is not None:
            out["epe_velocity"] = self.epe_velocity
        if self.depth_change_error is not None:
            out["depth_change_error"] = self.depth_change_error
        return out


def _check_flow(name: str, flow: Tensor, shape: tuple[int, ...]) -> None:
    if tuple(flow.shape) != (*shape, 2):
        raise ValueError(f"{name} must be [H, W, 2] (or [K, 2] at K pixels) = {[*shape, 2]}, got {list(flow.shape)}")


def _check_valid(valid: Tensor, shape: tuple[int, ...]) -> None:
    if tuple(valid.shape) != shape or valid.dtype != torch.bool:
        raise ValueError(f"valid must be a bool [H, W] (or [K]) = {list(shape)} mask, got {valid.dtype} {list(valid.shape)}")


def end_point_error(flow: Tensor, flow_gt: Tensor, valid: Tensor | None = None) -> Tensor:
    """Mean Euclidean distance |flow - flow_gt| in pixels over ``valid`` pixels (0 when there are none)."""
    shape = tuple(flow_gt.shape[:-1])
    _check_flow("flow_gt", flow_gt, shape)
    _check_flow("flow", flow, shape)
    err = (flow - flow_gt).norm(dim=-1)
    if valid is None:
        return err.mean()
    _check_valid(valid, shape)
    return err[valid].mean() if valid.any() else err.new_zeros(())


def flow_l1(flow: Tensor, flow_gt: Tensor, valid: Tensor) -> Tensor:
    """Mean over ``valid`` pixels of |dx| + |dy| (pixels); a graph-connected 0 when no pixel is valid."""
    diff = (flow - flow_gt).abs().sum(-1)
    count = valid.sum()
    return (diff * valid).sum() / count.clamp_min(1)


def depth_change_l1(depth_change: Tensor, target: FlowTarget, valid: Tensor) -> Tensor:
    """Mean over ``valid`` pixels whose target depth change is known of |dz x scale - dz_gt| (pixel-equivalents);
    ``depth_change`` [H, W] is a rendered camera-t depth change in world units."""
    assert target.depth_change is not None and target.depth_scale is not None
    known = valid & (target.depth_scale > 0)
    diff = (depth_change * target.depth_scale.to(depth_change.dtype) - target.depth_change.to(depth_change.dtype)).abs()
    return (diff * known).sum() / known.sum().clamp_min(1)


def lpfm_loss(
    flow_gaussian: Tensor,
    flow_velocity: Tensor | None,
    target: FlowTarget,
    alpha: Tensor,
    config: FlowConfig,
    depth_changes: tuple[Tensor, Tensor | None] | None = None,
) -> LPFMResult:
    """L_LPFM between rendered flows [H, W, 2] (camera t, :func:`pidg.flow.gaussian_flow.decode_flows`) and the
    motion-flow target on frame t's grid; ``alpha`` [H, W] is the rendered accumulated opacity. ``depth_changes``:
    the rendered depth changes of the Gaussians and of the velocity advection [H, W] (world units,
    :func:`pidg.flow.gaussian_flow.decode_depth_changes`), scored when the target carries its depth change and
    ``config.lambda_depth_change`` > 0. Every field may instead be gathered at K pixels ([K, 2], [K]: the target's
    :meth:`FlowTarget.at` and :func:`pidg.flow.gaussian_flow.decode_flows_at`), for the same loss at less cost."""
    shape = tuple(target.flow.shape[:-1])
    _check_flow("flow_gt", target.flow, shape)
    _check_flow("flow_gaussian", flow_gaussian, shape)
    if flow_velocity is not None:
        _check_flow("flow_velocity", flow_velocity, shape)
    _check_valid(target.valid, shape)
    if tuple(alpha.shape) != shape:
        raise ValueError(f"alpha must be [H, W] = {list(shape)}, got {list(alpha.shape)}")
    valid = target.valid & (alpha.detach() > config.min_alpha)
    gt = target.flow.to(flow_gaussian.dtype)
    loss = config.lambda_gaussian * flow_l1(flow_gaussian, gt, valid)
    epe_v = None
    if flow_velocity is not None:
        loss = loss + config.lambda_velocity * flow_l1(flow_velocity, gt, valid)
        epe_v = float(end_point_error(flow_velocity.detach(), gt, valid))
    dz_error = None
    if depth_changes is not None and target.depth_change is not None and config.lambda_depth_change > 0:
        dz_g, dz_v = depth_changes
        err_g = depth_change_l1(dz_g, target, valid)
        loss = loss + config.lambda_depth_change * config.lambda_gaussian * err_g
        dz_error = float(err_g.detach())
        if dz_v is not None:
            err_v = depth_change_l1(dz_v, target, valid)
            loss = loss + config.lambda_depth_change * config.lambda_velocity * err_v
            dz_error = float(err_v.detach())
    count = int(valid.sum())
    return LPFMResult(
        loss=loss,
        epe_gaussian=float(end_point_error(flow_gaussian.detach(), gt, valid)),
        epe_velocity=epe_v,
        valid_pixels=count,
        mean_target_px=float(gt[valid].norm(dim=-1).mean()) if count else 0.0,
        depth_change_error=dz_error,
    )


def sample_tiles(valid: Tensor, fraction: float, generator: torch.Generator, tile_size: int = TILE_SIZE) -> Tensor:
    """``valid`` [H, W] kept in ``fraction`` of the rasterizer's tiles that hold a valid pixel (at least one tile);
    the rest set False. ``fraction`` 1 returns ``valid`` itself. The kept tiles are a run of consecutive occupied
    tiles in row-major order (a band of the image, wrapping around) from a start drawn with ``generator`` (CPU), so
    every tile is kept with the same probability; a band rather than scattered tiles, because a Gaussian covers
    several tiles: scattered ones would still reach most Gaussians, a band reaches about ``fraction`` of them."""
    if not 0 < fraction <= 1:
        raise ValueError(f"sample_tiles: fraction must be in (0, 1], got {fraction}")
    if fraction == 1:
        return valid
    h, w = valid.shape
    occupied = tiles_touched(valid, tile_size)
    tiles_y, tiles_x = occupied.shape
    candidates = occupied.reshape(-1).cpu().nonzero().squeeze(1)
    if candidates.numel() == 0:
        return valid
    count = max(1, round(fraction * candidates.numel()))
    start = int(torch.randint(candidates.numel(), (1,), generator=generator))
    picked = candidates[(start + torch.arange(count)) % candidates.numel()]
    keep = torch.zeros(tiles_y * tiles_x, dtype=torch.bool)
    keep[picked] = True
    tiles = keep.reshape(tiles_y, 1, tiles_x, 1).expand(tiles_y, tile_size, tiles_x, tile_size)
    return valid & tiles.reshape(tiles_y * tile_size, tiles_x * tile_size)[:h, :w].to(valid.device)


def depth_from_render(render: RenderOutput, min_alpha: float = OPAQUE_ALPHA) -> Tensor:
    """Expected depth [H, W] of a render (frame t+1, camera t+1), 0 (= unknown) where alpha < ``min_alpha``:
    half-transparent pixels mix foreground and background depths, and empty ones have none."""
    with torch.no_grad():  # kept, never differentiated: recording the graph of its full-image operations costs
        return render.opaque_depth(min_alpha)


def total_flow_target(pair: FlowPair, config: FlowConfig) -> FlowTarget:
    """flow_gt of ``FlowConfig.target = "total"``: the pair's forward optical flow itself, on its forward-backward
    consistent pixels, within frame t's motion mask (dilated) where the dataset has one."""
    valid = pair.valid_forward
    if pair.frame0.mask is not None:
        valid = valid & dilate_mask(pair.frame0.mask.to(valid.device), config.mask_dilation)
    return FlowTarget(torch.where(valid.unsqueeze(-1), pair.forward, torch.zeros_like(pair.forward)), valid)


def flow_target_for_pair(pair: FlowPair, depth1: Tensor | None, config: FlowConfig) -> FlowTarget:
    """flow_gt for a cached pair. ``config.target`` "motion" (the paper): the motion flow, given frame t+1's depth
    [H, W] (dataset depth, or the model's render at t+1 in camera t+1 through :func:`depth_from_render`; 0 =
    unknown); motion mask: the dataset's mask of frame t when present, else derived from the motion flow with
    ``config.motion_threshold``; with ``config.lambda_depth_change`` > 0 and frame t's depth map, also the depth
    change (:func:`pidg.flow.decomposition.depth_change_target`). "total": :func:`total_flow_target` (no depth
    needed)."""
    if config.target == "total":
        return total_flow_target(pair, config)
    if depth1 is None:
        raise ValueError("the motion-flow target needs frame t+1's depth")
    target = motion_flow_target(
        depth1,
        pair.frame0.camera,
        pair.frame1.camera,
        pair.forward,
        pair.backward,
        pair.valid_forward,
        pair.valid_backward,
        motion_mask0=pair.frame0.mask,
        dilation=config.mask_dilation,
        motion_threshold=config.motion_threshold,
    )
    if config.lambda_depth_change > 0 and pair.frame0.depth is not None:
        depth0 = pair.frame0.depth.to(device=depth1.device, dtype=depth1.dtype)
        change, scale = depth_change_target(depth0, depth1, pair.frame0.camera, pair.frame1.camera, pair.forward, target.valid)
        target = dataclasses.replace(target, depth_change=change, depth_scale=scale)
    return target
