"""``pidg bench motion-fit``: surface samples follow the true meshes, the scores measure what they say (a field that
carries the truth scores 0, one that stands still scores 1), and a fresh field fitted to a turning body turns it."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import Tensor

from pidg.bench.motion_fit import (
    MotionFitConfig,
    carried_points,
    fit_velocity_field,
    fitted_velocities,
    fresh_field,
    fresh_material_field,
    score_field,
    score_velocities,
    static_anchors,
    surface_samples,
    trained_velocities,
)
from pidg.data.motion_gt import MotionGroundTruth, MotionObject, VertexMotion
from pidg.models.deformation import Bounds, Grid4D, Grid4DConfig, HashGridConfig
from pidg.models.deformation.identity import IdentityDeformation
from pidg.models.material_field import MaterialField, MaterialFieldConfig
from pidg.models.time_axis import TimeAxis
from pidg.training.config import TrainConfig
from pidg.training.motion_start import fit_config, fit_field
from pidg.training.optim import deformation_optimizer, material_optimizers

TURN_DEG = 10.0  # the square's turn per sample interval


def _square(samples: int = 8, turn_deg: float = TURN_DEG, shift: float = 0.05) -> MotionGroundTruth:
    """A unit square (two triangles) in the plane z = 0.5, turning ``turn_deg`` about its centre's vertical axis and
    sliding ``shift`` along x per sample, with its vertices' exact velocities (per unit of dataset time)."""
    corners = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    per_time = samples - 1  # sample intervals per unit of dataset time
    positions, velocities = [], []
    for k in range(samples):
        a = math.radians(turn_deg * k)
        rotation = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        spin = np.array([[-math.sin(a), -math.cos(a), 0.0], [math.cos(a), -math.sin(a), 0.0], [0.0, 0.0, 0.0]])  # dR/da
        positions.append(corners @ rotation.T + np.array([shift * k, 0.0, 0.5]))
        velocities.append(corners @ spin.T * math.radians(turn_deg) * per_time + np.array([shift * per_time, 0.0, 0.0]))
    times = np.linspace(0.0, 1.0, samples)
    vertices = VertexMotion(times, np.array(positions, np.float32), np.array(velocities, np.float32),
                            np.array([[0, 1, 2], [0, 2, 3]], np.int64))
    return MotionGroundTruth(Path("motion_gt"), float(times[1]), [MotionObject("square", "rigid", 0, 4)], vertices)


def test_surface_samples_lie_on_the_triangles_and_move_with_them():
    truth = _square()
    samples = surface_samples(truth, 500, torch.Generator().manual_seed(0))
    first = samples.trajectories[0]
    assert samples.trajectories.shape == (8, 500, 3)
    assert (samples.owner == 0).all()
    assert torch.allclose(first[:, 2], torch.full((500,), 0.5))  # on the square's plane
    assert (first[:, :2].abs() <= 0.5 + 1e-6).all()  # inside it
    assert first[:, 0].std() > 0.2 and first[:, 1].std() > 0.2  # spread over it, not on one edge
    # carried rigidly: pairwise distances are kept, and the turn is the square's
    distances = lambda x: torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist")
    assert torch.allclose(distances(first), distances(samples.trajectories[5]), atol=1e-5)
    centred = lambda x: x - x.mean(0)
    angle = torch.atan2(centred(samples.trajectories[1])[:, 1], centred(samples.trajectories[1])[:, 0]) - \
        torch.atan2(centred(first)[:, 1], centred(first)[:, 0])
    assert torch.allclose(torch.remainder(angle + math.pi, 2 * math.pi) - math.pi, torch.full((500,), math.radians(TURN_DEG)), atol=1e-4)


def test_a_field_that_carries_the_truth_scores_zero_and_one_that_stands_still_scores_one():
    truth = _square()
    samples = surface_samples(truth, 300, torch.Generator().manual_seed(1))
    right = score_field(samples.trajectories.clone(), samples, truth)
    assert right.position_error < 1e-6 and right.step_relative < 1e-5 and right.spin_relative < 1e-3
    assert right.spin_intervals == 7 and right.spin_true_deg == pytest.approx(TURN_DEG, abs=1e-3)
    still = score_field(samples.trajectories[:1].expand(8, -1, -1), samples, truth)
    assert still.position_relative == pytest.approx(1.0, abs=1e-6)
    assert still.step_relative == pytest.approx(1.0, abs=1e-6)
    assert still.spin_relative == pytest.approx(1.0, abs=1e-3) and still.spin_learned_deg == pytest.approx(0.0, abs=1e-3)
    # the translation alone: right in position at the centre, no spin
    slid = samples.trajectories[:1] + (samples.trajectories.mean(1, keepdim=True) - samples.trajectories[:1].mean(1, keepdim=True))
    translated = score_field(slid, samples, truth)
    assert translated.spin_relative == pytest.approx(1.0, abs=1e-3)
    assert 0.0 < translated.position_relative < 1.0


