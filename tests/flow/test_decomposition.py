"""Backward motion-flow decomposition on an analytic scene with exact flows, depths and motion.

The scene is the plane z = 0 seen obliquely by two cameras; a disk of the plane (radius R) slides by ``d`` within
the plane between t and t+1 (so depth stays exact and the only occlusions are where the disk covers or uncovers
the static plane). Optical flows, depth and the expected motion flow all follow from ray-plane intersections.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch

import pidg  # noqa: F401
from pidg.flow.decomposition import (
    depth_change_target,
    smooth_depth,
    FlowTarget,
    backproject,
    decompose_backward_flow,
    dilate_mask,
    motion_flow_target,
    motion_mask_from_flow,
    warp_to_first_frame,
)
from pidg.flow.optical_flow import forward_backward_consistency, pixel_centers
from pidg.render import Camera

F64 = torch.float64
W, H = 64, 48
RADIUS = 0.8
CENTER_T1 = torch.tensor([0.2, 0.1, 0.0], dtype=F64)  # disk centre at t+1


def cam(eye: tuple[float, float, float]) -> Camera:
    return Camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), W, H, math.radians(55.0))


def plane_hits(camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [H, W, 3] where each pixel's ray meets z = 0, and their camera depth [H, W]."""
    c2w = torch.linalg.inv(camera.world_to_camera.to(F64))
    p = pixel_centers(H, W, F64)
    rays_cam = torch.stack([(p[..., 0] - camera.cx) / camera.fx, (p[..., 1] - camera.cy) / camera.fy,
                            torch.ones(H, W, dtype=F64)], dim=-1)
    rays = rays_cam @ c2w[:3, :3].T  # world directions whose camera z is 1
    origin = c2w[:3, 3]
    s = -origin[2] / rays[..., 2]  # = camera depth, since the ray's camera z grows by 1 per unit s
    return origin + s.unsqueeze(-1) * rays, s


def project(camera: Camera, points: torch.Tensor) -> torch.Tensor:
    uv, _ = camera.project_points(points.reshape(-1, 3))
    return uv.reshape(points.shape[:-1] + (2,))


@dataclass
class PlaneScene:
    depth1: torch.Tensor
    forward: torch.Tensor
    backward: torch.Tensor
    expected: torch.Tensor  # motion flow on frame t's grid (0 on static pixels)
    moving0: torch.Tensor  # frame t pixels on the disk
    clean0: torch.Tensor  # frame t pixels well away from the disk's rim


def make_plane_scene(cam0: Camera, cam1: Camera, d: tuple[float, float]) -> PlaneScene:
    shift = torch.tensor([d[0], d[1], 0.0], dtype=F64)
    x4, depth1 = plane_hits(cam1)
    on_disk1 = (x4 - CENTER_T1).norm(dim=-1) < RADIUS
    backward = project(cam0, x4 - shift * on_disk1.unsqueeze(-1)) - pixel_centers(H, W, F64)
    x0, _ = plane_hits(cam0)
    dist0 = (x0 - (CENTER_T1 - shift)).norm(dim=-1)
    on_disk0 = dist0 < RADIUS
    x0_next = x0 + shift * on_disk0.unsqueeze(-1)
    forward = project(cam1, x0_next) - pixel_centers(H, W, F64)
    expected = torch.where(on_disk0.unsqueeze(-1), project(cam0, x0_next) - project(cam0, x0), 0.0)
    margin = 0.2  # world units (~2-3 pixels): bilinear lookups on the disk never mix in the static plane
    # clean: away from the disk's rim at t, and (for static points) from where its rim passes at t+1
    clean = ((dist0 - RADIUS).abs() > margin) & (on_disk0 | ((x0 - CENTER_T1).norm(dim=-1) - RADIUS).abs().gt(margin))
    return PlaneScene(depth1, forward, backward, expected, on_disk0, clean)


CAM0 = cam((0.5, -3.0, 2.2))
CAM1 = cam((1.0, -2.8, 2.3))


def consistency(scene: PlaneScene) -> tuple[torch.Tensor, torch.Tensor]:
    return (forward_backward_consistency(scene.forward, scene.backward),
            forward_backward_consistency(scene.backward, scene.forward))


