"""gsplat (CUDA) gives the same images as the CPU kernel. Skips cleanly without CUDA and gsplat."""
import pytest
import torch

from pidg.render import rasterize
from pidg.render.rasterize_gsplat import gsplat_available
from pidg.render.scenes import orbit_camera, random_scene

pytestmark = pytest.mark.skipif(not gsplat_available(), reason="gsplat backend needs CUDA and `pip install gsplat`")


def test_gsplat_matches_cpu_kernel():
    camera = orbit_camera(96, 64)
    scene = random_scene(500, camera, n_features=5, seed=0)
    bg = torch.tensor([0.1, 0.2, 0.3])
    cpu = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, features=scene.features, background=bg, backend="cpu")
    to = lambda t: t.cuda()  # noqa: E731
    gpu = rasterize(to(scene.means), to(scene.quats), to(scene.opacities), to(scene.colors), camera, scales=to(scene.scales), features=to(scene.features), background=to(bg), backend="gsplat")
    for name in ("rgb", "alpha", "depth", "features"):
        assert (getattr(cpu, name) - getattr(gpu, name).cpu()).abs().max() < 1e-3, name
    assert torch.equal(cpu.visible, gpu.visible.cpu())
