"""bench rigid-tracks: tracks scored against a truth they are known to differ from by a set amount."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math
from pathlib import Path

import numpy as np
import torch

from pidg.bench.rigid_tracks import format_result, score_tracks, TrackBenchResult
from pidg.data.motion_gt import MotionGroundTruth, MotionObject, VertexMotion
from pidg.flow.rigid_tracks import RigidTracks


def truth_of_a_turning_cube_and_a_cloth(frames: int) -> MotionGroundTruth:
    """A cube's 8 corners (rigid: turning 0.1 rad a frame about z while moving 0.2 along x) and 4 cloth vertices
    (non-rigid) far from it."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64)
    cloth = np.array([[5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [5.0, 1.0, 0.0], [6.0, 1.0, 0.0]])
    positions = []
    for k in range(frames):
        c, s = math.cos(0.1 * k), math.sin(0.1 * k)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        positions.append(np.concatenate([corners @ rotation.T + [0.2 * k, 0.0, 0.0], cloth + [0.0, 0.0, 0.3 * k * k]]))
    times = np.linspace(0.0, 1.0, frames)
    vertices = VertexMotion(times, np.stack(positions).astype(np.float32), np.zeros((frames, 12, 3), np.float32),
                            np.zeros((0, 3), np.int64))
    objects = [MotionObject("cube", "rigid", 0, 8), MotionObject("sheet", "cloth", 8, 4)]
    return MotionGroundTruth(Path("."), 1.0 / (frames - 1), objects, vertices)


def test_tracks_off_by_a_set_amount_score_that_share_of_the_travel():
    frames = 5
    truth = truth_of_a_turning_cube_and_a_cloth(frames)
    start = torch.tensor([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.0, 0.5, 0.5], [5.5, 0.5, 0.0]], dtype=torch.float64)
    expected = []
    for k in range(frames):
        c, s = math.cos(0.1 * k), math.sin(0.1 * k)
        rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        expected.append(start @ rotation.T + torch.tensor([0.2 * k, 0.0, 0.0], dtype=torch.float64))
    expected = torch.stack(expected)
    off = expected.clone()
    off[1:, :, 2] += 0.05  # every tracked position 0.05 off after the first frame
    known = torch.ones(frames, 4, dtype=torch.bool)
    known[4, 2] = False  # ... and body 1 lost before the last frame
    body = torch.tensor([0, 0, 1, 2])
    found = torch.ones(frames - 1, 3, dtype=torch.bool)
    found[0, 0] = False
    tracks = RigidTracks(torch.tensor(truth.vertices.times), off, known, body, torch.zeros(0, 3), found,
                         torch.tensor([1, 3, 1]), torch.tensor([0.9, 0.8, math.nan], dtype=torch.float64))
    relative, step_relative, move_relative, bodies, not_scored = score_tracks(tracks, truth)
    travel = (expected[:, :3] - expected[0, :3]).norm(dim=-1)
    scored = known[:, :3]
    assert math.isclose(relative, 0.05 * int(scored[1:].sum()) / float(travel[scored].sum()), rel_tol=1e-5)  # float32 vertices
    # the moves: only the first is off (by 0.05), on the three scored points; the others are exact
    steps = (expected[1:, :3] - expected[:-1, :3]).norm(dim=-1)
    stepped = scored[1:] & scored[:-1]
    assert math.isclose(step_relative, 0.05 * 3 / float(steps[stepped].sum()), rel_tol=1e-5)
    assert math.isclose(bodies[1].step_relative, 0.05 / float(steps[:3, 2].sum()), rel_tol=1e-5)  # lost at the last frame
    # an offset along the turn's axis moves as the point itself: the move error is the step error here
    assert math.isclose(move_relative, step_relative, rel_tol=1e-5) and bodies[2].move_relative is None
    assert not_scored == ["sheet"]
    assert [b.object for b in bodies] == ["cube", "cube", ""]  # body 2 lies on the cloth: not scored
    assert bodies[2].relative is None and bodies[2].error is None
    assert bodies[0].tracked_intervals == 4 and bodies[1].tracked_intervals == 3
    assert math.isclose(bodies[0].fitted, 0.75) and bodies[1].fitted == 1.0
    assert math.isclose(bodies[0].error, 0.05 * 4 / 5, rel_tol=1e-5)  # 0 at the first frame, 0.05 at the four others
    assert bodies[2].step_relative is None
    # frame by frame: the error appears in the first interval (which body 0's tracker carried, body 1's fitted)
    assert bodies[0].error_by_frame[0] == 0.0
    assert all(math.isclose(e, 0.05, rel_tol=1e-5) for e in bodies[0].error_by_frame[1:])
    assert bodies[1].error_by_frame[4] is None and bodies[2].error_by_frame == [None] * frames
    assert (bodies[0].worst_interval, bodies[0].worst_fitted) == (0, False)
    assert (bodies[1].worst_interval, bodies[1].worst_fitted) == (0, True)
    assert math.isclose(bodies[1].worst_growth, 0.05, rel_tol=1e-5)
    assert bodies[2].worst_interval is None
    assert [b.chains for b in bodies] == [1, 3, 1] and bodies[1].look == 0.8 and bodies[2].look is None
    text = format_result(TrackBenchResult("scene", 4, 1.0, relative, step_relative, move_relative, 0.95, bodies, not_scored))
    assert "| 1 | cube | 1 | 100 % | 3/4 | 100 % | 3 | 0.800 |" in text
    assert "| 2 | (not rigid) |" in text and "not scored (not rigid): sheet" in text
    assert "interval 0 (+0.050, carried) |" in text and "interval 0 (+0.050, fitted) |" in text


def test_a_track_drifted_to_another_part_of_its_body_moves_right_there():
    """A track that jumps, over interval 1, from one corner of the turning cube to the opposite one, then follows
    that corner: its step error counts every later move against the first corner's (the turn moves opposite corners
    opposite ways), while its move error counts only the jump, each later move being what the cube does where the
    track is."""
    frames = 5
    truth = truth_of_a_turning_cube_and_a_cloth(frames)
    corner, opposite = torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64), torch.tensor([[-0.5, -0.5, 0.5]], dtype=torch.float64)

    def carried(point: torch.Tensor, k: int) -> torch.Tensor:
        c, s = math.cos(0.1 * k), math.sin(0.1 * k)
        rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        return point @ rotation.T + torch.tensor([0.2 * k, 0.0, 0.0], dtype=torch.float64)

    positions = torch.stack([carried(corner if k <= 1 else opposite, k) for k in range(frames)])
    tracks = RigidTracks(torch.tensor(truth.vertices.times), positions, torch.ones(frames, 1, dtype=torch.bool),
                         torch.zeros(1, dtype=torch.long), torch.zeros(0, 3), torch.ones(frames - 1, 1, dtype=torch.bool),
                         torch.ones(1, dtype=torch.long), torch.ones(1, dtype=torch.float64))
    _, step_relative, move_relative, bodies, _ = score_tracks(tracks, truth)
    moves = torch.stack([carried(corner, k + 1) - carried(corner, k) for k in range(frames - 1)])[:, 0]
    there = torch.stack([carried(corner if k <= 1 else opposite, k + 1) - carried(corner if k <= 1 else opposite, k)
                         for k in range(frames - 1)])[:, 0]  # the true moves where the track is
    jump = float((positions[2, 0] - positions[1, 0] - moves[1]).norm())
    assert math.isclose(move_relative, jump / float(there.norm(dim=-1).sum()), rel_tol=1e-5)
    assert step_relative > move_relative + 0.1 and bodies[0].move_relative == move_relative
