"""The numba CPU compositor against the plain-torch reference, and the reference against finite differences."""
import math

import pytest
import torch

from pidg.render import Camera, rasterize
from pidg.render.scenes import GaussianScene, orbit_camera, random_scene


def hard_scene(camera: Camera, n_random: int, dtype: torch.dtype, n_features: int = 2, seed: int = 0) -> GaussianScene:
    """Random Gaussians plus the awkward cases: behind the camera, off-screen, sub-pixel, huge, stacked."""
    base = random_scene(n_random, camera, n_features=n_features, dtype=torch.float64, seed=seed)
    c2w = torch.linalg.inv(camera.world_to_camera.to(torch.float64))
    def world(points_cam):  # camera-space points -> world
        p = torch.tensor(points_cam, dtype=torch.float64)
        return p @ c2w[:3, :3].T + c2w[:3, 3]
    z = 4.0
    special_cam = [
        [0.0, 0.0, -1.0],                 # behind the camera
        [0.1, 0.0, 0.001],                # inside the near plane
        [50.0, 0.0, z],                   # far off-screen
        [0.0, 0.0, z],                    # sub-pixel
        [0.05, -0.02, z + 0.5],           # huge: covers the whole image
        [0.2, 0.1, z], [0.2, 0.1, z], [0.2, 0.1, z + 1e-3],  # stacked (equal depths: ties broken by index)
        [-z * math.tan(camera.fov_x / 2) * 1.02, 0.0, z],    # centre just off the left edge, footprint on-screen
    ]
    sigma_px = [3.0, 3.0, 3.0, 0.15, 400.0, 6.0, 6.0, 6.0, 5.0]
    means = world(special_cam)
    k = means.shape[0]
    gen = torch.Generator().manual_seed(seed + 1)
    scales = torch.tensor(sigma_px, dtype=torch.float64)[:, None] * z / camera.fx * (0.5 + torch.rand(k, 3, generator=gen, dtype=torch.float64))
    opac = torch.tensor([0.8, 0.8, 0.9, 0.9, 0.3, 0.7, 0.6, 0.95, 0.8], dtype=torch.float64)
    cat = lambda a, b: torch.cat([a, b]).to(dtype)  # noqa: E731
    return GaussianScene(
        means=cat(base.means, means),
        quats=cat(base.quats, torch.randn(k, 4, generator=gen, dtype=torch.float64)),
        scales=cat(base.scales, scales),
        opacities=cat(base.opacities, opac),
        colors=cat(base.colors, torch.rand(k, 3, generator=gen, dtype=torch.float64)),
        features=cat(base.features, torch.randn(k, n_features, generator=gen, dtype=torch.float64)) if n_features else None,
    )


def render(scene: GaussianScene, camera: Camera, backend: str, sh_degree=None, background=None):
    return rasterize(
        scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales,
        features=scene.features, backend=backend, sh_degree=sh_degree, background=background,
    )


def scalar_loss(out, seed=7):
    """A loss touching every output with random weights, so every gradient path is exercised."""
    gen = torch.Generator().manual_seed(seed)
    total = 0.0
    for t in (out.rgb, out.alpha, out.depth, out.features):
        if t is not None:
            total = total + (t * torch.randn(t.shape, generator=gen, dtype=t.dtype)).sum()
    return total


CAMERAS = {
    "square": lambda: orbit_camera(48, 48),
    "wide": lambda: orbit_camera(70, 38, azimuth_deg=30.0),
    "tall_offset": lambda: Camera(orbit_camera(33, 61).world_to_camera, 40.0, 44.0, 14.0, 33.0, 33, 61),
}


