"""The projection + SH colour kernel against its torch reference (project_gaussians, sh_to_rgb): values, culling,
radii and every gradient, including the cases where the reference passes none (culled rows, clamped tangent,
clamped colour)."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import pidg  # noqa: F401
from pidg.render import Camera, rasterize
from pidg.render.projection import project_gaussians
from pidg.render.projection_cpu import project_and_shade_cpu
from pidg.render.sh import sh_to_rgb


def camera(width: int = 50, height: int = 34) -> Camera:
    cam = Camera.look_at((0.6, -3.5, 1.1), (0.0, 0.1, 0.0), (0.0, 0.0, 1.0), width, height, math.radians(60.0))
    return dataclasses.replace(cam, cx=cam.cx + 3.7, cy=cam.cy - 2.2)  # off-centre principal point


def gaussians(n: int, seed: int, sh_degree: int | None) -> list[torch.Tensor]:
    """Random Gaussians with every culling case: behind the camera, beyond the image, transparent, very oblique
    (clamped tangent), flat (degenerate scale), and colours whose SH sum goes below -1/2 (clamped)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 1.2
    means[:5] = torch.tensor([0.6, -5.0, 1.1])  # behind the camera
    means[5:10, 0] = 25.0  # far outside the view: clamped tangent, off-screen
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.2 + 0.01
    scales[10:13, 2] = 1e-7  # flat
    opacities = torch.rand(n, generator=g)
    opacities[13:16] = 1e-3  # below 1/255
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g)
    else:
        colors = torch.randn(n, 16, 3, generator=g) * 0.6
    return [means, quats, scales, opacities, colors]


def reference(means, quats, scales, opacities, colors, cam, sh_degree):
    proj = project_gaussians(means, quats, scales, opacities, cam)
    rgb = colors if sh_degree is None else sh_to_rgb(colors, means - cam.camera_center.to(means.dtype), sh_degree)
    return proj, rgb


@pytest.mark.parametrize("sh_degree", [None, 0, 1, 2, 3])
def test_kernel_values_and_gradients_equal_the_torch_reference(sh_degree):
    cam = camera()
    base = gaussians(400, seed=3 + (sh_degree or 0), sh_degree=sh_degree)
    weights = [torch.randn(400, k, generator=torch.Generator().manual_seed(k)) for k in (2, 3, 1, 3, 3)]
    results = []
    for fn in (reference, project_and_shade_cpu):
        params = [t.clone().requires_grad_(True) for t in base]
        proj, rgb = fn(*params, cam, sh_degree)
        outputs = (proj.means2d, proj.conics, proj.depths[:, None], proj.cov2d, rgb)
        # a loss that weighs every output, so every gradient path is exercised
        loss = sum((o * w).sum() for o, w in zip(outputs, weights))
        loss.backward()
        grads = [p.grad for p in params]
        results.append((proj, rgb, grads))
    (ref, ref_rgb, ref_grads), (ker, ker_rgb, ker_grads) = results
    assert torch.equal(ker.radii, ref.radii)
    assert int((ref.radii > 0).all(-1).sum()) > 200 and int((ref.radii == 0).all(-1).sum()) >= 16
    for name in ("means2d", "conics", "depths", "cov2d"):
        torch.testing.assert_close(getattr(ker, name), getattr(ref, name), rtol=2e-5, atol=1e-5, msg=name)
    torch.testing.assert_close(ker_rgb, ref_rgb, rtol=1e-5, atol=1e-6)
    if sh_degree is not None:
        assert (ref_rgb == 0).any()  # the colour clamp is exercised
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), ker_grads, ref_grads):
        if name == "opacities":
            assert a is None or not a.any()
            continue
        if sh_degree is None and name == "colors":
            torch.testing.assert_close(a, b)
            continue
        scale = float(b.abs().max())
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * scale, msg=name)


def test_rasterize_on_the_cpu_backend_matches_the_torch_backend_with_gradients():
    cam = camera(40, 30)
    base = gaussians(300, seed=11, sh_degree=3)
    base[0] = base[0] * 0.5
    features = torch.rand(300, 2, generator=torch.Generator().manual_seed(2))
    outs = {}
    for backend in ("torch", "cpu"):
        means, quats, scales, opacities, colors = [t.clone().requires_grad_(True) for t in base]
        out = rasterize(means, quats, opacities.detach(), colors, cam, log_scales=scales.log(), features=features,
                        sh_degree=3, backend=backend)
        (out.rgb.square().sum() + out.depth.sum() + out.features.sum()).backward()
        outs[backend] = (out, [means.grad, quats.grad, scales.grad, colors.grad], out.means2d_grad())
    (a, ga, ma), (b, gb, mb) = outs["torch"], outs["cpu"]
    torch.testing.assert_close(b.rgb, a.rgb, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(b.depth, a.depth, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(mb, ma, rtol=1e-3, atol=1e-4 * float(ma.abs().max()))  # densification's statistic
    for x, y in zip(gb, ga):
        torch.testing.assert_close(x, y, rtol=1e-3, atol=1e-3 * float(y.abs().max()))


def test_a_huge_gaussian_keeps_finite_gradients():
    """A Gaussian scaled ~1e8 (a deformation that ran away early in a run) overflows float32's det(cov2d): its
    conic is 0 and its radius the cap. Its gradients must stay finite: exactly zero where none reaches it (that
    case returned NaN and rolled runs back), and the float64 reference's where its centre is supervised."""
    cam = camera()
    means = torch.tensor([[0.0, 0.1, 0.0], [0.2, 0.0, 0.1]])
    quats = torch.tensor([[0.9, 0.1, -0.3, 0.2], [1.0, 0.0, 0.0, 0.0]])
    scales = torch.tensor([[1e8, 3e7, 6e8], [0.1, 0.1, 0.1]])
    opacities = torch.tensor([0.5, 0.5])
    colors = torch.rand(2, 3, generator=torch.Generator().manual_seed(0))
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    proj, _ = project_and_shade_cpu(*params, cam, None)
    assert torch.isfinite(proj.conics).all() and proj.radii[0].tolist() == [2**30, 2**30]
    (proj.means2d[1].sum() + proj.conics[1].sum()).backward()  # only the ordinary Gaussian is supervised
    for p in params[:3]:
        assert torch.isfinite(p.grad).all()
        assert (p.grad[0] == 0).all()

    grads = []
    for fn, dtype in ((reference, torch.float64), (project_and_shade_cpu, torch.float32)):
        params = [t.to(dtype).clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        proj, _ = fn(*params, cam, None)
        (proj.means2d[0].sum() + proj.depths[0] + proj.conics[0].sum()).backward()
        grads.append([p.grad[0].double() for p in params[:3]])
    for ref, kernel in zip(*grads):
        assert torch.isfinite(kernel).all()
        torch.testing.assert_close(kernel, ref, rtol=1e-4, atol=1e-6)
