"""Static/dynamic decoupling: the split from motion masks or from the learned motion, and no jump at the switch."""
import math

import pytest
import torch

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.models.deformation import DeformationConfig, DeformationModel, DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.training.decoupling import StaticDynamicDecoupling, time_averaged_state


class Sway(DeformationModel):
    """Rows with canonical x > 0 move by ``amplitude * sin(2 pi t)`` along y (the others stay); every row also turns
    about z by ``angle * t`` (a known rotation, to check the quaternion average)."""

    def __init__(self, amplitude: float, angle: float = 0.0) -> None:
        super().__init__()
        self.amplitude, self.angle = amplitude, angle

    def deform(self, means, quats, log_scales, times, regularize=False) -> DeformedGaussians:
        shift = torch.zeros_like(means)
        shift[:, 1] = self.amplitude * torch.sin(2 * math.pi * times) * (means[:, 0] > 0)
        half = 0.5 * self.angle * times
        turn = torch.stack([torch.cos(half), 0 * half, 0 * half, torch.sin(half)], dim=-1)  # about z, (w, x, y, z)
        w1, v1 = turn[:, :1], turn[:, 1:]
        w2, v2 = quats[:, :1], quats[:, 1:]
        product = torch.cat([w1 * w2 - (v1 * v2).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.linalg.cross(v1, v2)], dim=-1)
        return DeformedGaussians(means + shift, product, log_scales + 0.1 * times[:, None])


@pytest.fixture(scope="module")
def scene():
    return make_procedural_scene(ProceduralSceneConfig(n_train=12, n_test=2, width=48, height=48, n_gaussians=1500, n_init_points=400))


def model_with(scene, deformation: DeformationModel) -> DynamicGaussians:
    model = DynamicGaussians.from_scene(scene, GaussianModelConfig(), DeformationConfig(kind="identity"), None)
    model.deformation = deformation
    return model


def test_time_average_is_the_mean_state(scene):
    model = model_with(scene, Sway(amplitude=0.3, angle=0.4))
    times = [f.time for f in scene.train]
    average = time_averaged_state(model, times)
    expected_means = torch.stack([model.at(t).means for t in times]).mean(0)
    assert torch.allclose(average.means, expected_means, atol=1e-6)
    assert torch.allclose(average.log_scales, model.gaussians.params["log_scales"] + 0.1 * sum(times) / len(times), atol=1e-6)
    # rotations about z by angle * t averaged over evenly spread t: the rotation by angle * mean(t) (symmetric spread)
    mid = DeformedGaussians(*Sway(0.0, 0.4).deform(model.gaussians.params["means"], model.gaussians.params["quats"],
                                                   model.gaussians.params["log_scales"], torch.full((model.num_gaussians,), 0.5)).__dict__.values())
    aligned = torch.where((average.quats * mid.quats).sum(-1, keepdim=True) < 0, -average.quats, average.quats)
    assert torch.allclose(aligned, mid.quats, atol=1e-3)


def test_without_masks_the_learned_motion_splits_and_static_gaussians_do_not_jump(scene):
    frames = [f.__class__(f.camera, f.time, f.image_u8, None, f.name) for f in scene.train]  # no masks
    model = model_with(scene, Sway(amplitude=0.2))
    moving = model.gaussians.params["means"][:, 0] > 0
    before = {t: model.at(t).means.clone() for t in (0.0, 0.5)}
    hook = StaticDynamicDecoupling(at_step=1, vote=0.4, motion_px=1.0)
    assert hook.step_post_backward(model, frames, step=0)
    dynamic = model.dynamic_mask
    assert dynamic is not None
    # every Gaussian that sways (0.2 world units: many pixels at 48 px) is dynamic; the others are static
    always_seen = torch.ones_like(moving)
    for f in frames:
        uv, z = f.camera.project_points(before[0.0])
        always_seen &= (z > f.camera.near) & (uv[:, 0] >= 2) & (uv[:, 0] < 46) & (uv[:, 1] >= 2) & (uv[:, 1] < 46)
    assert int((moving & always_seen).sum()) > 50
    assert bool(dynamic[moving & always_seen].all()) and not bool(dynamic[~moving].any())
    # static ones keep where they were (their time average equals their position: they never moved) ...
    assert torch.allclose(model.at(0.5).means[~moving], before[0.5][~moving], atol=1e-6)
    assert not hook.step_post_backward(model, frames, step=5)  # once only


def test_static_gaussians_take_their_time_averaged_state_at_the_switch(scene):
    model = model_with(scene, Sway(amplitude=0.0))  # nothing moves, but every scale grows with t
    canonical = model.gaussians.params["log_scales"].clone()
    StaticDynamicDecoupling(at_step=1, vote=0.4, motion_px=1.0).step_post_backward(model, scene.train, step=0)
    static = ~model.dynamic_mask
    assert bool(static.any())
    mean_t = sum(f.time for f in scene.train) / len(scene.train)
    assert torch.allclose(model.at(0.0).log_scales[static], canonical[static] + 0.1 * mean_t, atol=1e-6)


def test_no_masks_and_motion_split_off_leaves_every_gaussian_dynamic(scene):
    frames = [f.__class__(f.camera, f.time, f.image_u8, None, f.name) for f in scene.train]
    model = model_with(scene, Sway(amplitude=0.2))
    assert not StaticDynamicDecoupling(at_step=1, motion_px=0.0).step_post_backward(model, frames, step=0)
    assert model.dynamic_mask is None


def test_a_learned_motion_split_waits_for_the_deformation_and_never_freezes_a_still_one(scene):
    """Without masks the split follows the learned motion: a deformation that has learned none yet (an MLP just out
    of its static warm-up) must not make every Gaussian static, and the split waits until ``motion_at_step``."""
    frames = [f.__class__(f.camera, f.time, f.image_u8, None, f.name) for f in scene.train]
    still = model_with(scene, Sway(amplitude=0.0))
    hook = StaticDynamicDecoupling(at_step=1, vote=0.4, motion_px=1.0)
    assert not hook.step_post_backward(still, frames, step=0)
    assert still.dynamic_mask is None  # every Gaussian keeps deforming
    swaying = model_with(scene, Sway(amplitude=0.2))
    later = StaticDynamicDecoupling(at_step=1, vote=0.4, motion_px=1.0, motion_at_step=4)
    assert not later.step_post_backward(swaying, frames, step=0) and swaying.dynamic_mask is None
    assert later.step_post_backward(swaying, frames, step=3) and swaying.dynamic_mask is not None
