"""Backward motion-flow decomposition (paper Sec. 4.3 "Optical Flow Decomposition", supp. B; NOTES.md section 6).

Between frames I_t (camera t) and I_{t+1} (camera t+1): a pixel p4 of I_{t+1} with depth D4 is back-projected with
camera t+1 and re-projected with camera t to p2, which is where that scene point -- *at its t+1 position* --
appears in camera t. The backward optical flow gives p1 = p4 + b(p4), where the same point was seen at time t.
Hence

    camera flow = p4 - p2        (what the camera change alone does to the point)
    motion flow = p2 - p1        (the point's own motion t -> t+1, as camera t sees it)

The motion flow lives on I_{t+1}'s pixel grid; it is carried onto I_t's grid with the forward flow (value at
p + f(p) for each pixel p of I_t), so that it can be compared with the Gaussian flow rendered in camera t without
warping the rendered flow. The functions here are plain torch on [H, W, ...] tensors (any float dtype), no model;
``motion_flow_target`` runs the numba kernels of :mod:`pidg.flow.decomposition_cpu` on float32 CPU tensors, with
these functions as their reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from pidg.flow.decomposition_cpu import motion_flow_target_cpu
from pidg.flow.optical_flow import pixel_centers, sample_bilinear, sample_mask
from pidg.render.camera import Camera


@dataclass
class FlowTarget:
    """A flow field [H, W, 2] in pixels with its validity [H, W] (flow is 0 where invalid), and optionally the
    surface's depth change over the pair (:func:`depth_change_target`), which a 2D flow cannot see."""

    flow: Tensor
    valid: Tensor
    depth_change: Tensor | None = None
    """[H, W] camera-t depth change z(t+1) - z(t) of the surface point at each pixel, in *pixel-equivalents*: times
    ``depth_scale`` (0 where unknown)."""
    depth_scale: Tensor | None = None
    """[H, W] pixels per world unit, fx / z(t): converts a depth change in world units to the lateral image motion of
    the same 3D size, so that it weighs like a flow; 0 where the depth change is unknown."""

    def at(self, index: Tensor) -> "FlowTarget":
        """The target at K pixels, every field gathered to [K, ...]: ``index`` [K] holds row-major pixel indices
        (y * W + x, e.g. ``mask.reshape(-1).nonzero().squeeze(1)``); what a loss that reads only those pixels needs."""
        pick = lambda t: None if t is None else t.reshape(-1, *t.shape[2:]).index_select(0, index)  # noqa: E731
        return FlowTarget(pick(self.flow), pick(self.valid), pick(self.depth_change), pick(self.depth_scale))  # type: ignore[arg-type]


@dataclass
class BackwardDecomposition:
    """Camera and motion flow on frame t+1's pixel grid (both 0 where ``valid`` is False)."""

    camera_flow: Tensor  # [H, W, 2] p4 - p2
    motion_flow: Tensor  # [H, W, 2] p2 - p1
    valid: Tensor  # [H, W] bool: valid depth, in front of camera t, consistent backward flow


def _check_field(name: str, t: Tensor, h: int, w: int, channels: int | None) -> None:
    expected = (h, w) if channels is None else (h, w, channels)
    if tuple(t.shape) != expected:
        raise ValueError(f"{name} must have shape {list(expected)} (rows, columns[, xy]), got {list(t.shape)}")


def backproject(depth: Tensor, camera: Camera) -> Tensor:
    """World points [H, W, 3] of every pixel centre at camera-space depth ``depth`` [H, W] (z, not ray length)."""
    h, w = depth.shape
    return unproject_points(pixel_centers(h, w, depth.dtype, depth.device), depth, camera)


