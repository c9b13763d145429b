"""Rigid-body tracks from flow and depth: the motions' maths against closed forms, and two bodies tracked through an
exact synthetic flow (one of them through a gap) to their true positions."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math

import pytest
import torch

import pidg.flow.rigid_tracks as rigid_tracks
from pidg.data.scene import Frame
from pidg.flow.preprocess import FlowCache
from pidg.flow.rigid_tracks import (
    RigidTrackConfig,
    _constant_velocity,
    _rotation_power,
    connected_labels,
    axis_angle_rotation,
    blurred,
    chain_look,
    cross_matrix,
    lifted_pairs,
    look_agreement,
    masked_blur,
    moving_surface,
    pair_images,
    photometric_refine,
    photometric_rows,
    point_plane_fit,
    ransac_rigid,
    refine_motion,
    rigid_fit,
    rotation_angle,
    seen_through,
    track_rigid_bodies,
)
from pidg.render import Camera


def rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def random_rotation(generator: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.linalg.det(q) > 0 else -q


def test_rigid_fit_recovers_a_rotation_and_translation():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    rotation, shift = random_rotation(gen), torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    r, t = rigid_fit(a, a @ rotation.T + shift)
    torch.testing.assert_close(r, rotation, atol=1e-10, rtol=0)
    torch.testing.assert_close(t, shift, atol=1e-10, rtol=0)
    assert torch.linalg.det(rigid_fit(a, a * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))[0]) > 0  # no reflection


def test_rigid_fit_batched_fits_each_set_on_its_own():
    """Leading dimensions are independent fits (RANSAC fits all its draws at once): each equals its own fit, and the
    exact motions come back, a reflection in one set not reaching the others."""
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)  # four minimal three-point sets
    rotations = torch.stack([random_rotation(gen) for _ in range(4)])
    shifts = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    b = a @ rotations.transpose(-1, -2) + shifts[:, None]
    b[2] = a[2] * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # a mirror: the best proper rotation instead
    r, t = rigid_fit(a, b)
    assert r.shape == (4, 3, 3) and t.shape == (4, 3)
    for k in range(4):
        rk, tk = rigid_fit(a[k], b[k])
        torch.testing.assert_close(r[k], rk, atol=1e-12, rtol=0)
        torch.testing.assert_close(t[k], tk, atol=1e-12, rtol=0)
        assert torch.linalg.det(r[k]) > 0
    for k in (0, 1, 3):
        torch.testing.assert_close(r[k], rotations[k], atol=1e-10, rtol=0)
        torch.testing.assert_close(t[k], shifts[k], atol=1e-10, rtol=0)


def test_cross_matrix_and_axis_angle_rotation_against_closed_forms():
    gen = torch.Generator().manual_seed(4)
    v, u = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(cross_matrix(v) @ u[..., None], torch.linalg.cross(v, u)[..., None], atol=1e-12, rtol=0)
    torch.testing.assert_close(axis_angle_rotation(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 0.3),
                               rotation_z(0.3), atol=1e-12, rtol=0)
    rotation = random_rotation(gen)
    assert abs(rotation_angle(_rotation_power(rotation, 0.25)) - 0.25 * rotation_angle(rotation)) < 1e-10


def test_point_plane_fit_recovers_a_motion_from_pairs_as_kabsch_does():
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(40, 3, generator=gen, dtype=torch.float64)
    rotation, shift = random_rotation(gen), torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    eye, none = torch.eye(3, dtype=torch.float64), a[:0]
    r, t = point_plane_fit(eye, torch.zeros(3, dtype=torch.float64), a, a @ rotation.T + shift, none, none, none,
                           iterations=12)
    kabsch = rigid_fit(a, a @ rotation.T + shift)
    torch.testing.assert_close(r, kabsch[0], atol=1e-9, rtol=0)
    torch.testing.assert_close(t, kabsch[1], atol=1e-9, rtol=0)


def test_point_plane_fit_takes_a_faces_slide_and_turn_from_the_pairs():
    """A face (the plane z = 5) slides and turns in its plane and moves 0.2 toward the camera. Its surface, point to
    plane, tells only the move along its normal; ten exact flow pairs tell the rest. From rest the fit finds the
    motion exactly. Kabsch to the same surface pairs moved onto the plane (the rule before) stays short of the slide
    and the turn: each such target keeps the start's motion along the plane, so the surface holds the body back."""
    gen = torch.Generator().manual_seed(6)
    x = torch.cat([torch.rand(200, 2, generator=gen, dtype=torch.float64) * 2 - 1,
                   torch.full((200, 1), 5.0, dtype=torch.float64)], 1)
    turn, shift = rotation_z(0.1), torch.tensor([0.15, -0.05, -0.2], dtype=torch.float64)  # about the z axis
    a = x[:10]
    eye, zero = torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    target = x.clone()
    target[:, 2] = 4.8  # the next frame's plane where the start (rest) puts each point: moved along the normal only
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(200, 3)
    r, t = point_plane_fit(eye, zero, a, a @ turn.T + shift, x, target, normal)
    torch.testing.assert_close(r, turn, atol=1e-9, rtol=0)
    torch.testing.assert_close(t, shift, atol=1e-9, rtol=0)
    kabsch = rigid_fit(torch.cat([a, x]), torch.cat([a @ turn.T + shift, target]))
    assert rotation_angle(kabsch[0]) < 0.02 and float((kabsch[1] - shift)[:2].norm()) > 0.1
    outline = point_plane_fit(eye, zero, a[:0], a[:0], x, x @ turn.T + shift, torch.zeros_like(x))  # point to point
    torch.testing.assert_close(outline[0], turn, atol=1e-9, rtol=0)