@pytest.mark.parametrize("cam_name", sorted(CAMERAS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_reference(cam_name, dtype):
    camera = CAMERAS[cam_name]()
    scene = hard_scene(camera, 150, dtype)
    bg = torch.tensor([0.2, 0.5, 1.0], dtype=dtype)
    ref = render(scene, camera, "torch", background=bg)
    cpu = render(scene, camera, "cpu", background=bg)
    assert ref.rgb.shape == (camera.height, camera.width, 3)
    assert ref.alpha.max() > 0.9 and ref.alpha.min() < 0.5  # the scene really draws something, not everywhere
    for name in ("rgb", "alpha", "depth", "features"):
        err = (getattr(ref, name) - getattr(cpu, name)).abs().max().item()
        assert err < 1e-5, f"{name}: max abs error {err}"
    assert torch.equal(ref.radii, cpu.radii)
    assert not ref.visible[-9] and not ref.visible[-8] and not ref.visible[-7]  # behind, near, off-screen
    assert ref.visible[-6] and ref.visible[-5] and ref.visible[-1]


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single(n):
    camera = orbit_camera(20, 13)
    scene = random_scene(n, camera, pixel_sigma=(3.0, 3.0), n_features=3, seed=3)
    if n == 1:
        scene.means.zero_()
    bg = torch.tensor([0.1, 0.2, 0.3])
    ref = render(scene.requires_grad_(), camera, "torch", background=bg)
    cpu = render(scene, camera, "cpu", background=bg)
    for name in ("rgb", "alpha", "depth", "features"):
        assert torch.allclose(getattr(ref, name), getattr(cpu, name), atol=1e-6)
    if n == 0:
        assert torch.allclose(cpu.rgb, bg.expand(13, 20, 3)) and cpu.alpha.abs().max() == 0
    else:
        assert cpu.alpha.max() > 0.05
    scalar_loss(cpu).backward()
    for t in scene.params():
        assert t.grad is not None and t.grad.shape == t.shape and torch.isfinite(t.grad).all()


# The kernel computes in float32 (like gsplat) whatever the input dtype; the float64 case checks that only
# float32 rounding separates it from the exact reference.
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-4), (torch.float64, 1e-5)])
@pytest.mark.parametrize("sh_degree", [None, 3])
def test_gradients_match_reference(dtype, tol, sh_degree):
    camera = CAMERAS["wide"]()
    scene = hard_scene(camera, 120, dtype, n_features=3, seed=5)
    if sh_degree is not None:
        gen = torch.Generator().manual_seed(9)
        scene.colors = (0.3 * torch.randn(scene.means.shape[0], 16, 3, generator=gen)).to(dtype)
    bg = torch.tensor([0.3, 0.3, 0.3], dtype=dtype)
    grads, _ = _gradients_by_backend(scene, camera, sh_degree=sh_degree, background=bg)
    _assert_gradients_match(grads, tol)


_GRADIENT_NAMES = ["means", "quats", "scales", "opacities", "colors", "features", "means2d"]


def _gradients_by_backend(scene: GaussianScene, camera: Camera, **render_options) -> tuple[dict, dict]:
    """Gradients of ``scalar_loss`` w.r.t. the scene's parameters and the projected means (``_GRADIENT_NAMES``), and
    the renders, of the torch reference and the kernel (keys "torch", "cpu")."""
    grads, outs = {}, {}
    for backend in ("torch", "cpu"):
        params = [t.detach().clone().requires_grad_(True) for t in scene.params()]
        out = render(GaussianScene(*params), camera, backend, **render_options)
        scalar_loss(out).backward()
        grads[backend], outs[backend] = [p.grad for p in params] + [out.means2d.grad], out
    return grads, outs


def _assert_gradients_match(grads: dict, tol: float, names: list[str] = _GRADIENT_NAMES) -> None:
    for name, g_ref, g_cpu in zip(names, grads["torch"], grads["cpu"], strict=True):
        rel = ((g_ref - g_cpu).norm() / g_ref.norm()).item()
        assert g_ref.norm() > 0, name
        assert rel < tol, f"{name}: relative gradient error {rel:.2e}"


