"""The gsplat (CUDA) adapter. On CPU: its plumbing against a stand-in for gsplat's documented ``rasterization``
(built from pidg's torch reference), so the positional gradient densification reads, the radii of either gsplat
version, depth and feature channels are checked without a GPU. On CUDA with gsplat: the same images, and the same
gradients (the view-space one densification thresholds included), as the CPU kernel."""
import sys
import types

import pytest
import torch

from pidg.render import rasterize
from pidg.render.projection import project_gaussians
from pidg.render.rasterize_gsplat import gsplat_available, rasterize_gsplat
from pidg.render.rasterize_torch import composite_reference
from pidg.render.scenes import orbit_camera, random_scene

DOCUMENTED = {  # gsplat.rasterization's keyword arguments (gsplat >= 1.4 API reference)
    "means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "width", "height", "near_plane", "far_plane",
    "radius_clip", "eps2d", "sh_degree", "packed", "tile_size", "backgrounds", "render_mode", "sparse_grad",
    "absgrad", "rasterize_mode", "channel_chunk", "distributed", "camera_model",
}


def _fake_gsplat(isotropic_radii: bool) -> types.ModuleType:
    """A module whose ``rasterization`` follows gsplat's contract for one camera, packed=False, RGB+D: renders
    [1, H, W, D + 1] (colours, then accumulated depth), alphas [1, H, W, 1], meta with means2d [1, N, 2] (the tensor
    its backward fills), radii [1, N, 2] (gsplat >= 1.5) or [1, N], depths [1, N]."""

    def rasterization(**kw):
        assert set(kw) <= DOCUMENTED, set(kw) - DOCUMENTED
        assert kw["packed"] is False and kw["render_mode"] == "RGB+D" and kw["sh_degree"] is None
        assert kw["viewmats"].shape == (1, 4, 4) and kw["Ks"].shape == (1, 3, 3)
        from pidg.render.camera import Camera

        w2c, k = kw["viewmats"][0], kw["Ks"][0]
        camera = Camera(
            w2c, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), kw["width"], kw["height"], kw["near_plane"], kw["far_plane"]
        )
        proj = project_gaussians(kw["means"], kw["quats"], kw["scales"], kw["opacities"], camera)
        means2d = proj.means2d[None]  # the gradient arrives here, as in gsplat
        per = torch.cat([kw["colors"], proj.depths[:, None]], dim=-1)
        image, alpha, _ = composite_reference(means2d[0], proj.conics, kw["opacities"], per, proj.depths, proj.radii, kw["width"], kw["height"])
        radii = proj.radii.max(dim=-1).values if isotropic_radii else proj.radii
        return image[None], alpha[None, ..., None], {"means2d": means2d, "radii": radii[None], "depths": proj.depths[None]}

    module = types.ModuleType("gsplat")
    module.rasterization = rasterization
    return module


@pytest.mark.parametrize("isotropic_radii", [False, True])
def test_adapter_plumbing_against_the_documented_contract(monkeypatch, isotropic_radii):
    monkeypatch.setitem(sys.modules, "gsplat", _fake_gsplat(isotropic_radii))
    camera = orbit_camera(40, 32)
    scene = random_scene(300, camera, n_features=5, seed=1)
    bg = torch.tensor([0.1, 0.2, 0.3])
    means = scene.means.clone().requires_grad_(True)
    ref = rasterize(means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, features=scene.features, background=bg, backend="torch")
    ref.retain_means2d_grad()
    (ref.rgb.sum() + ref.features.square().sum()).backward()
    means_b = scene.means.clone().requires_grad_(True)
    out = rasterize_gsplat(means_b, scene.quats, scene.scales, scene.opacities, scene.colors, camera, scene.features, bg)
    out.retain_means2d_grad()
    (out.rgb.sum() + out.features.square().sum()).backward()
    for name in ("rgb", "alpha", "depth", "features"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=1e-5, rtol=1e-5, msg=name)
    assert out.means2d.shape == (300, 2) and out.radii.shape == (300, 2) and out.radii.dtype == torch.int32
    assert torch.equal(out.visible, ref.visible)
    torch.testing.assert_close(out.means2d_grad(), ref.means2d_grad(), atol=1e-6, rtol=1e-5)  # what densification reads
    torch.testing.assert_close(means_b.grad, means.grad, atol=1e-5, rtol=1e-5)