def test_ransac_finds_the_motion_most_pairs_agree_with():
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    rotation, shift = random_rotation(gen), torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64)
    b = a @ rotation.T + shift
    wrong = torch.arange(200) % 10 < 3  # 30 % of the pairs matched to somewhere else
    b[wrong] += torch.randn(int(wrong.sum()), 3, generator=gen, dtype=torch.float64)
    r, t, inliers = ransac_rigid(a, b, inlier=0.01, iterations=100, generator=gen)
    torch.testing.assert_close(r, rotation, atol=1e-9, rtol=0)
    torch.testing.assert_close(t, shift, atol=1e-9, rtol=0)
    assert torch.equal(inliers, ~wrong)
    assert ransac_rigid(a[:2], b[:2], 0.01, 10, gen) is None


def test_connected_labels_join_chains_and_part_clusters():
    chain = torch.stack([torch.arange(20, dtype=torch.float64) * 0.04, torch.zeros(20), torch.zeros(20)], dim=1)  # ends 0.76 apart
    apart = chain + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    labels = connected_labels(torch.cat([chain, apart]), link=0.05, chunk=7)  # blocks of 7 rows: across block edges
    assert len(torch.unique(labels[:20])) == 1 and len(torch.unique(labels[20:])) == 1 and labels[0] != labels[20]
    assert len(torch.unique(connected_labels(chain, link=0.03))) == 20  # no two points close enough


def test_a_motion_s_power_and_its_constant_velocity_extrapolation():
    gen = torch.Generator().manual_seed(2)
    rotation = random_rotation(gen)
    half = _rotation_power(rotation, 0.5)
    torch.testing.assert_close(half @ half, rotation, atol=1e-10, rtol=0)
    torch.testing.assert_close(_rotation_power(rotation, 1.0), rotation, atol=1e-10, rtol=0)
    x = torch.randn(30, 3, generator=gen, dtype=torch.float64)
    centre = x.mean(0)
    spin, drift = rotation_z(0.2), torch.tensor([0.1, 0.0, -0.2], dtype=torch.float64)
    shift = centre - centre @ spin.T + drift  # over one interval: a turn about the centroid, and the centroid moves
    for s in (2.0, 0.5):  # s intervals at the same velocities: s times the turn about the moving centroid, s times the drift
        expected = (x - centre) @ rotation_z(0.2 * s).T + centre + s * drift
        turn, moved = _constant_velocity(x, spin, shift, s)
        torch.testing.assert_close(x @ turn.T + moved, expected, atol=1e-10, rtol=0)


