"""Which Gaussians add to a set of pixels (``gaussians_reaching``): on the cpu backend exactly those the compositor
weights there, checked against the compositor's own gradients and against the float64 torch reference."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.render import Camera
from pidg.render.api import gaussians_reaching, prepare_render, project, rasterize
from pidg.render.footprint import footprints_touching
from pidg.render.rasterize_cpu import gaussians_reaching_cpu
from pidg.render.scenes import GaussianScene, orbit_camera, random_scene


def weighted_on(scene: GaussianScene, camera: Camera, pixels: torch.Tensor, backend: str) -> torch.Tensor:
    """[N] bool, by definition: the Gaussians whose weight alpha T is non-zero on some pixel of ``pixels`` in the
    backend's render. The weights are the image's derivative with respect to a feature channel of ones."""
    ones = torch.ones(scene.means.shape[0], 1, dtype=scene.means.dtype, requires_grad=True)
    out = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales,
                    features=ones, backend=backend)
    out.features[..., 0][pixels].sum().backward()
    return ones.grad[:, 0] > 0


def pixel_mask(camera: Camera, density: float, seed: int) -> torch.Tensor:
    """Random pixels plus a solid patch, so that some tiles are full and others hold a few pixels."""
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand(camera.height, camera.width, generator=gen) < density
    mask[5:14, 9:30] = density > 0
    return mask


def reaching(scene: GaussianScene, camera: Camera, pixels: torch.Tensor, backend: str = "cpu") -> torch.Tensor:
    screen = prepare_render(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, backend=backend)
    return gaussians_reaching(screen, pixels)


@pytest.mark.parametrize("density", [0.0, 0.03, 0.4])
@pytest.mark.parametrize("opacity", [(0.1, 0.6), (0.9, 0.99)])
def test_cpu_set_is_exactly_the_gaussians_the_compositor_weights_there(density, opacity):
    """Faint Gaussians (little is hidden) and near-opaque stacks (pixels saturate and hide what is behind them),
    partial tiles on both edges; the set equals the render's own and the float64 reference's."""
    camera = orbit_camera(61, 37)
    scene = random_scene(400, camera, pixel_sigma=(1.0, 9.0), opacity=opacity, extent=0.5, seed=int(density * 100) + 3)
    pixels = pixel_mask(camera, density, seed=5)
    found = reaching(scene, camera, pixels)
    assert torch.equal(found, weighted_on(scene, camera, pixels, "cpu"))
    scene64 = GaussianScene(*(None if x is None else x.double() for x in (scene.means, scene.quats, scene.scales,
                                                                          scene.opacities, scene.colors, scene.features)))
    assert torch.equal(found, weighted_on(scene64, camera, pixels, "torch"))
    if density > 0:
        proj = project(scene.means, scene.quats, scene.scales, scene.opacities, camera, "cpu")
        touching = footprints_touching(proj.means2d, proj.radii, pixels)
        assert 0 < int(found.sum()) and not (found & ~touching).any()
        if opacity[0] > 0.5:  # hidden Gaussians: the footprints cannot tell them apart, the compositor can
            assert int(found.sum()) < 0.8 * int(touching.sum())
    else:
        assert not found.any()


def test_ties_culled_and_huge_gaussians():
    """Exact copies (equal depths: the tile lists break ties by index), Gaussians behind the camera (culled) and
    one that covers the whole image: the set still equals the compositor's own weights."""
    camera = orbit_camera(45, 33)
    base = random_scene(150, camera, pixel_sigma=(1.0, 8.0), opacity=(0.5, 0.99), extent=0.4, seed=11)
    centre = torch.linalg.inv(camera.world_to_camera)[:3, 3]
    behind = centre + (centre - torch.zeros(3)) * torch.tensor([[0.1], [0.3], [0.6]])  # beyond the camera, away from the scene
    means = torch.cat([base.means, base.means[:20], behind, torch.zeros(1, 3)])
    k = means.shape[0] - base.means.shape[0]
    scene = GaussianScene(
        means=means,
        quats=torch.cat([base.quats, base.quats[:20], torch.tensor([[1.0, 0, 0, 0]] * 4)]),
        scales=torch.cat([base.scales, base.scales[:20], torch.full((3, 3), 0.05), torch.full((1, 3), 3.0)]),
        opacities=torch.cat([base.opacities, base.opacities[:20], torch.full((3,), 0.9), torch.tensor([0.05])]),
        colors=torch.rand(means.shape[0], 3), features=None,
    )
    assert k == 24
    for density in (0.05, 0.6):
        pixels = pixel_mask(camera, density, seed=4)
        found = reaching(scene, camera, pixels)
        assert torch.equal(found, weighted_on(scene, camera, pixels, "cpu"))
        assert not found[170:173].any() and bool(found[173])  # the culled ones never, the huge faint one here