def test_backproject_inverts_projection():
    x, depth = plane_hits(CAM1)
    torch.testing.assert_close(backproject(depth, CAM1), x, atol=1e-9, rtol=0)
    torch.testing.assert_close(project(CAM1, x), pixel_centers(H, W, F64), atol=1e-9, rtol=0)


def test_camera_motion_only_gives_zero_motion_flow():
    scene = make_plane_scene(CAM0, CAM1, (0.0, 0.0))
    vf, vb = consistency(scene)
    dec = decompose_backward_flow(scene.depth1, CAM0, CAM1, scene.backward, vb)
    assert dec.valid.float().mean() > 0.7
    assert dec.motion_flow[dec.valid].abs().max() < 1e-6
    # the camera flow is all of the backward flow's (negated) displacement
    torch.testing.assert_close(dec.camera_flow[dec.valid], -scene.backward[dec.valid], atol=1e-6, rtol=0)
    assert dec.camera_flow[dec.valid].norm(dim=-1).mean() > 2.0  # the cameras really differ
    target = motion_flow_target(scene.depth1, CAM0, CAM1, scene.forward, scene.backward, vf, vb,
                                motion_mask0=torch.ones(H, W, dtype=torch.bool))
    assert target.valid.float().mean() > 0.6
    assert target.flow.abs().max() < 1e-6
    # without a dataset mask, nothing moves, so nothing is supervised
    derived = motion_flow_target(scene.depth1, CAM0, CAM1, scene.forward, scene.backward, vf, vb)
    assert not derived.valid.any()


@pytest.mark.parametrize("camera1", [CAM0, CAM1], ids=["static-camera", "moving-camera"])
def test_object_motion_is_recovered_on_frame_t_grid(camera1: Camera):
    scene = make_plane_scene(CAM0, camera1, (0.25, -0.15))
    vf, vb = consistency(scene)
    target = motion_flow_target(scene.depth1, CAM0, camera1, scene.forward, scene.backward, vf, vb,
                                motion_threshold=0.5)
    moving, static = scene.moving0 & scene.clean0, ~scene.moving0 & scene.clean0
    assert moving.sum() > 100
    assert target.valid[moving].float().mean() > 0.95
    err = (target.flow - scene.expected).norm(dim=-1)
    assert err[moving & target.valid].max() < 0.02  # bilinear lookup of a smooth field: tiny error
    assert scene.expected[moving].norm(dim=-1).mean() > 3.0  # ...of a motion of several pixels
    assert not target.valid[static].any()  # the derived mask leaves static pixels unsupervised
    # with the true mask (dataset-style), same flow on the disk
    masked = motion_flow_target(scene.depth1, CAM0, camera1, scene.forward, scene.backward, vf, vb,
                                motion_mask0=scene.moving0)
    assert (masked.flow - scene.expected).norm(dim=-1)[moving & masked.valid].max() < 0.02
    assert (masked.flow[~masked.valid] == 0).all()


def test_occluded_pixels_are_not_supervised():
    """Static plane pixels the disk covers at t+1 fail the forward-backward check and get no target."""
    scene = make_plane_scene(CAM0, CAM0, (0.3, 0.0))
    vf, vb = consistency(scene)
    x0, _ = plane_hits(CAM0)
    will_be_covered = ~scene.moving0 & ((x0 - CENTER_T1).norm(dim=-1) < RADIUS - 0.1)
    assert will_be_covered.sum() > 10
    assert not vf[will_be_covered].any()
    target = motion_flow_target(scene.depth1, CAM0, CAM0, scene.forward, scene.backward, vf, vb,
                                motion_mask0=torch.ones(H, W, dtype=torch.bool))
    assert not target.valid[will_be_covered].any()


def test_invalid_depth_and_lookups_outside_are_invalid():
    scene = make_plane_scene(CAM0, CAM1, (0.0, 0.0))
    depth = scene.depth1.clone()
    depth[:10] = 0.0  # unknown depth (rendered alpha ~ 0)
    depth[10:12] = float("nan")
    dec = decompose_backward_flow(depth, CAM0, CAM1, scene.backward)
    assert not dec.valid[:12].any() and torch.isfinite(dec.motion_flow).all()
    # forward flow pointing out of the image: no lookup there
    forward = torch.zeros(H, W, 2, dtype=F64)
    forward[:, :, 0] = 1000.0
    field = FlowTarget(torch.ones(H, W, 2, dtype=F64), torch.ones(H, W, dtype=torch.bool))
    assert not warp_to_first_frame(field, forward).valid.any()