# ---- two bodies in an exact synthetic flow ----------------------------------------------------------------------
SIZE, DEPTH, FOCAL = 64, 5.0, 64.0
CAMERA = Camera(torch.eye(4), FOCAL, FOCAL, SIZE / 2, SIZE / 2, SIZE, SIZE)
HALF = 0.6  # each body is a square of side 1.2 world units facing the camera at depth 5
CENTRES = torch.tensor([[-1.0, 0.0, DEPTH], [1.1, 0.2, DEPTH]], dtype=torch.float64)
STEP = [(rotation_z(0.08), torch.tensor([0.03, 0.02, 0.0], dtype=torch.float64)),  # body 0 turns about its centre and drifts
        (torch.eye(3, dtype=torch.float64), torch.tensor([-0.025, 0.015, 0.0], dtype=torch.float64))]  # body 1 slides


def texture(points: torch.Tensor, phase: float) -> torch.Tensor:
    """Colours [N, 3] in [0, 1] of a smooth pattern at plane coordinates ``points`` [N, 2] (world units): waves 0.5-1
    world units long (6-13 px on the bodies), so that a body's look shows its turn and slide."""
    waves = torch.tensor([[2.0, 9.0], [12.0, -4.0], [-7.0, 10.0]], dtype=torch.float64)  # radians per world unit
    return 0.5 + 0.2 * torch.sin(points @ waves.T + phase) + 0.15 * torch.cos(0.7 * points @ waves.flip(1).T + 2 * phase)


def pose(body: int, k: int, stop: dict[int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Body ``body``'s motion from frame 0 to frame k: x_k = R x_0 + t (k steps about its moving centre; none after
    frame ``stop[body]``)."""
    k = min(k, (stop or {}).get(body, k))
    rotation, drift = STEP[body]
    r = torch.linalg.matrix_power(rotation, k)
    c = CENTRES[body]
    return r, c + k * drift - c @ r.T


def frames_and_cache(
    n: int, gap: dict[int, list[int]], stop: dict[int, int] | None = None, hidden: dict[int, list[int]] | None = None,
    wrong: dict[int, list[int]] | None = None, short: float = 0.0,
) -> tuple[list[Frame], FlowCache]:
    """``n`` frames of the two bodies over a still background at depth 9; each pair's forward flow exact, and invalid
    on body b's pixels for the intervals in ``gap[b]``, 4 px off (consistently: the flow's failure that its checks
    miss) for those in ``wrong[b]``; body b still from frame ``stop[b]`` on (off the motion mask), and not seen at all
    in the frames ``hidden[b]`` (gone from the view); with ``short``, every body's flow falls that share short of its
    motion (as DIS's does on small, fast-turning bodies)."""
    stop, hidden, wrong = stop or {}, hidden or {}, wrong or {}
    ys, xs = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64) + 0.5, torch.arange(SIZE, dtype=torch.float64) + 0.5,
                            indexing="ij")
    pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2)
    frames, owners = [], []
    for k in range(n):
        depth, owner = torch.full((SIZE * SIZE,), 9.0, dtype=torch.float64), torch.full((SIZE * SIZE,), -1)
        colours = texture((pixels - SIZE / 2) / FOCAL * 9.0, 0.0)  # the still background at depth 9
        for body in range(2):
            if k in hidden.get(body, []):
                continue
            r, t = pose(body, k, stop)
            world = torch.cat([(pixels - SIZE / 2) / FOCAL * DEPTH, torch.full((SIZE * SIZE, 1), DEPTH, dtype=torch.float64)], 1)
            at_start = (world - t) @ r  # where the point seen here was at frame 0 (inverse motion)
            inside = ((at_start[:, :2] - CENTRES[body, :2]).abs() < HALF).all(dim=1)
            depth[inside], owner[inside] = DEPTH, body
            colours[inside] = texture(at_start[inside, :2], 1.0 + body)  # the body's texture moves with it
        moving = (owner >= 0) & ~torch.tensor([k >= stop.get(b, n) for b in range(2)] + [False])[owner]
        image = (colours * 255).round().to(torch.uint8).reshape(SIZE, SIZE, 3)
        frames.append(Frame(CAMERA, k / (n - 1), image, moving.reshape(SIZE, SIZE), f"train/{k:03d}",
                            depth=depth.reshape(SIZE, SIZE).float()))
        owners.append(owner)
    forward, valid = torch.zeros(n - 1, SIZE, SIZE, 2), torch.zeros(n - 1, SIZE, SIZE, dtype=torch.bool)
    for k in range(n - 1):
        flow = torch.zeros(SIZE * SIZE, 2, dtype=torch.float64)
        ok = torch.ones(SIZE * SIZE, dtype=torch.bool)  # the still background: zero flow, valid
        world = torch.cat([(pixels - SIZE / 2) / FOCAL * DEPTH, torch.full((SIZE * SIZE, 1), DEPTH, dtype=torch.float64)], 1)
        for body in range(2):
            mine = owners[k] == body
            r0, t0 = pose(body, k, stop)
            r1, t1 = pose(body, k + 1, stop)
            moved = ((world[mine] - t0) @ r0) @ r1.T + t1  # frame k -> frame 0 -> frame k + 1
            flow[mine] = (1.0 - short) * (CAMERA.project_points(moved)[0] - pixels[mine])
            if k in gap.get(body, []):
                ok[mine] = False
            if k in wrong.get(body, []):
                flow[mine] += torch.tensor([4.0, -2.0], dtype=torch.float64)
        forward[k], valid[k] = flow.reshape(SIZE, SIZE, 2).float(), ok.reshape(SIZE, SIZE)
    return frames, FlowCache(None, frames, forward.half(), forward.half(), valid, valid)