def _kernel_and_reference_gradients(scene: GaussianScene, camera: Camera):
    grads, outs = _gradients_by_backend(scene, camera, background=torch.tensor([0.4, 0.6, 0.2], dtype=torch.float64))
    for name in ("rgb", "alpha", "depth", "features"):
        assert (getattr(outs["torch"], name) - getattr(outs["cpu"], name)).abs().max() < 1e-5, name
    _assert_gradients_match(grads, 1e-5)
    return outs["torch"]


def test_gradients_match_reference_where_pixels_saturate():
    """A dense stack of near-opaque Gaussians: most pixels end their walk early (transmittance below 1e-4: the
    kernel's per-lane stop and per-row early exit, forward and backward)."""
    camera = orbit_camera(37, 29)  # partial tiles on both edges
    scene = random_scene(300, camera, pixel_sigma=(4.0, 14.0), opacity=(0.9, 0.98), extent=0.3, n_features=3,
                         dtype=torch.float64, seed=21)
    ref = _kernel_and_reference_gradients(scene, camera)
    # a pixel stops where the next Gaussian would take its transmittance below 1e-4: with alpha <= 0.99, T < 1e-2
    assert (ref.alpha > 0.999).float().mean() > 0.3


def test_gradients_match_reference_where_alpha_clamps():
    """Large Gaussians of opacity above 0.99: around each centre alpha is clamped to 0.99 and passes no gradient."""
    camera = orbit_camera(40, 32)
    scene = random_scene(6, camera, pixel_sigma=(12.0, 18.0), opacity=(0.995, 0.999), extent=0.6, n_features=2,
                         dtype=torch.float64, seed=4)
    _kernel_and_reference_gradients(scene, camera)


def test_reference_gradients_match_finite_differences():
    camera = CAMERAS["tall_offset"]()
    scene = random_scene(12, camera, pixel_sigma=(2.0, 6.0), opacity=(0.2, 0.9), n_features=2, dtype=torch.float64, seed=11)

    def loss(means, quats, scales, opacities, colors, features):
        s = GaussianScene(means, quats, scales, opacities, colors, features)
        return scalar_loss(render(s, camera, "torch", background=torch.tensor([0.5, 0.2, 0.1], dtype=torch.float64)))

    inputs = tuple(t.requires_grad_(True) for t in scene.params())
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_features_composite_like_colour():
    """Feature channels use exactly the colour weights: features = colours must reproduce the RGB image."""
    camera = orbit_camera(40, 30)
    scene = random_scene(200, camera, seed=2)
    scene.features = scene.colors.clone()
    out = render(scene, camera, "cpu")  # black background: rgb has no background term
    assert torch.allclose(out.features, out.rgb, atol=1e-6)


def test_depth_of_an_opaque_wall():
    """A large, flat, opaque Gaussian facing the camera gives its depth everywhere it covers."""
    camera = Camera.look_at((0, 0, 0), (0, 0, 1), (0, -1, 0), 32, 24, math.radians(50))
    means = torch.tensor([[0.0, 0.0, 3.0]])
    scene = GaussianScene(means, torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[1000.0, 1000.0, 1e-3]]), torch.tensor([0.98]), torch.ones(1, 3))
    out = render(scene, camera, "cpu")
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.98), atol=1e-4)
    assert torch.allclose(out.depth_normalized(), torch.full_like(out.depth, 3.0), atol=1e-4)
    assert torch.allclose(out.depth, 0.98 * 3.0 * torch.ones_like(out.depth), atol=1e-3)