def test_warp_does_not_blend_invalid_neighbours():
    field = FlowTarget(torch.ones(H, W, 2, dtype=F64), torch.ones(H, W, dtype=torch.bool))
    field.valid[:, 20] = False
    forward = torch.zeros(H, W, 2, dtype=F64)
    forward[..., 0] = 0.5  # every lookup falls halfway between two pixel centres
    warped = warp_to_first_frame(field, forward)
    assert not warped.valid[:, 19].any() and not warped.valid[:, 20].any()
    assert warped.valid[:, 18].all() and warped.valid[:, 21].all()


def test_dilate_and_motion_mask():
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[20, 30] = True
    grown = dilate_mask(mask, 2)
    assert grown.sum() == 25 and grown[18:23, 28:33].all()
    assert torch.equal(dilate_mask(mask, 0), mask)
    flow = torch.zeros(H, W, 2)
    flow[5:10, 5:10, 1] = 3.0
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[5, 5] = False
    moving = motion_mask_from_flow(flow, valid, threshold=1.0)
    assert moving.sum() == 24 and not moving[5, 5]


def test_shapes_are_checked():
    scene = make_plane_scene(CAM0, CAM1, (0.0, 0.0))
    with pytest.raises(ValueError, match="backward flow"):
        decompose_backward_flow(scene.depth1, CAM0, CAM1, scene.backward.permute(2, 0, 1))
    with pytest.raises(ValueError, match="forward flow"):
        warp_to_first_frame(FlowTarget(scene.backward, torch.ones(H, W, dtype=torch.bool)), scene.forward[:, :-1])