def unproject_points(pixels: Tensor, depth: Tensor, camera: Camera) -> Tensor:
    """World points [..., 3] of image positions ``pixels`` [..., 2] (x right, y down, centre convention) at
    camera-space depths ``depth`` [...] (z, not ray length): the inverse of ``Camera.project_points``."""
    x = (pixels[..., 0] - camera.cx) / camera.fx * depth
    y = (pixels[..., 1] - camera.cy) / camera.fy * depth
    cam = torch.stack([x, y, depth], dim=-1)
    # The exact inverse rather than R^T: a float32 rotation is orthogonal only to ~1e-7, and the re-projection
    # must invert Camera.project_points to well below a pixel's thousandth.
    c2w = torch.linalg.inv(camera.world_to_camera.to(device=depth.device, dtype=torch.float64)).to(depth.dtype)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def decompose_backward_flow(
    depth1: Tensor, camera0: Camera, camera1: Camera, backward: Tensor, valid_backward: Tensor | None = None
) -> BackwardDecomposition:
    """Camera flow and motion flow on frame t+1's grid from its depth ``depth1`` [H, W] (camera z; <= near,
    NaN or inf = unknown) and the backward optical flow ``backward`` [H, W, 2] (t+1 -> t)."""
    h, w = depth1.shape
    _check_field("backward flow", backward, h, w, 2)
    if (camera1.width, camera1.height) != (w, h):
        raise ValueError(f"depth is {w}x{h} but camera t+1 renders {camera1.width}x{camera1.height}")
    dtype = depth1.dtype
    p4 = pixel_centers(h, w, dtype, depth1.device)
    depth_ok = torch.isfinite(depth1) & (depth1 > camera1.near)
    safe_depth = torch.where(depth_ok, depth1, torch.ones_like(depth1))
    world = backproject(safe_depth, camera1)
    p2, z0 = camera0.project_points(world.reshape(-1, 3))
    p2, z0 = p2.reshape(h, w, 2), z0.reshape(h, w)
    p1 = p4 + backward.to(dtype)
    valid = depth_ok & (z0 > camera0.near)
    if valid_backward is not None:
        _check_field("valid_backward", valid_backward, h, w, None)
        valid = valid & valid_backward
    zero = torch.zeros_like(p4)
    keep = valid.unsqueeze(-1)
    return BackwardDecomposition(
        camera_flow=torch.where(keep, p4 - p2, zero), motion_flow=torch.where(keep, p2 - p1, zero), valid=valid
    )


def warp_to_first_frame(field: FlowTarget, forward: Tensor, valid_forward: Tensor | None = None) -> FlowTarget:
    """Carry a flow defined on frame t+1's grid onto frame t's: value(p) = bilinear lookup at p + f(p).

    Valid where the forward flow is consistent, p + f(p) lies inside the image and every pixel that the lookup
    mixes is valid (so no invalid zero is blended in).
    """
    h, w, _ = field.flow.shape
    _check_field("forward flow", forward, h, w, 2)
    target = pixel_centers(h, w, field.flow.dtype, field.flow.device) + forward.to(field.flow.dtype)
    values, _ = sample_bilinear(field.flow, target)
    valid = sample_mask(field.valid, target)
    if valid_forward is not None:
        _check_field("valid_forward", valid_forward, h, w, None)
        valid = valid & valid_forward
    return FlowTarget(torch.where(valid.unsqueeze(-1), values, torch.zeros_like(values)), valid)


def dilate_mask(mask: Tensor, radius: int) -> Tensor:
    """Bool [H, W] mask grown by ``radius`` pixels (square structuring element), for masks drawn a bit tight."""
    if radius <= 0:
        return mask.bool()
    grown = F.max_pool2d(mask.float()[None, None], kernel_size=2 * radius + 1, stride=1, padding=radius)
    return grown[0, 0] > 0.5


DEPTH_EDGE_TOLERANCE = 0.05
"""Largest relative depth range in a pixel's 3x3 neighbourhood for its depth to count as one smooth surface: a
lookup across an occluding edge would mix foreground and background depths."""


def smooth_depth(depth: Tensor, near: float, tolerance: float = DEPTH_EDGE_TOLERANCE) -> Tensor:
    """[H, W] bool: finite depth beyond ``near`` whose 3x3 neighbourhood (valid neighbours) spans at most
    ``tolerance`` of it."""
    ok = torch.isfinite(depth) & (depth > near)
    inf = torch.full_like(depth, float("inf"))
    hi = F.max_pool2d(torch.where(ok, depth, -inf)[None, None], 3, stride=1, padding=1)[0, 0]
    lo = -F.max_pool2d(torch.where(ok, -depth, -inf)[None, None], 3, stride=1, padding=1)[0, 0]
    return ok & (hi - lo <= tolerance * torch.where(ok, depth, inf))