def test_results_do_not_depend_on_tile_size():
    """Radii bound every contribution, so tiling is only an acceleration."""
    camera = orbit_camera(50, 40)
    scene = random_scene(300, camera, seed=4)
    a = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, tile_size=16)
    b = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, tile_size=5)
    assert (a.rgb - b.rgb).abs().max() < 1e-6


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_feature_pixels_composite_features_in_their_tile_rows_only(backend):
    """``feature_pixels``: features are those of the full render in the tile rows (a 16x16 tile's pixels on one
    image row) holding a chosen pixel and 0 elsewhere; colour, alpha and depth are untouched; a loss reading the
    features at the chosen pixels gets the same gradients, bit for bit on the kernel (its zeroed channels add exact
    zeros)."""
    camera = CAMERAS["wide"]()  # 70 x 38: partial tiles at the right and bottom edges
    scene = hard_scene(camera, 150, torch.float32, n_features=5, seed=3)
    pixels = torch.zeros(camera.height, camera.width, dtype=torch.bool)
    pixels[3, 5] = pixels[20:22, 66:69] = True  # in tiles (0, 0), (1, 4); (1, 4) is the partial corner tile
    tiles = torch.zeros_like(pixels)  # their tile rows
    tiles[3, 0:16] = tiles[20:22, 64:70] = True
    gen = torch.Generator().manual_seed(2)
    weights = [torch.randn(camera.height, camera.width, k, generator=gen) for k in (3, 5)]
    runs = {}
    for restricted in (False, True):
        params = [t.detach().clone().requires_grad_(True) for t in scene.params()]
        s = GaussianScene(*params)
        out = rasterize(s.means, s.quats, s.opacities, s.colors, camera, scales=s.scales, features=s.features,
                        backend=backend, feature_pixels=pixels if restricted else None)
        ((out.rgb * weights[0]).sum() + (out.features * weights[1] * pixels[..., None]).sum() + out.depth.sum()).backward()
        runs[restricted] = (out, [p.grad for p in params])
    (full, full_grads), (part, part_grads) = runs[False], runs[True]
    assert torch.equal(part.rgb, full.rgb) and torch.equal(part.alpha, full.alpha) and torch.equal(part.depth, full.depth)
    assert full.features[~tiles].abs().sum() > 0 and part.features[~tiles].abs().max() == 0
    assert torch.equal(part.features[tiles], full.features[tiles])
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors", "features"], full_grads, part_grads):
        if backend == "cpu":
            assert torch.equal(a, b), name
        else:
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("restricted", [False, True])
def test_the_image_and_extra_channels_of_the_kernel_are_the_references(restricted):
    """``image_channels``: the compositors return the leading channels as the image and the rest as ``extra``, each
    its own array; the kernel's outputs and gradients equal the reference's whichever of image, alpha and extra a
    loss reads (autograd sends None for the others: the kernel then skips the extra channels' backward), with and
    without tiles that composite the image's channels only."""
    from pidg.render.projection import project_gaussians
    from pidg.render.rasterize_cpu import composite_cpu
    from pidg.render.rasterize_torch import composite_reference

    camera = CAMERAS["wide"]()
    scene = hard_scene(camera, 150, torch.float32, n_features=5, seed=5)
    with torch.no_grad():
        proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.opacities, camera)
    per_gaussian = torch.cat([scene.colors, proj.depths[:, None], scene.features], dim=-1)  # 3 + 1 + 5 channels
    tiles = None
    if restricted:  # a third of the tile rows composite all 9 channels, the rest the image's 4 (fewer means 4)
        tiles = torch.tensor([9, 4, 2, 0, 9, 4])[torch.randint(6, (38, 5), generator=torch.Generator().manual_seed(6))]
    gen = torch.Generator().manual_seed(4)
    weights = [torch.randn(camera.height, camera.width, *k, generator=gen) for k in ((4,), (), (5,))]
    for read in [(True, True, True), (True, True, False), (False, False, True), (True, False, False)]:
        results = []
        for composite in (composite_reference, composite_cpu):
            leaves = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, scene.opacities, per_gaussian)]
            outputs = composite(*leaves, proj.depths, proj.radii, camera.width, camera.height, 16, tiles, image_channels=4)
            assert [tuple(o.shape) for o in outputs] == [(38, 70, 4), (38, 70), (38, 70, 5)]
            sum(((o * w).sum() for o, w, r in zip(outputs, weights, read) if r), torch.zeros(())).backward()
            results.append([o.detach() for o in outputs] + [t.grad for t in leaves])
        for name, ref, got in zip(["image", "alpha", "extra"], results[0][:3], results[1][:3]):
            torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6, msg=f"{name} reading {read}")
        # float32 against the reference, as test_gradients_match_reference
        _assert_gradients_match({"torch": results[0][3:], "cpu": results[1][3:]}, 1e-4, ["means2d", "conics", "opacities", "features"])
        if not read[2]:  # nothing reads the extra channels: no gradient reaches their per-Gaussian values
            assert results[1][-1][:, 4:].abs().max() == 0
    with pytest.raises(ValueError, match=r"image_channels must be in \[0, 9\]"):
        composite_cpu(proj.means2d, proj.conics, scene.opacities, per_gaussian, proj.depths, proj.radii, camera.width,
                      camera.height, image_channels=10)