def test_a_body_that_does_not_turn_is_not_scored_for_spin():
    truth = _square(turn_deg=0.0)
    samples = surface_samples(truth, 100, torch.Generator().manual_seed(2))
    scores = score_field(samples.trajectories.clone(), samples, truth)
    assert scores.spin_relative is None and scores.spin_intervals == 0
    assert scores.per_object == {"square": pytest.approx(0.0, abs=1e-6)}


def test_static_anchors_stay_clear_of_every_moving_point():
    truth = _square(samples=4)
    samples = surface_samples(truth, 2000, torch.Generator().manual_seed(0))
    moving = torch.cat([torch.from_numpy(truth.vertices.positions), samples.trajectories], dim=1)
    # the square's centre is far from its corners but on its surface; the last point passes where it slides
    means = torch.tensor([[0.0, 0.0, 0.5], [0.3, 0.0, 0.5], [3.0, 3.0, 0.0], [-3.0, 2.0, 0.0], [0.65, 0.0, 0.52]])
    anchors = static_anchors(means, moving, 0.05, 10, torch.Generator().manual_seed(0))
    assert sorted(map(tuple, anchors.tolist())) == [(-3.0, 2.0, 0.0), (3.0, 3.0, 0.0)]
    assert len(static_anchors(means, moving, 0.05, 1, torch.Generator().manual_seed(0))) == 1


def test_a_fresh_field_fitted_to_the_trajectories_learns_the_turn():
    truth = _square(samples=6)
    samples = surface_samples(truth, 400, torch.Generator().manual_seed(3))
    config = Grid4DConfig(spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16),
                          width=32)
    field = Grid4D(config, Bounds.from_points(samples.trajectories.reshape(-1, 3), margin=0.2))
    before = score_field(carried_points(field, samples.trajectories[0], samples.times), samples, truth)
    assert before.spin_relative == pytest.approx(1.0, abs=1e-3)  # the heads start at zero: no motion
    optimizer = deformation_optimizer(field, fit_config(TrainConfig(), 300), scene_extent=1.0)  # rates 2e-3, grids x10
    fit_field(field, samples.trajectories[0], samples.trajectories, samples.times, optimizer, 300, torch.Generator().manual_seed(0))
    after = score_field(carried_points(field, samples.trajectories[0], samples.times), samples, truth)
    assert after.position_relative < 0.2
    assert after.spin_relative < 0.4
    copy = fresh_field(field)
    assert type(copy) is Grid4D and torch.equal(copy.normalize.centre, field.normalize.centre)
    assert not torch.equal(copy.head_warp.weight, field.head_warp.weight)  # untrained


def test_bad_settings_and_fields_without_parameters_get_one_clear_error():
    with pytest.raises(ValueError, match="--points must be >= 3"):
        MotionFitConfig(surface_points=2)
    with pytest.raises(ValueError, match="--steps must be >= 0"):
        MotionFitConfig(steps=-1)
    with pytest.raises(ValueError, match="nothing to fit"):
        fresh_field(IdentityDeformation())


def test_a_truth_of_points_without_triangles_is_sampled_at_its_vertices():
    truth = _square()
    points = MotionGroundTruth(truth.root, truth.frame_interval, truth.objects, VertexMotion(
        truth.vertices.times, truth.vertices.positions, truth.vertices.velocities, np.zeros((0, 3), np.int64)))
    samples = surface_samples(points, 10, torch.Generator().manual_seed(0))
    assert samples.trajectories.shape == (8, 4, 3)  # all four vertices, once each
    assert torch.allclose(samples.trajectories, torch.from_numpy(truth.vertices.positions))
    assert (samples.owner == 0).all()
    assert score_field(samples.trajectories.clone(), samples, points).spin_relative < 1e-3