def test_a_gaussian_behind_an_opaque_one_is_left_out():
    """A stack of three large near-opaque Gaussians on the camera's axis in front of a small one: the pixels at the
    centre saturate on the stack (transmittance ~1e-6), so the one behind adds nothing there, though its footprint
    covers them."""
    camera = orbit_camera(32, 32)
    towards = -torch.linalg.inv(camera.world_to_camera)[:3, 3]  # from the camera centre to the origin
    towards = towards / towards.norm()
    means = torch.stack([(-0.5 + 0.01 * k) * towards for k in range(3)] + [0.5 * towards])
    scene = GaussianScene(
        means=means, quats=torch.tensor([[1.0, 0, 0, 0]] * 4), scales=torch.tensor([[0.5] * 3] * 3 + [[0.05] * 3]),
        opacities=torch.tensor([0.999, 0.999, 0.999, 0.9]), colors=torch.rand(4, 3), features=None,
    )
    pixels = torch.zeros(32, 32, dtype=torch.bool)
    pixels[15:17, 15:17] = True
    found = reaching(scene, camera, pixels)
    proj = project(scene.means, scene.quats, scene.scales, scene.opacities, camera, "cpu")
    assert footprints_touching(proj.means2d, proj.radii, pixels).tolist() == [True] * 4
    assert torch.equal(found, weighted_on(scene, camera, pixels, "cpu"))
    assert found.tolist() == [True, True, False, False]  # the third would take T below 1e-4: the pixel stops there


def test_other_backends_take_the_footprints():
    """The torch reference (and gsplat) get the footprint boxes' superset: never less than the exact set."""
    camera = orbit_camera(40, 30)
    scene = random_scene(200, camera, opacity=(0.9, 0.99), extent=0.4, seed=8)
    pixels = pixel_mask(camera, 0.1, seed=2)
    proj = project(scene.means, scene.quats, scene.scales, scene.opacities, camera, "torch")
    assert torch.equal(reaching(scene, camera, pixels, "torch"), footprints_touching(proj.means2d, proj.radii, pixels))
    exact = reaching(scene, camera, pixels, "cpu")
    assert not (exact & ~reaching(scene, camera, pixels, "torch")).any()


def test_no_gaussians_and_wide_tiles():
    empty = torch.zeros(0, 2)
    got = gaussians_reaching_cpu(empty, torch.zeros(0, 3), torch.zeros(0), torch.zeros(0), torch.zeros(0, 2, dtype=torch.int32),
                                 torch.ones(8, 8, dtype=torch.bool))
    assert got.shape == (0,)
    with pytest.raises(ValueError, match="tiles up to 16 pixels"):
        gaussians_reaching_cpu(torch.zeros(1, 2), torch.ones(1, 3), torch.ones(1), torch.ones(1), torch.ones(1, 2, dtype=torch.int32),
                               torch.ones(8, 8, dtype=torch.bool), tile_size=32)


def test_a_prepared_render_bins_once_for_the_reaching_test_and_the_compositing(monkeypatch):
    """The flow loss asks which Gaussians reach its pixels between the render's projection and its compositing: both
    read one set of tile lists, and the set is the one a separate binning gives."""
    import pidg.render.api as api
    from pidg.render.api import composite

    camera = orbit_camera(48, 40)
    scene = random_scene(300, camera, pixel_sigma=(1.0, 6.0), opacity=(0.5, 0.99), extent=0.4, seed=21)
    pixels = pixel_mask(camera, 0.05, seed=9)
    calls = []
    original = api.bin_gaussians
    monkeypatch.setattr(api, "bin_gaussians", lambda *a, **k: calls.append(1) or original(*a, **k))
    screen = prepare_render(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, backend="cpu")
    found = gaussians_reaching(screen, pixels)
    features = torch.ones(scene.means.shape[0], 1)
    out = composite(screen, features, feature_pixels=pixels)
    assert len(calls) == 1
    proj = screen.projection
    assert torch.equal(found, gaussians_reaching_cpu(proj.means2d, proj.conics, scene.opacities, proj.depths, proj.radii, pixels))
    assert torch.equal(found, weighted_on(scene, camera, pixels, "cpu"))
    whole = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, features=features,
                      feature_pixels=pixels, backend="cpu")
    assert torch.equal(out.rgb, whole.rgb) and torch.equal(out.features, whole.features)
    other = prepare_render(scene.means[:-1], scene.quats[:-1], scene.opacities[:-1], scene.colors[:-1], camera,
                           scales=scene.scales[:-1], backend="cpu")
    with pytest.raises(ValueError, match="tile lists were made for other Gaussians"):
        gaussians_reaching_cpu(proj.means2d[:-1], proj.conics[:-1], scene.opacities[:-1], proj.depths[:-1], proj.radii[:-1],
                               pixels, bins=screen.bins)
    assert other.bins is not screen.bins
    torch_screen = prepare_render(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, backend="torch")
    with pytest.raises(ValueError, match="tile lists belong to the cpu backend"):
        torch_screen.bins