def test_feature_pixels_of_the_wrong_size_are_named():
    camera = orbit_camera(20, 10)
    scene = random_scene(5, camera, n_features=2)
    with pytest.raises(ValueError, match=r"feature_pixels must be \[H, W\] = \[10, 20\]"):
        rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales,
                  features=scene.features, feature_pixels=torch.ones(20, 10, dtype=torch.bool))


def test_kernel_exp_matches_numpy_over_its_domain():
    """The kernels' branch-free exp (polynomial times 2^n built from its bits, ``pidg.kernel_math``) against
    numpy's: on the compositor's domain [-5.6, 0] (alpha and its gradient rest on it) and on the whole range the
    attention gate uses, down to where 2^n leaves the normal floats; below it the clamped form stays there."""
    import numpy as np
    from numba import njit

    from pidg.kernel_math import EXP_MIN_ARGUMENT, exp_nonpositive, exp_nonpositive_unclamped

    @njit
    def exp_all(x, clamped):
        out = np.empty_like(x)
        for i in range(x.shape[0]):
            out[i] = exp_nonpositive(x[i]) if clamped else exp_nonpositive_unclamped(x[i])
        return out

    for lo in (-5.6, EXP_MIN_ARGUMENT):
        x = np.linspace(lo, 0.0, 200_001).astype(np.float32)
        approx = exp_all(x, False).astype(np.float64)
        exact = np.exp(x.astype(np.float64))
        # further out the float32 rounding of x log2(e) adds up to |x| x 1e-7 (4e-6 measured at x = -87)
        bound = 5e-7 if lo == -5.6 else 5e-7 + 1e-7 * np.abs(x)
        assert np.all(np.abs(approx - exact) / exact < bound), lo
    # the exact powers of two at the reduction's break points: -k ln 2 -> 2^-k
    k = np.arange(0, 9)
    at_powers = exp_all((-k * math.log(2.0)).astype(np.float32), False).astype(np.float64)
    assert np.allclose(at_powers, 2.0 ** -k, rtol=5e-7, atol=0)
    far = exp_all(np.array([-100.0, -1e30, -np.inf], dtype=np.float32), True)
    assert np.all(far == exp_all(np.array([EXP_MIN_ARGUMENT], dtype=np.float32), False)[0]) and np.all(far < 1e-37)