def truth(start: torch.Tensor, k: int, stop: dict[int, int] | None = None) -> torch.Tensor:
    """Where the tracked points ``start`` (frame 0) are at frame k: each carried by its own body's motion."""
    body = (start[:, 0] > 0).long()  # body 0 left of the axis, body 1 right
    out = start.clone()
    for b in range(2):
        r, t = pose(b, k, stop)
        out[body == b] = start[body == b] @ r.T + t
    return out


def test_two_bodies_are_tracked_to_their_true_positions_through_a_gap_and_a_wrong_flow():
    frames, cache = frames_and_cache(8, gap={1: [3, 4]}, wrong={0: [5]})
    a, b = lifted_pairs(cache.pair(0))
    assert len(a) > 400 and bool((a[:, 2] - DEPTH).abs().max() < 1e-5)  # the still background is not a moving pixel
    tracks = track_rigid_bodies(cache, RigidTrackConfig(points=400, static_points=50, iterations=50, photometric=False),
                                torch.Generator().manual_seed(0))
    assert int(tracks.body.max()) == 1 and tracks.positions.shape[:2] == (8, 400 + 7 * 100) and tracks.known.all()
    # 400 points of the first frame, 100 of each later one's surface carried back to the first frame: all on the
    # bodies they were seen on
    assert torch.equal(tracks.body, (tracks.positions[0, :, 0] > 0).long()) or torch.equal(tracks.body, (tracks.positions[0, :, 0] < 0).long())
    # body 1 had no flow over two intervals (more than max_gap): the surface the next frames show carried it on
    assert bool(tracks.found[3:5, tracks.body[tracks.positions[0, :, 0] > 0][0]].all())
    left = tracks.positions[0, :, 0] < 0
    for k in range(8):  # a pixel spans 0.078 world units here
        error = (tracks.positions[k] - truth(tracks.positions[0], k)).norm(dim=1)
        assert float(error[left].max()) < 0.02  # body 0, its flow wrong over interval 5, not taken: within a quarter px
        # body 1 through two intervals without flow, its face's outline paired point to point: within 1.1 px. Only
        # the outline pins a face's slide in its own plane, and each outline sample pulls a point to a pixel centre:
        # this face, parallel to the image, is the worst case (1.0 px here; 0.6 px with the Kabsch rule before the
        # point-to-plane fit, which the generated scenes' tracks favour: docs/motion.md, "Tracks fitted point to
        # plane")
        assert float(error[~left].max()) < 0.085
    assert tracks.static.shape == (50, 3) and bool(((tracks.static[:, 2] - 9.0).abs() < 1e-4).all())