def _random_target_inputs(h: int, w: int, seed: int, with_mask: bool):
    """Realistic cameras, a depth map with invalid patches, noisy flows (some pointing outside the image), holes in
    both consistency masks and, optionally, a motion mask: every branch of the target's validity."""
    gen = torch.Generator().manual_seed(seed)
    cam0 = Camera.look_at((0.5, -3.0, 2.2), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), w, h, math.radians(55.0))
    cam1 = Camera.look_at((0.8, -2.9, 2.3), (0.1, 0.0, 0.0), (0.0, 0.0, 1.0), w, h, math.radians(55.0))
    depth = 3.0 + torch.rand(h, w, generator=gen)
    depth[: h // 4, : w // 3] = 0.0  # unknown (rendered alpha too low)
    depth[h // 2, :] = float("nan")
    depth[-2:, -5:] = float("inf")
    forward = torch.randn(h, w, 2, generator=gen) * 2.0
    forward[:, -3:, 0] += 6.0  # these leave the image
    backward = torch.randn(h, w, 2, generator=gen) * 2.0
    valid_f = torch.rand(h, w, generator=gen) > 0.1
    valid_b = torch.rand(h, w, generator=gen) > 0.1
    mask = (torch.rand(h, w, generator=gen) > 0.8) if with_mask else None
    return depth, cam0, cam1, forward, backward, valid_f, valid_b, mask


@pytest.mark.parametrize("size", [(23, 37), (48, 64), (96, 96)])
@pytest.mark.parametrize("with_mask", [True, False])
@pytest.mark.parametrize("dilation", [0, 3])
def test_the_numba_target_equals_the_torch_reference(size, with_mask, dilation):
    h, w = size
    depth, cam0, cam1, fwd, bwd, vf, vb, mask = _random_target_inputs(h, w, seed=h + w + dilation, with_mask=with_mask)
    args = (depth, cam0, cam1, fwd, bwd, vf, vb, mask, dilation, 1.0)
    reference = motion_flow_target(*args, kernel=False)
    fast = motion_flow_target(*args, kernel=True)
    # the validity may differ where a lookup lands within float rounding of a pixel centre; never elsewhere
    differ = fast.valid != reference.valid
    assert differ.sum() <= max(1, h * w // 2000)
    same = fast.valid & reference.valid
    assert same.sum() > 0.05 * h * w
    torch.testing.assert_close(fast.flow[same], reference.flow[same], atol=1e-4, rtol=1e-5)
    assert (fast.flow[~fast.valid] == 0).all()


def test_the_numba_target_on_the_plane_scene_recovers_the_motion():
    scene = make_plane_scene(CAM0, CAM1, (0.3, -0.2))
    vf, vb = consistency(scene)
    args = (scene.depth1.float(), CAM0, CAM1, scene.forward.float(), scene.backward.float(), vf, vb)
    fast = motion_flow_target(*args, motion_mask0=scene.moving0, dilation=2)
    assert fast.flow.dtype == torch.float32
    reference = motion_flow_target(*args, motion_mask0=scene.moving0, dilation=2, kernel=False)
    assert torch.equal(fast.valid, reference.valid)
    check = fast.valid & scene.clean0
    assert check.sum() > 50
    torch.testing.assert_close(fast.flow[check].double(), scene.expected[check], atol=2e-3, rtol=0)


# ---- the depth change (--flow.lambda_depth_change) ----------------------------------------------------------------
def plane_hits_at(camera: Camera, height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`plane_hits` for the plane z = ``height``."""
    lifted = Camera(camera.world_to_camera.to(F64) @ torch.tensor(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, height], [0, 0, 0, 1]], dtype=F64), camera.fx, camera.fy, camera.cx,
        camera.cy, camera.width, camera.height, camera.near, camera.far)
    points, depth = plane_hits(lifted)
    return points + torch.tensor([0.0, 0.0, height], dtype=F64), depth


@pytest.mark.parametrize("camera1", [CAM0, CAM1], ids=["static-camera", "moving-camera"])
def test_depth_change_of_a_plane_moving_in_3d_is_its_motion_along_camera_t_axis(camera1: Camera):
    m = torch.tensor([0.1, -0.05, 0.3], dtype=F64)  # the whole plane z = 0 moves by m: to z = 0.3
    x0, depth0 = plane_hits(CAM0)
    _, depth1 = plane_hits_at(camera1, 0.3)
    forward = project(camera1, x0 + m) - pixel_centers(H, W, F64)
    valid = torch.ones(H, W, dtype=torch.bool)
    change, scale = depth_change_target(depth0, depth1, CAM0, camera1, forward, valid)
    axis = CAM0.world_to_camera.to(F64)[2, :3]  # camera t's viewing axis in world coordinates
    expected_dz = float(axis @ m)  # closed form: every point's camera-t depth changes by m . axis
    known = scale > 0
    assert known.float().mean() > 0.4  # the sky, steep depth near the horizon and lookups outside frame t+1 are not
    torch.testing.assert_close(scale[known], CAM0.fx / depth0[known], rtol=1e-9, atol=0)
    # exact up to the bilinear lookup of the depth field, which is second order: < 0.5 % of the change here
    torch.testing.assert_close(change[known] / scale[known], torch.full_like(change[known], expected_dz), atol=1e-3, rtol=0)
    assert abs(expected_dz) > 0.1  # the plane really moves along the axis
    assert (change[~known] == 0).all() and (scale[~known] == 0).all()
    # only supervised pixels get a depth change
    none, _ = depth_change_target(depth0, depth1, CAM0, camera1, forward, torch.zeros_like(valid))
    assert (none == 0).all()


def test_depth_change_is_unknown_across_depth_edges_and_where_depth_is_missing():
    depth = torch.full((H, W), 4.0, dtype=F64)
    depth[:, W // 2:] = 6.0  # an occluding edge between columns W/2 - 1 and W/2
    depth[:5, :5] = 0.0  # unknown (dataset depth maps mark it 0)
    smooth = smooth_depth(depth, near=0.01)
    assert not smooth[:, W // 2 - 1 : W // 2 + 1].any() and smooth[10:, W // 2 - 3].all() and smooth[10:, W // 2 + 2].all()
    assert not smooth[:5, :5].any() and smooth[10:, 10].all()
    assert smooth_depth(depth, near=0.01, tolerance=0.6)[10:, W // 2 - 1 : W // 2 + 1].all()  # 4 vs 6: a 50 % range
    still = torch.zeros(H, W, 2, dtype=F64)
    change, scale = depth_change_target(depth, depth, CAM0, CAM0, still, torch.ones(H, W, dtype=torch.bool))
    assert (scale[:, W // 2 - 1 : W // 2 + 1] == 0).all() and (scale[:5, :5] == 0).all()
    assert change[scale > 0].abs().max() < 1e-9  # nothing moved