def test_surface_samples_carry_the_rigid_velocity_of_their_place():
    """Each sample's velocity is the square's rigid one at its position, omega x (p - centre) + the slide's rate (a
    closed form, not the vertices' interpolation it is computed by)."""
    truth = _square()
    samples = surface_samples(truth, 300, torch.Generator().manual_seed(4))
    per_time = len(truth.vertices.times) - 1
    omega = torch.tensor([0.0, 0.0, math.radians(TURN_DEG) * per_time])
    slide = torch.tensor([0.05 * per_time, 0.0, 0.0])
    for k in (0, 3, 7):
        centre = torch.tensor([0.05 * k, 0.0, 0.5])
        expected = torch.linalg.cross(omega.expand(300, 3), samples.trajectories[k] - centre) + slide
        assert torch.allclose(samples.velocities[k], expected, atol=1e-5)


def test_velocity_scores_are_zero_for_the_truth_and_one_for_standing_still():
    truth = _square()
    samples = surface_samples(truth, 200, torch.Generator().manual_seed(5))
    right = score_velocities(samples.velocities.clone(), samples)
    assert right.relative == pytest.approx(0.0, abs=1e-6) and right.error == pytest.approx(0.0, abs=1e-6)
    still = score_velocities(torch.zeros_like(samples.velocities), samples)
    assert still.relative == pytest.approx(1.0, abs=1e-6)
    assert still.relative_by_time == [pytest.approx(1.0, abs=1e-6)] * 8
    assert still.error == pytest.approx(float(samples.velocities.norm(dim=2).mean()), rel=1e-6)
    half = score_velocities(samples.velocities * 0.5, samples)  # half the speed everywhere: half of it off
    assert half.relative == pytest.approx(0.5, abs=1e-6)


def test_a_fresh_material_field_fitted_to_the_velocities_learns_them_in_the_fields_units():
    """Fitted in world units per physics time unit (here 4 per unit of dataset time), scored in the truth's units."""
    truth = _square(samples=6)
    samples = surface_samples(truth, 300, torch.Generator().manual_seed(6))
    axis = TimeAxis(physics_per_dataset=4.0, frame_interval=0.2)
    run_field = MaterialField(Bounds.from_points(samples.trajectories.reshape(-1, 3), margin=0.2), 10,
                              MaterialFieldConfig(width=64, spatial_resolution=8, time_resolution=6))
    field = fresh_material_field(run_field, 300)
    assert field.num_particles == 300 and torch.equal(field.normalize.centre, run_field.normalize.centre)
    before = score_velocities(fitted_velocities(field, samples, axis), samples)
    assert before.relative == pytest.approx(1.0, abs=0.1)  # the velocity head starts small: nearly still
    optimizers = material_optimizers(field, fit_config(TrainConfig(), 400), scene_extent=1.0)
    fit_velocity_field(field, samples.trajectories, samples.velocities / 4.0, samples.times, optimizers, 400,
                       torch.Generator().manual_seed(0))
    after = score_velocities(fitted_velocities(field, samples, axis), samples)
    assert after.relative < 0.2
    wrong_units = score_velocities(fitted_velocities(field, samples, TimeAxis(physics_per_dataset=1.0, frame_interval=0.2)), samples)
    assert wrong_units.relative > 0.6  # read as per dataset time, the same v is a quarter of the speed


def test_the_trained_field_is_read_with_the_index_of_the_gaussian_nearest_each_point():
    """A stand-in field whose v is its index along x: each point gets the index of the Gaussian nearest it *at that
    time* (the Gaussians move), times the time axis' scale."""
    truth = _square(samples=3)
    samples = surface_samples(truth, 50, torch.Generator().manual_seed(7))
    far = torch.tensor([[100.0, 0.0, 0.0]])

    def at(t: float) -> SimpleNamespace:  # Gaussian 0 sits on the square at t = 0.5 only, Gaussian 1 otherwise
        k = int(round(t * 2))
        square = samples.trajectories[k].mean(0, keepdim=True)
        return SimpleNamespace(means=torch.cat([square, far] if k == 1 else [far, square]))

    def field(x: Tensor, t: Tensor, index: Tensor) -> tuple[Tensor, None]:
        return torch.stack([index.float() + 10.0, torch.zeros(len(x)), torch.zeros(len(x))], dim=1), None

    model = SimpleNamespace(material_field=field, at=at, gaussians=SimpleNamespace(particle_index=torch.tensor([3, 5])),
                            time_axis=TimeAxis(physics_per_dataset=2.0, frame_interval=0.5))
    v = trained_velocities(model, samples)
    assert v.shape == (3, 50, 3)
    assert torch.all(v[0, :, 0] == 30.0) and torch.all(v[1, :, 0] == 26.0) and torch.all(v[2, :, 0] == 30.0)