def test_the_two_stage_render_takes_gsplat_the_same_way(monkeypatch):
    """``prepare_render`` / ``gaussians_reaching`` / ``composite`` on the gsplat backend (CUDA's path, here against the
    stand-in, the backend forced for CPU tensors): no projection of its own (gsplat projects inside), the footprint
    superset from the torch projection for the reaching test, and the image, depth and features read at the asked
    pixels' tile rows as the torch reference renders them."""
    import pidg.render.api as api
    from pidg.render.api import composite, gaussians_reaching, prepare_render
    from pidg.render.footprint import footprints_touching

    monkeypatch.setitem(sys.modules, "gsplat", _fake_gsplat(isotropic_radii=False))
    monkeypatch.setattr(api, "resolve_backend", lambda backend, device: "gsplat" if backend == "gsplat" else "torch")
    camera = orbit_camera(40, 32)
    scene = random_scene(300, camera, n_features=5, seed=3)
    bg = torch.tensor([0.1, 0.2, 0.3])
    pixels = torch.zeros(32, 40, dtype=torch.bool)
    pixels[3:5, 20:23] = True
    pixels[25, 2] = True
    screen = prepare_render(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, background=bg, backend="gsplat")
    assert screen.backend == "gsplat" and screen.projection is None
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    assert torch.equal(gaussians_reaching(screen, pixels), footprints_touching(proj.means2d, proj.radii, pixels))
    out = composite(screen, scene.features, feature_pixels=pixels)
    ref = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, features=scene.features,
                    background=bg, backend="torch", feature_pixels=pixels)
    for name in ("rgb", "alpha", "depth", "features"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=1e-5, rtol=1e-5, msg=name)
    assert bool(out.features[pixels].abs().sum() > 0) and not out.features[10:20].any()  # rows without a read pixel: 0


def test_missing_gsplat_names_the_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import fails
    camera = orbit_camera(8, 8)
    scene = random_scene(5, camera, seed=0)
    with pytest.raises(ImportError, match="pip install gsplat"):
        rasterize_gsplat(scene.means, scene.quats, scene.scales, scene.opacities, scene.colors, camera, None, torch.zeros(3))


@pytest.mark.skipif(not gsplat_available(), reason="gsplat backend needs CUDA and `pip install gsplat`")
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


@pytest.mark.skipif(not gsplat_available(), reason="gsplat backend needs CUDA and `pip install gsplat`")
def test_gsplat_gradients_match_cpu_kernel():
    """Training and densification read these: d loss / d (means, quats, scales, opacities, colours, features) and
    the view-space positional gradient, for a loss on every output channel."""
    camera = orbit_camera(96, 64)
    scene = random_scene(400, camera, n_features=5, seed=1)
    bg = torch.tensor([0.1, 0.2, 0.3])
    names = ("means", "quats", "scales", "opacities", "colors", "features")
    weights = torch.Generator().manual_seed(2)
    shapes = {"rgb": (64, 96, 3), "alpha": (64, 96), "depth": (64, 96), "features": (64, 96, 5)}
    channel_weights = {c: torch.rand(s, generator=weights) for c, s in shapes.items()}

    def grads(backend: str, device: str) -> dict[str, torch.Tensor]:
        leaves = {n: getattr(scene, n).detach().to(device).requires_grad_(True) for n in names}
        out = rasterize(leaves["means"], leaves["quats"], leaves["opacities"], leaves["colors"], camera,
                        scales=leaves["scales"], features=leaves["features"], background=bg.to(device), backend=backend)
        loss = sum((getattr(out, c) * w.to(device)).sum() for c, w in channel_weights.items())
        loss.backward()
        found = {n: t.grad.cpu() for n, t in leaves.items()}
        found["means2d"] = out.means2d_grad().cpu()
        return found

    cpu, gpu = grads("cpu", "cpu"), grads("gsplat", "cuda")
    for name, expected in cpu.items():
        scale = expected.abs().max().clamp_min(1e-6)
        assert ((gpu[name] - expected).abs().max() / scale) < 1e-2, name