def depth_change_target(
    depth0: Tensor, depth1: Tensor, camera0: Camera, camera1: Camera, forward: Tensor, valid: Tensor
) -> tuple[Tensor, Tensor]:
    """The third component of the motion that a 2D flow cannot see: for each pixel p of frame t, camera t's depth of
    the surface point's t+1 position (frame t+1's depth at p + f(p), back-projected with camera t+1 and looked up
    bilinearly) minus its depth at t (frame t's depth at p). Camera motion cancels as in the motion flow.

    ``depth0`` / ``depth1`` [H, W]: camera-z depth maps of frames t and t+1 (<= near, NaN or inf = unknown);
    ``forward`` [H, W, 2]: the optical flow t -> t+1; ``valid`` [H, W]: the pixels the flow target supervises.
    Returns (``depth_change``, ``depth_scale``) [H, W] as :class:`FlowTarget` holds them: the change in
    pixel-equivalents (fx / z(t) x the change in world units) and that factor; both 0 where either depth is
    missing or not smooth (:func:`smooth_depth`), or the lookup leaves the hull of frame t+1's pixel centres.
    The bilinear lookup of a smooth depth field is exact to second order (0.01 % on a tilted plane)."""
    h, w = depth0.shape
    for name, field in (("depth1", depth1), ("valid", valid)):
        _check_field(name, field, h, w, None)
    _check_field("forward flow", forward, h, w, 2)
    dtype = depth1.dtype
    ok1 = smooth_depth(depth1, camera1.near)
    world = backproject(torch.where(ok1, depth1, torch.ones_like(depth1)), camera1)
    _, z_in_t = camera0.project_points(world.reshape(-1, 3))
    z_in_t = z_in_t.reshape(h, w).to(dtype)
    lookup = pixel_centers(h, w, dtype, depth1.device) + forward.to(dtype)
    z1, _ = sample_bilinear(z_in_t.unsqueeze(-1), lookup)
    between_centres = ((lookup >= 0.5) & (lookup <= lookup.new_tensor([w - 0.5, h - 0.5]))).all(-1)  # no edge padding
    known = valid & smooth_depth(depth0, camera0.near) & sample_mask(ok1, lookup) & between_centres
    scale = torch.where(known, camera0.fx / torch.where(known, depth0, torch.ones_like(depth0)), torch.zeros_like(depth0))
    change = torch.where(known, (z1[..., 0] - depth0) * scale, torch.zeros_like(depth0))
    return change, scale.to(dtype)


def motion_mask_from_flow(flow: Tensor, valid: Tensor, threshold: float) -> Tensor:
    """Moving pixels [H, W] bool: camera-compensated (motion) flow longer than ``threshold`` pixels, where valid.

    The fallback when a dataset ships no motion masks; equally usable to label pixels for static/dynamic
    decoupling from any motion flow.
    """
    _check_field("valid", valid, flow.shape[0], flow.shape[1], None)
    return valid & (flow.norm(dim=-1) > threshold)


def motion_flow_target(
    depth1: Tensor,
    camera0: Camera,
    camera1: Camera,
    forward: Tensor,
    backward: Tensor,
    valid_forward: Tensor | None = None,
    valid_backward: Tensor | None = None,
    motion_mask0: Tensor | None = None,
    dilation: int = 0,
    motion_threshold: float = 1.0,
    kernel: bool | None = None,
) -> FlowTarget:
    """flow_gt on frame t's pixel grid, the supervision of the Gaussian and velocity flows rendered in camera t.

    ``motion_mask0`` [H, W] bool is frame t's motion mask (dataset); without one, moving pixels are those whose
    warped motion flow exceeds ``motion_threshold`` pixels. The mask is dilated by ``dilation`` pixels and ANDed
    with the validity (consistent forward and backward flow, lookup inside the image, valid depth); flow_gt is 0
    wherever the result is False.

    ``kernel``: the numba kernels of :mod:`pidg.flow.decomposition_cpu` (float32; the default for float32 CPU
    tensors) or, False, the torch functions of this module (any device and dtype; the readable reference the tests
    compare with).
    """
    h, w = depth1.shape
    _check_field("backward flow", backward, h, w, 2)
    _check_field("forward flow", forward, h, w, 2)
    if (camera1.width, camera1.height) != (w, h):
        raise ValueError(f"depth is {w}x{h} but camera t+1 renders {camera1.width}x{camera1.height}")
    for name, field in (("valid_forward", valid_forward), ("valid_backward", valid_backward), ("motion mask", motion_mask0)):
        if field is not None:
            _check_field(name, field, h, w, None)
    if kernel is None:  # float64 inputs ask for float64 results: the reference path
        kernel = depth1.device.type == "cpu" and depth1.dtype == torch.float32
    if kernel:
        flow, valid = motion_flow_target_cpu(
            depth1, camera0, camera1, forward, backward, valid_forward, valid_backward, motion_mask0, dilation, motion_threshold
        )
        return FlowTarget(flow.to(depth1.dtype), valid)
    decomposition = decompose_backward_flow(depth1, camera0, camera1, backward, valid_backward)
    warped = warp_to_first_frame(FlowTarget(decomposition.motion_flow, decomposition.valid), forward, valid_forward)
    if motion_mask0 is None:
        motion_mask0 = motion_mask_from_flow(warped.flow, warped.valid, motion_threshold)
    else:
        _check_field("motion mask", motion_mask0, *warped.valid.shape, None)
    valid = warped.valid & dilate_mask(motion_mask0.to(warped.valid.device), dilation)
    return FlowTarget(torch.where(valid.unsqueeze(-1), warped.flow, torch.zeros_like(warped.flow)), valid)