def test_row_cull_never_drops_a_gaussian_that_reaches_the_row():
    """The compositor's per-row cull against a brute-force alpha at every pixel centre of the row: a Gaussian whose
    alpha reaches 1/255 at some pixel must be kept (the kernel skips the others), and the test is tight enough to
    drop most of those that do not reach the row."""
    import numpy as np

    from pidg.render.projection import ALPHA_MIN
    from pidg.render.rasterize_cpu import CULL_BLOCK, _cull_block, _fill_tile, _padded

    rng = np.random.default_rng(3)
    n, x_lo, lanes = 300, 32, 16
    means2d = np.stack([rng.uniform(x_lo - 20, x_lo + 36, n), rng.uniform(-20, 36, n)], axis=1).astype(np.float32)
    sigma = rng.uniform(0.3, 6.0, (n, 2))
    angle = rng.uniform(0, np.pi, n)
    c, s = np.cos(angle), np.sin(angle)
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0] = c * c * sigma[:, 0] ** 2 + s * s * sigma[:, 1] ** 2
    cov[:, 1, 1] = s * s * sigma[:, 0] ** 2 + c * c * sigma[:, 1] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = c * s * (sigma[:, 0] ** 2 - sigma[:, 1] ** 2)
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], axis=1).astype(np.float32)
    opacities = rng.uniform(0.01, 0.999, n).astype(np.float32)
    feats = np.zeros((n, 1), np.float32)
    table = np.empty((12, _padded(n)), np.float32)
    _fill_tile(means2d, conics, opacities, feats, np.zeros((n, 0), np.float32), np.arange(n, dtype=np.int64), 0, x_lo, 0,
               _padded(n), table, np.empty((n, 1), np.float32))
    misses, hits = np.empty(CULL_BLOCK, np.float32), np.empty(CULL_BLOCK, np.int64)
    px = x_lo + np.arange(lanes) + 0.5
    kept_total = reaching_total = 0
    for py in range(16):
        kept = set()
        for k0 in range(0, n, CULL_BLOCK):
            count = _cull_block(table, k0, n, np.float32(py + 0.5), lanes, misses, hits)
            kept.update(int(k) for k in hits[:count])
        dx = means2d[:, 0:1].astype(np.float64) - px[None, :]
        dy = means2d[:, 1:2].astype(np.float64) - (py + 0.5)
        a, b, cc = (conics[:, i:i + 1].astype(np.float64) for i in range(3))
        power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
        alpha = np.minimum(0.99, opacities[:, None] * np.exp(power))
        reaching = set(np.nonzero((alpha >= ALPHA_MIN * (1 + 1e-4)).any(axis=1))[0].tolist())
        assert reaching <= kept, f"row {py}: reaching Gaussians culled: {sorted(reaching - kept)[:5]}"
        kept_total, reaching_total = kept_total + len(kept), reaching_total + len(reaching)
    assert reaching_total > 100  # the scene does reach the rows
    assert kept_total < 1.1 * reaching_total and kept_total < 0.8 * 16 * n  # and the cull drops the rest


def test_a_tile_list_too_long_for_the_kernel_is_named(monkeypatch):
    """The kernel keeps a pixel's end in its tile's list as a float32 lane value (exact below 2^24): a longer list
    is refused with one line instead of rounding silently (shown here with the limit lowered to 5)."""
    import pidg.render.rasterize_cpu as rc

    camera = orbit_camera(16, 16)
    scene = random_scene(40, camera, pixel_sigma=(6.0, 8.0), extent=0.2, seed=1)
    monkeypatch.setattr(rc, "_MAX_TILE_LIST", 5)
    with pytest.raises(ValueError, match=r"composite_cpu: a tile holds \d+ Gaussians.*exact below 5"):
        render(scene, camera, "cpu")