def test_a_wrong_flow_motion_leaves_points_where_the_next_frame_sees_through_them():
    frames, cache = frames_and_cache(3, gap={}, wrong={0: [1]})
    a, b = lifted_pairs(cache.pair(1))
    left = a[:, 0] < 0  # body 0's pairs
    (r1, t1), (r2, t2) = pose(0, 1), pose(0, 2)
    rotation, shift, _ = ransac_rigid(a[left], b[left], 0.05, 50, torch.Generator().manual_seed(0))  # the flow's motion
    x = moving_surface(frames[1])[0]
    x = x[x[:, 0] < 0]  # all of body 0 in frame 1 (the pairs hold only the points the wrong flow lands on it)
    assert seen_through(((x - t1) @ r1) @ r2.T + t2, frames[2], 0.05) == 0.0  # the true motion: on its surface
    assert seen_through(x @ rotation.T + shift, frames[2], 0.05) > 0.1  # the flow's, 4 px off: onto the background
    assert seen_through(torch.tensor([[0.0, 0.0, 20.0]], dtype=torch.float64), frames[2], 0.05) == 0.0  # behind: hidden
    assert seen_through(torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64), frames[2], 0.05) == 0.0  # not in view


def turning_sphere() -> tuple[Frame, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A sphere (radius 1, at depth 5; a pixel spans 0.08 there) seen by one camera, turning 0.15 rad about its centre
    as it moves: (the next frame, the points of its side the camera sees, its turn, its shift, its centre before and
    after)."""
    radius, centre = 1.0, torch.tensor([0.1, -0.05, DEPTH], dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64) + 0.5, torch.arange(SIZE, dtype=torch.float64) + 0.5,
                            indexing="ij")
    rays = torch.stack([(xs - SIZE / 2) / FOCAL, (ys - SIZE / 2) / FOCAL, torch.ones_like(xs)], dim=-1)  # z = 1
    moved_centre = centre + torch.tensor([0.05, 0.02, -0.1], dtype=torch.float64)
    along = (rays * moved_centre).sum(-1)
    disc = along ** 2 - (rays * rays).sum(-1) * ((moved_centre ** 2).sum() - radius ** 2)
    hit = disc > 0
    z = torch.where(hit, (along - disc.clamp_min(0).sqrt()) / (rays * rays).sum(-1), torch.zeros_like(along))
    frame = Frame(CAMERA, 1.0, torch.zeros(SIZE, SIZE, 3, dtype=torch.uint8), hit, "train/001", depth=z.float())
    gen = torch.Generator().manual_seed(3)
    direction = torch.randn(800, 3, generator=gen, dtype=torch.float64)
    x = centre + radius * direction / direction.norm(dim=1, keepdim=True)
    x = x[x[:, 2] < centre[2] - 0.3]  # the side the camera sees
    turn = rotation_z(0.15)
    return frame, x, turn, moved_centre - centre @ turn.T, centre, moved_centre


def test_refine_motion_fits_a_sphere_s_position_to_the_surface_and_its_turn_to_the_flow():
    """Flow pairs 0.06 too near the camera (a depth error) place the sphere 0.06 off; fitted to its surface as well,
    the motion is nearer the truth and keeps the flow's turn, which the surface cannot tell. The surface alone, from
    0.15 off, finds where it is."""
    frame, x, turn, shift, centre, moved_centre = turning_sphere()
    truth_x = x @ turn.T + shift
    a = x[::3]
    b = a @ turn.T + shift + torch.tensor([0.0, 0.0, -0.06], dtype=torch.float64)
    flow_r, flow_t = rigid_fit(a, b)  # the flow's motion alone
    flow_error = float((x @ flow_r.T + flow_t - truth_x).norm(dim=1).mean())
    assert flow_error > 0.059
    rotation, moved, n_flow, n_surface = refine_motion(x, flow_r, flow_t, a, b, moving_surface(frame), frame, reach=0.1,
                                                       inlier=0.05)
    assert n_flow == len(a) and n_surface > 0.8 * len(x)
    assert float((x @ rotation.T + moved - truth_x).norm(dim=1).mean()) < 0.5 * flow_error  # the pairs pull both ways
    assert rotation_angle(rotation @ turn.T) < 0.01  # radians: the turn kept
    alone = refine_motion(x, torch.eye(3, dtype=torch.float64), shift - centre @ (torch.eye(3, dtype=torch.float64) - turn.T)
                          + torch.tensor([0.1, 0.05, 0.1], dtype=torch.float64), a[:0], b[:0], moving_surface(frame), frame,
                          reach=0.1, inlier=0.05, rounds=12)
    assert float((centre @ alone[0].T + alone[1] - moved_centre).norm()) < 0.01


def test_a_body_gone_from_view_longer_than_the_allowed_gap_ends_its_tracks():
    frames, cache = frames_and_cache(7, gap={0: [2, 3]}, hidden={0: [3, 4, 5, 6]})
    tracks = track_rigid_bodies(cache, RigidTrackConfig(points=300, static_points=10, iterations=50, max_gap=1),
                                torch.Generator().manual_seed(0))
    left = tracks.positions[0, :, 0] < 0
    assert tracks.known[:4, left].all() and not tracks.known[4:, left].any()  # carried over interval 2, ended at 3
    assert tracks.known[:, ~left].all()


def test_a_body_that_comes_to_rest_stays_tracked_where_it_stopped():
    frames, cache = frames_and_cache(8, gap={}, stop={1: 4})  # body 1 still (and off the motion mask) from frame 4
    tracks = track_rigid_bodies(cache, RigidTrackConfig(points=300, static_points=10, iterations=50, max_gap=1,
                                                        photometric=False), torch.Generator().manual_seed(0))
    right = tracks.positions[0, :, 0] > 0
    assert tracks.known.all()  # not lost: at rest
    assert not tracks.found[4:, tracks.body[right][0]].any()  # no flow pairs on it from frame 4
    for k in range(8):  # to a quarter of a pixel, as above
        assert float((tracks.positions[k] - truth(tracks.positions[0], k, {1: 4})).norm(dim=1).max()) < 0.02


def test_frames_without_depth_are_named():
    frames, cache = frames_and_cache(3, gap={})
    frames[1].depth = None
    with pytest.raises(ValueError, match="train/001 has no depth"):
        track_rigid_bodies(cache, RigidTrackConfig(), torch.Generator())


# ---- the look: photometric refinement --------------------------------------------------------------------------
def test_blurred_keeps_a_constant_and_spreads_a_point_by_sigma():
    flat = torch.full((20, 30, 3), 0.4, dtype=torch.float64)
    torch.testing.assert_close(blurred(flat, 2.0), flat, atol=1e-12, rtol=0)
    point = torch.zeros(41, 41, 1, dtype=torch.float64)
    point[20, 20] = 1.0
    spread = blurred(point, 2.0)[..., 0]
    offsets = (torch.arange(41, dtype=torch.float64) - 20.0) ** 2
    assert abs(float(spread.sum()) - 1.0) < 1e-12
    assert abs(float((spread.sum(0) * offsets).sum()) - 4.0) < 0.05  # variance sigma^2 along each axis
    assert torch.equal(blurred(point, 0.0), point)


def test_masked_blur_keeps_a_body_s_colours_from_the_background():
    image = torch.zeros(16, 16, 3, dtype=torch.float64)
    image[:, :8] = torch.tensor([0.9, 0.1, 0.2], dtype=torch.float64)  # the body
    image[:, 8:] = torch.tensor([0.1, 0.8, 0.7], dtype=torch.float64)  # the background
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[:, :8] = True
    inside = masked_blur(image, mask, 3.0)
    torch.testing.assert_close(inside[:, :8], image[:, :8], atol=1e-12, rtol=0)  # no background mixed in at its edge
    assert float(inside[:, 8:].abs().max()) == 0.0
    assert float((blurred(image, 3.0)[:, 7] - image[:, 7]).abs().max()) > 0.1  # the plain blur mixes it in


def look_case() -> tuple[Frame, Frame, torch.Tensor, torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """Body 0 of the synthetic frames over one interval: (frame 0, frame 1, its surface points at frame 0, its true
    turn and shift, frame 1's moving surface)."""
    frames, _ = frames_and_cache(2, gap={})
    points = moving_surface(frames[0])[0]
    rotation, shift = pose(0, 1)
    return frames[0], frames[1], points[points[:, 0] < 0], rotation, shift, moving_surface(frames[1])


def test_photometric_rows_jacobian_against_finite_differences():
    frame0, frame1, x, rotation, shift, _ = look_case()
    y, image = x @ rotation.T + shift, frame1.image.double()
    colours, centre = torch.rand(len(x), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), y.mean(0)
    residual, jacobian = photometric_rows(y, colours, image, frame1, centre)
    eps, columns = 1e-6, []
    for d in range(6):
        moved = []
        for sign in (1.0, -1.0):
            update = torch.zeros(6, dtype=torch.float64)
            update[d] = sign * eps
            angle = float(update[:3].norm())
            turn = axis_angle_rotation(update[:3] / angle, angle) if angle > 0 else torch.eye(3, dtype=torch.float64)
            moved.append(photometric_rows((y - centre) @ turn.T + centre + update[3:], colours, image, frame1, centre)[0])
        columns.append((moved[0] - moved[1]) / (2 * eps))
    numeric = torch.stack(columns, 1)
    assert float(numeric.norm()) > 1.0  # the texture gives the look a gradient in every direction
    assert float((jacobian - numeric).norm() / numeric.norm()) < 1e-6


@pytest.mark.parametrize("high_pass", [0.0, 3.0])
def test_photometric_refine_finds_a_textured_face_s_turn_and_slide(high_pass: float):
    """From 1.1 px off (a turn of 0.03 rad and a slide), the body's look in the next frame takes its motion to within
    a tenth of a pixel on average (a pixel spans 0.078 world units here); started at the truth it stays there."""
    frame0, frame1, x, rotation, shift, surface = look_case()
    truth_y = x @ rotation.T + shift
    off = (rotation_z(0.03) @ rotation, shift + torch.tensor([0.05, -0.04, 0.0], dtype=torch.float64))
    assert float((x @ off[0].T + off[1] - truth_y).norm(dim=1).mean()) > 0.08
    for start in (off, (rotation, shift)):
        refined = photometric_refine(x, *start, frame0, frame1, pair_images(frame0, frame1, high_pass), surface, 0.3,
                                     DEPTH / FOCAL)
        error = (x @ refined[0].T + refined[1] - truth_y).norm(dim=1)
        assert float(error.mean()) < 0.006 and float(error.max()) < 0.015


def test_look_agreement_prefers_the_true_motion_and_ignores_brightness_and_contrast():
    frame0, frame1, x, rotation, shift, _ = look_case()
    images = pair_images(frame0, frame1, 3.0)
    right = look_agreement(x, rotation, shift, frame0, frame1, images, 0.3)
    wrong = look_agreement(x, rotation_z(0.05) @ rotation, shift + torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64),
                           frame0, frame1, images, 0.3)
    assert right > 0.9 and wrong < right - 0.2
    dimmer = Frame(frame1.camera, frame1.time, (frame1.image * 0.7 + 0.2).mul(255).round().to(torch.uint8), frame1.mask,
                   frame1.name, depth=frame1.depth)
    assert abs(look_agreement(x, rotation, shift, frame0, dimmer, pair_images(frame0, dimmer, 3.0), 0.3) - right) < 0.01
    away = torch.tensor([0.0, 0.0, 50.0], dtype=torch.float64)  # carried out of view: nothing seen to compare
    assert math.isnan(look_agreement(x, rotation, shift + away, frame0, frame1, images, 0.3))


def test_a_flow_that_falls_short_is_made_up_by_the_look():
    """Every body's flow 12 % short of its motion (as DIS's on the generated rigid bodies): without the look the
    turning body's tracks fall behind by more than a pixel after seven intervals; with it they stay within a third of
    a pixel."""
    frames, cache = frames_and_cache(8, gap={}, short=0.12)
    errors = {}
    for photometric in (False, True):
        tracks = track_rigid_bodies(cache, RigidTrackConfig(points=300, static_points=10, iterations=50,
                                                            photometric=photometric), torch.Generator().manual_seed(0))
        left = tracks.positions[0, :, 0] < 0  # body 0, turning
        errors[photometric] = [float((tracks.positions[k] - truth(tracks.positions[0], k)).norm(dim=1)[left].max())
                               for k in range(8)]
    assert errors[False][-1] > 0.078
    assert max(errors[True]) < 0.026


def test_chain_look_sees_a_chain_that_slipped_onto_another_part_of_its_texture():
    """A body carried right looks alike from each frame to the next (near 1 on the exact synthetic images); one whose
    chain slips 4 px at frame 4 (onto another part of its texture, as a chain gone wrong does) looks anti-correlated
    with itself over that interval and less alike on average; one lost after frame 4 is scored on the intervals it was
    tracked through; the other body's scores do not move."""
    frames, cache = frames_and_cache(8, gap={})
    start, _ = lifted_pairs(cache.pair(0))
    body = (start[:, 0] > 0).long()
    right = torch.stack([truth(start, k) for k in range(8)])
    known = torch.ones(8, len(start), dtype=torch.bool)
    mean, lowest = chain_look(right, known, body, frames, 0.3)
    assert bool((lowest > 0.95).all()) and bool((mean <= 1.0).all())
    slipped = right.clone()
    left = body == 0
    slipped[4:, left] += torch.tensor([0.3, -0.15, 0.0], dtype=torch.float64)  # 4 px (a pixel spans 0.078 here)
    slipped_mean, slipped_lowest = chain_look(slipped, known, body, frames, 0.3)
    assert float(slipped_lowest[0]) < 0 and float(slipped_mean[0]) < float(mean[0]) - 0.1
    assert (float(slipped_mean[1]), float(slipped_lowest[1])) == (float(mean[1]), float(lowest[1]))
    lost = known.clone()
    lost[5:, left] = False
    lost_mean, lost_lowest = chain_look(right, lost, body, frames, 0.3)
    assert float(lost_mean[0]) == pytest.approx(float(mean[0]), abs=0.01) and float(lost_lowest[0]) > 0.95
    never = known.clone()
    never[1:, left] = False  # not tracked past the first frame: nothing to score
    assert bool(chain_look(right, never, body, frames, 0.3)[0][0].isnan())


def test_a_body_whose_chain_went_wrong_is_chained_again(monkeypatch):
    """``attempts``: where a body's chain went wrong (here the first chain slips body 0 by 4 px at frame 3), the
    tracker chains again with new RANSAC draws and keeps the chain that looks most alike: with two attempts body 0's
    tracks are right, with one the wrong ones stay; a chain that did not go wrong is made once."""
    frames, cache = frames_and_cache(6, gap={})
    real, calls = rigid_tracks._chain, []

    def first_goes_wrong(intervals, first_surface, start, body, *args):
        chain = real(intervals, first_surface, start, body, *args)
        calls.append(len(calls))
        if len(calls) == 1 and slip:
            chain.positions[3:, start[:, 0] < 0] += torch.tensor([0.3, -0.15, 0.0], dtype=torch.float64)
        return chain

    monkeypatch.setattr(rigid_tracks, "_chain", first_goes_wrong)
    errors = {}
    for slip, attempts, chains in ((True, 1, 1), (True, 2, 2), (False, 3, 1)):
        calls.clear()
        config = RigidTrackConfig(points=300, static_points=10, iterations=50, photometric=False, later_points=0,
                                  attempts=attempts)
        tracks = track_rigid_bodies(cache, config, torch.Generator().manual_seed(0))
        assert len(calls) == chains
        left = tracks.positions[0, :, 0] < 0
        errors[slip, attempts] = float((tracks.positions[5] - truth(tracks.positions[0], 5)).norm(dim=1)[left].max())
    assert errors[True, 1] > 0.3 and errors[True, 2] < 0.02 and errors[False, 3] < 0.02
    with pytest.raises(ValueError, match="attempts must be at least 1"):
        track_rigid_bodies(cache, RigidTrackConfig(attempts=0), torch.Generator())
