"""Bad input to the rasterizer raises a clear error naming the problem."""
import pytest
import torch

from pidg.render import rasterize
from pidg.render.scenes import orbit_camera, random_scene


@pytest.fixture
def scene():
    return random_scene(10, orbit_camera(16, 16), seed=0)


def call(scene, **overrides):
    args = dict(means=scene.means, quats=scene.quats, opacities=scene.opacities, colors=scene.colors, camera=orbit_camera(16, 16), scales=scene.scales)
    args.update(overrides)
    return rasterize(**args)


@pytest.mark.parametrize(
    "override,match",
    [
        (lambda s: dict(quats=s.quats[:5]), "quats must have shape"),
        (lambda s: dict(means=s.means[:, :2]), "means must have shape"),
        (lambda s: dict(colors=torch.rand(10, 4)), "colors must be RGB"),
        (lambda s: dict(colors=torch.rand(10, 4, 3), sh_degree=2), "sh_degree=2"),
        (lambda s: dict(features=torch.rand(9, 2)), "features must have shape"),
        (lambda s: dict(opacities=s.opacities.double()), "dtype"),
        (lambda s: dict(means=s.means.half(), quats=s.quats.half(), scales=s.scales.half(), opacities=s.opacities.half(), colors=s.colors.half()), "float32 or float64"),
        (lambda s: dict(scales=torch.where(torch.arange(10)[:, None] == 3, float("nan"), s.scales)), r"scales contains NaN.*\[3\]"),
        (lambda s: dict(colors=s.colors.to("meta")), "colors is on meta"),
        (lambda s: dict(scales=-s.scales), "non-negative"),
        (lambda s: dict(log_scales=s.scales.log()), "exactly one"),
        (lambda s: dict(backend="gsplat"), "CUDA"),
        (lambda s: dict(backend="vulkan"), "unknown backend"),
        (lambda s: dict(background=torch.ones(4)), "background"),
    ],
)
def test_bad_input_raises(scene, override, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call(scene, **override(scene))


def test_log_scales_equivalent(scene):
    a = call(scene)
    b = call(scene, scales=None, log_scales=scene.scales.log())
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6)