def test_depth_order_is_a_stable_depth_sort():
    """The 64-bit-key sort of float32 depths equals numpy's stable argsort (ties in index order, negatives, inf),
    and float64 depths that round to the same float32 keep their true order."""
    import numpy as np

    from pidg.render.rasterize_cpu import depth_order

    rng = np.random.default_rng(0)
    depths = np.concatenate([rng.normal(size=500), rng.integers(0, 5, size=500), [np.inf, -np.inf, 1e-30]]).astype(np.float32)
    indices = np.nonzero(rng.random(depths.size) > 0.3)[0]
    expected = indices[np.argsort(depths[indices], kind="stable")]
    assert np.array_equal(depth_order(depths, indices), expected)
    close = np.array([1.0 + 1e-12, 1.0], dtype=np.float64)  # equal in float32
    assert depth_order(close, np.arange(2)).tolist() == [1, 0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bins_are_each_tiles_gaussians_front_to_back(dtype):
    """``bin_gaussians`` against a loop: tile t lists the visible Gaussians (both radii > 0) whose box touches it,
    by depth then index; Gaussian g's intersections sit at slots gauss_offsets[g]:gauss_offsets[g + 1], one per tile
    in row-major tile order. Centres off the image, zero radii and the projection's int32 radii included."""
    import numpy as np

    from pidg.render.rasterize_cpu import bin_gaussians

    gen = torch.Generator().manual_seed(5)
    n, width, height, ts = 300, 70, 45, 16
    means2d = (torch.rand(n, 2, generator=gen) * torch.tensor([width + 40.0, height + 40.0]) - 20.0).to(dtype)
    radii = torch.randint(0, 12, (n, 2), generator=gen, dtype=torch.int32)
    depths = torch.randint(1, 20, (n,), generator=gen).to(torch.float32)  # ties: index order decides
    bins = bin_gaussians(means2d, radii, depths, width, height, ts)
    tiles_x, tiles_y = -(-width // ts), -(-height // ts)
    m, r = means2d.double().numpy(), radii.numpy()
    lists = [[] for _ in range(tiles_x * tiles_y)]
    for g in sorted(range(n), key=lambda g: (float(depths[g]), g)):
        if r[g, 0] <= 0 or r[g, 1] <= 0:
            continue
        x0, x1 = max(0, math.floor((m[g, 0] - r[g, 0]) / ts)), min(tiles_x - 1, math.floor((m[g, 0] + r[g, 0]) / ts))
        y0, y1 = max(0, math.floor((m[g, 1] - r[g, 1]) / ts)), min(tiles_y - 1, math.floor((m[g, 1] + r[g, 1]) / ts))
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                lists[ty * tiles_x + tx].append(g)
    got = [bins.isect_ids[bins.tile_offsets[t]:bins.tile_offsets[t + 1]].tolist() for t in range(tiles_x * tiles_y)]
    assert got == lists and any(len(x) > 1 for x in lists)
    slots = np.sort(bins.slot_of_isect)
    assert np.array_equal(slots, np.arange(bins.num_intersections))  # every slot once
    for g in range(n):  # a Gaussian's slots hold its own intersections
        mine = np.nonzero(bins.isect_ids == g)[0]
        assert sorted(bins.slot_of_isect[mine].tolist()) == list(range(bins.gauss_offsets[g], bins.gauss_offsets[g + 1]))


def test_finish_image_is_the_torch_arithmetic():
    """``finish_image_cpu`` (rgb over the background and depth as separate arrays, in one pass): its outputs and the
    gradients of image and alpha equal the torch form's, whichever outputs a loss reads (autograd sends None for the
    others, which count as zeros)."""
    from pidg.render.rasterize_cpu import finish_image_cpu

    gen = torch.Generator().manual_seed(0)
    image = torch.rand(9, 13, 4, generator=gen)
    alpha = torch.rand(9, 13, generator=gen)
    background = torch.tensor([1.0, 0.25, 0.5])
    for read in [(True, True), (True, False), (False, True)]:
        results = []
        for kernel in (False, True):
            x, a = image.clone().requires_grad_(True), alpha.clone().requires_grad_(True)
            if kernel:
                outputs = finish_image_cpu(x, a, background)
            else:
                colour, depth = x.split([3, 1], dim=-1)
                outputs = (colour + (1.0 - a).unsqueeze(-1) * background, depth.squeeze(-1))
            weights = torch.Generator().manual_seed(1)
            loss = sum((o * torch.randn(o.shape, generator=weights)).sum() for o, r in zip(outputs, read) if r)
            (loss + a.square().sum()).backward()  # alpha also reaches the loss directly, as the renders' alpha does
            results.append([o.detach() for o in outputs] + [x.grad, a.grad])
        for name, ref, got in zip(["rgb", "depth", "d image", "d alpha"], *results):
            assert got.shape == ref.shape, name
            torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-6, msg=name)
    with pytest.raises(ValueError, match="float32 CPU"):
        finish_image_cpu(image.double(), alpha.double(), background.double())
    with pytest.raises(ValueError, match=r"\[H, W, 4\]"):
        finish_image_cpu(torch.rand(9, 13, 7), alpha, background)


@pytest.mark.parametrize("tile_size", [16, 8, 5])
def test_tiles_touched_are_the_tiles_holding_a_pixel(tile_size):
    """Against a loop over the tiles, on an image whose last tile row and column are partial; sizes a multiple of 8
    read a tile row as int64 words, the others as bools."""
    from pidg.render.projection import tiles_touched

    gen = torch.Generator().manual_seed(3)
    pixels = torch.rand(37, 50, generator=gen) > 0.995
    pixels[36, 49] = True  # the partial corner tile
    pixels[17, 8] = True  # the first pixel of the second word of a 16-wide tile's row
    expected = torch.tensor([[bool(pixels[y:y + tile_size, x:x + tile_size].any()) for x in range(0, 50, tile_size)]
                             for y in range(0, 37, tile_size)])
    assert expected.sum() < expected.numel()  # some tiles are empty
    assert torch.equal(tiles_touched(pixels, tile_size), expected)
    # whole tiles (F.pad returns the input itself) of a view: strided, at an odd offset in its storage
    whole = torch.zeros(49, 81, dtype=torch.bool)
    whole[1:, 1:] = torch.rand(48, 80, generator=gen) > 0.995
    assert torch.equal(tiles_touched(whole[1:, 1:], tile_size), tiles_touched(whole[1:, 1:].clone(), tile_size))
    assert torch.equal(tiles_touched(whole[1:, 1:], 16), whole[1:, 1:].reshape(3, 16, 5, 16).any(3).any(1))


@pytest.mark.parametrize("tile_size", [16, 5])
def test_tile_rows_touched_are_the_tile_rows_holding_a_pixel(tile_size):
    """Against a loop over each image row's tiles, on an image whose last tile column is partial."""
    from pidg.render.projection import tile_rows_touched

    pixels = torch.rand(37, 50, generator=torch.Generator().manual_seed(5)) > 0.98
    pixels[36, 49] = True  # the partial last tile's row
    expected = torch.tensor([[bool(pixels[y, x:x + tile_size].any()) for x in range(0, 50, tile_size)] for y in range(37)])
    assert 0 < expected.sum() < expected.numel()
    assert torch.equal(tile_rows_touched(pixels, tile_size), expected)


@pytest.mark.parametrize("workers", [1, 3])
def test_the_kernels_give_the_same_bits_for_any_number_of_workers(monkeypatch, workers):
    """Tiles are dealt round-robin to the workers (``kernel_math.round_robin_workers``); each tile is computed whole by
    one worker, so the render, its gradients and the set of Gaussians reaching some pixels do not depend on how many
    there are (here 1 or 3 against the machine's count)."""
    import pidg.render.rasterize_cpu as rasterize_cpu
    from pidg.render.api import gaussians_reaching, prepare_render

    camera = orbit_camera(70, 38, azimuth_deg=30.0)
    scene = hard_scene(camera, 400, torch.float32)
    pixels = torch.zeros(38, 70, dtype=torch.bool)
    pixels[5:30:4, 3:60:5] = True

    def run():
        params = [t.detach().clone().requires_grad_(True) for t in scene.params()]
        out = render(GaussianScene(*params), camera, "cpu")
        scalar_loss(out).backward()
        screen = prepare_render(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, backend="cpu")
        reaching = gaussians_reaching(screen, pixels)
        return [out.rgb.detach(), out.alpha.detach(), out.features.detach(), reaching, *(p.grad for p in params)]

    default = run()
    monkeypatch.setattr(rasterize_cpu, "round_robin_workers", lambda: workers)
    for a, b in zip(default, run(), strict=True):
        assert torch.equal(a, b)
