"""``rasterize``: Gaussians + camera (+ optional feature channels) in, images out.

The render core knows nothing of time, physics or datasets. Extra per-Gaussian feature channels [N, C] are
composited with the same weights as colour in the same pass (later: Gaussian flow and velocity flow).
"""
from __future__ import annotations

import dataclasses
from typing import Literal, get_args

import torch
from torch import Tensor

from pidg.errors import NonFiniteError, all_finite
from pidg.render.camera import Camera
from pidg.render.output import RenderOutput
from pidg.render.projection import TILE_SIZE, Projection, project_gaussians, tile_rows_touched
from pidg.render.projection_cpu import project_and_shade_cpu
from pidg.render.footprint import footprints_touching
from pidg.render.rasterize_cpu import TileBins, bin_gaussians, composite_cpu, finish_image_cpu, gaussians_reaching_cpu
from pidg.render.rasterize_gsplat import rasterize_gsplat
from pidg.render.rasterize_torch import channels_below, composite_reference
from pidg.render.sh import sh_to_rgb

#: Which compositor renders: "cpu" (numba kernel), "torch" (reference), "gsplat" (CUDA), "auto" (by device).
RenderBackend = Literal["auto", "cpu", "torch", "gsplat"]


def _opacity_vector(opacities: Tensor) -> Tensor:
    """Opacities as [N]: the renderers also take the [N, 1] column a model stores (anything else is left for
    ``_check_inputs`` to name)."""
    if isinstance(opacities, Tensor) and opacities.dim() == 2 and opacities.shape[-1] == 1:
        return opacities.squeeze(-1)
    return opacities


def _check_inputs(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, background: Tensor | None,
    sh_degree: int | None, camera: Camera,
) -> None:
    """Fail early, with the name of the offending input, on the mistakes that otherwise give garbage images."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    for name, t in named.items():
        if not isinstance(t, Tensor):
            raise TypeError(f"rasterize: {name} must be a torch.Tensor, got {type(t).__name__}")
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterize: means must have shape [N, 3], got {list(means.shape)}")
    n = means.shape[0]
    expected = {"quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"rasterize: {name} must have shape {list(shape)}, got {list(named[name].shape)}")
    if sh_degree is None:
        if tuple(colors.shape) != (n, 3):
            raise ValueError(f"rasterize: colors must be RGB [N, 3] = [{n}, 3] (or SH [N, K, 3] with sh_degree), got {list(colors.shape)}")
    else:
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[2] != 3 or colors.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(
                f"rasterize: with sh_degree={sh_degree} colors must be SH coefficients [N, K>={(sh_degree + 1) ** 2}, 3],"
                f" got {list(colors.shape)}"
            )
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"rasterize: means must be float32 or float64, got {dtype}")
    for name, t in named.items():
        _check_like_means(name, t, means)
    if (scales < 0).any():
        raise ValueError("rasterize: scales must be non-negative (pass log_scales= for log-space scales)")
    if (quats.norm(dim=-1) == 0).any():
        raise ValueError("rasterize: a quaternion has zero norm")
    if background is not None and (tuple(background.shape) != (3,) or not torch.isfinite(background).all()):
        raise ValueError(f"rasterize: background must be a finite RGB tensor of shape [3], got {list(background.shape)}")


def _check_like_means(name: str, t: Tensor, means: Tensor) -> None:
    """``t`` has the dtype and device of ``means`` and holds finite values only."""
    if t.dtype != means.dtype:
        raise TypeError(f"rasterize: {name} has dtype {t.dtype} but means has {means.dtype}; use one float dtype")
    if t.device != means.device:
        raise ValueError(f"rasterize: {name} is on {t.device} but means is on {means.device}")
    if not all_finite(t.detach()):
        bad = (~torch.isfinite(t)).reshape(t.shape[0], -1).any(dim=1).nonzero()[:5].flatten().tolist()
        raise NonFiniteError(f"rasterize: {name} contains NaN or infinite values (first bad Gaussians: {bad})")


def _check_features(features: Tensor, means: Tensor) -> None:
    if not isinstance(features, Tensor):
        raise TypeError(f"rasterize: features must be a torch.Tensor, got {type(features).__name__}")
    n = means.shape[0]
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"rasterize: features must have shape [N, C] = [{n}, C], got {list(features.shape)}")
    _check_like_means("features", features, means)


def resolve_backend(backend: RenderBackend, device: torch.device) -> Literal["cpu", "torch", "gsplat"]:
    """Pick the backend: gsplat for CUDA tensors, the numba kernel on CPU; the torch reference on request (any
    device: it is plain torch, the readable and slow path)."""
    if backend == "auto":
        return "gsplat" if device.type == "cuda" else "cpu"
    if backend not in get_args(RenderBackend):
        raise ValueError(f"rasterize: unknown backend '{backend}' ({', '.join(get_args(RenderBackend))})")
    if backend == "cpu" and device.type != "cpu":
        raise ValueError(f"rasterize: backend 'cpu' (the numba kernel) runs on CPU tensors, got tensors on {device}")
    if backend == "gsplat" and device.type != "cuda":
        raise ValueError("rasterize: the gsplat backend needs CUDA tensors")
    return backend  # type: ignore[return-value]


def feature_row_channels(feature_pixels: Tensor, always: int, n_features: int, tile_size: int = TILE_SIZE) -> Tensor:
    """[H, tiles_x] channels each tile row (a tile's pixels on one image row) composites: ``always + n_features``
    in the tile rows that hold a pixel of ``feature_pixels`` [H, W] (bool), ``always`` in the others."""
    return torch.where(tile_rows_touched(feature_pixels, tile_size), always + n_features, always)


def project(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: Camera, backend: RenderBackend = "auto"
) -> Projection:
    """The projection ``rasterize`` uses with the same ``backend`` (``project_gaussians``; the numba kernel for float32
    tensors on the cpu backend), for callers that need screen-space Gaussians of their own (Gaussian flow,
    footprints)."""
    if resolve_backend(backend, means.device) == "cpu" and means.dtype == torch.float32:
        return project_and_shade_cpu(means, quats, scales, opacities, means.new_zeros(means.shape[0], 3), camera, None)[0]
    return project_gaussians(means, quats, scales, opacities, camera)


@dataclasses.dataclass
class PreparedRender:
    """A render's first stage, for one camera: the Gaussians checked, projected and coloured (differentiable; on the
    cpu backend also binned into tiles, once, when first asked), before any feature channel is composited.
    :func:`composite` finishes it. A loss that must know which Gaussians reach some pixels before it makes their
    channels asks it (:func:`gaussians_reaching`) instead of projecting and binning the same Gaussians again."""

    backend: Literal["cpu", "torch", "gsplat"]
    camera: Camera  # on the Gaussians' device
    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3], linear
    opacities: Tensor  # [N]
    rgb: Tensor  # [N, 3] each Gaussian's colour seen from this camera (SH evaluated)
    background: Tensor  # [3]
    tile_size: int
    projection: Projection | None  # None on gsplat, which projects inside its own call
    _bins: TileBins | None = None

    @property
    def bins(self) -> TileBins:
        """The cpu compositor's depth-sorted tile lists (computed on first use, then shared)."""
        if self.backend != "cpu" or self.projection is None:
            raise ValueError(f"PreparedRender.bins: tile lists belong to the cpu backend, this render uses {self.backend}")
        if self._bins is None:
            proj = self.projection
            self._bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, self.camera.width, self.camera.height, self.tile_size)
        return self._bins


def prepare_render(
    means: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    camera: Camera,
    *,
    scales: Tensor | None = None,
    log_scales: Tensor | None = None,
    background: Tensor | None = None,
    sh_degree: int | None = None,
    backend: RenderBackend = "auto",
    tile_size: int = TILE_SIZE,
) -> PreparedRender:
    """:func:`rasterize`'s first stage (same arguments, without the feature channels)."""
    if (scales is None) == (log_scales is None):
        raise ValueError("rasterize: pass exactly one of scales= or log_scales=")
    opacities = _opacity_vector(opacities)
    lin_scales = scales if scales is not None else torch.exp(log_scales)  # type: ignore[arg-type]
    _check_inputs(means, quats, lin_scales, opacities, colors, background, sh_degree, camera)
    which = resolve_backend(backend, means.device)
    camera = camera.to(means.device)
    bg = background.to(means.dtype) if background is not None else means.new_zeros(3)
    proj: Projection | None = None
    if which == "cpu" and means.dtype == torch.float32:  # projection and colour as one numba kernel
        proj, rgb = project_and_shade_cpu(means, quats, lin_scales, opacities, colors, camera, sh_degree)
    else:
        rgb = colors if sh_degree is None else sh_to_rgb(colors, means - camera.camera_center.to(means.dtype), sh_degree)
        if which != "gsplat":
            proj = project_gaussians(means, quats, lin_scales, opacities, camera)
    if proj is not None and proj.means2d.requires_grad:
        proj.means2d.retain_grad()  # the view-space positional gradient densification reads
    return PreparedRender(which, camera, means, quats, lin_scales, opacities, rgb, bg, tile_size, proj)


@torch.no_grad()
def gaussians_reaching(screen: PreparedRender, pixels: Tensor) -> Tensor:
    """[N] bool: the Gaussians of a prepared render that can add to a pixel of ``pixels`` [H, W] (bool) once it is
    composited, so a loss on those pixels can skip the others' per-Gaussian work. On the cpu backend (float32) the
    set is exact, the compositor's own weights on its own tile lists (hidden and too faint Gaussians are left out:
    ``gaussians_reaching_cpu``); elsewhere it is the footprint boxes' superset (``footprints_touching``). Either way
    the others add exactly nothing at those pixels."""
    pixels = pixels.to(screen.means.device)
    proj = screen.projection
    if proj is None:  # gsplat projects inside its own call: the torch projection of the same Gaussians
        proj = project_gaussians(screen.means, screen.quats, screen.scales, screen.opacities, screen.camera)
    if screen.backend != "cpu" or proj.means2d.dtype != torch.float32:
        return footprints_touching(proj.means2d, proj.radii, pixels)
    return gaussians_reaching_cpu(
        proj.means2d, proj.conics, screen.opacities, proj.depths, proj.radii, pixels, screen.tile_size, bins=screen.bins
    )


def composite(screen: PreparedRender, features: Tensor | None = None, feature_pixels: Tensor | None = None) -> RenderOutput:
    """:func:`rasterize`'s second stage: composite a prepared render, with extra feature channels [N, C] (and
    ``feature_pixels`` [H, W]) as ``rasterize`` takes them."""
    camera, means, which, tile_size = screen.camera, screen.means, screen.backend, screen.tile_size
    if features is not None:
        _check_features(features, means)
    if feature_pixels is not None:
        if tuple(feature_pixels.shape) != (camera.height, camera.width):
            raise ValueError(f"rasterize: feature_pixels must be [H, W] = [{camera.height}, {camera.width}], got {list(feature_pixels.shape)}")
        feature_pixels = feature_pixels.to(device=means.device, dtype=torch.bool)
    bg, opacities = screen.background, screen.opacities
    if which == "gsplat":
        out = rasterize_gsplat(means, screen.quats, screen.scales, opacities, screen.rgb, camera, features, bg)
        if feature_pixels is not None and out.features is not None:
            n_feat = out.features.shape[-1]
            kept = channels_below(feature_row_channels(feature_pixels, 0, n_feat, tile_size), n_feat, camera.width, camera.height, tile_size)
            out = dataclasses.replace(out, features=out.features * kept.to(out.features.dtype))
        return out
    proj = screen.projection
    assert proj is not None
    n_feat = 0 if features is None else features.shape[1]
    channels = [screen.rgb, proj.depths.unsqueeze(-1)] + ([features] if features is not None else [])
    per_gaussian = torch.cat(channels, dim=-1)  # [N, 3 + 1 + C]: colour, depth and features in one pass
    row_channels = None
    if feature_pixels is not None and n_feat:
        row_channels = feature_row_channels(feature_pixels, 4, n_feat, tile_size)  # colour and depth everywhere
    # colour and depth into the image, the features into an image of their own (``extra``)
    args = (proj.means2d, proj.conics, opacities, per_gaussian, proj.depths, proj.radii, camera.width, camera.height, tile_size, row_channels)
    if which == "cpu":
        image, alpha, extra = composite_cpu(*args, image_channels=4, bins=screen.bins)
    else:
        image, alpha, extra = composite_reference(*args, image_channels=4)
    if which == "cpu" and image.dtype == torch.float32 and not bg.requires_grad:
        rgb, depth = finish_image_cpu(image, alpha, bg)  # the lines below as one numba pass
    else:
        # split, not sliced: each slice's backward fills a zero gradient of the whole image (measured 9 ms of a step)
        colour, depth = image.split([3, 1], dim=-1)
        rgb = colour + (1.0 - alpha).unsqueeze(-1) * bg
        depth = depth.squeeze(-1)
    return RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=depth,
        features=extra if n_feat else None,
        means2d=proj.means2d,
        radii=proj.radii,
        depths=proj.depths,
    )


def rasterize(
    means: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    camera: Camera,
    *,
    scales: Tensor | None = None,
    log_scales: Tensor | None = None,
    features: Tensor | None = None,
    background: Tensor | None = None,
    sh_degree: int | None = None,
    backend: RenderBackend = "auto",
    tile_size: int = TILE_SIZE,
    feature_pixels: Tensor | None = None,
) -> RenderOutput:
    """Render N Gaussians into one camera (:func:`prepare_render`, then :func:`composite`).

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z; need not be normalised), opacities [N] in [0, 1].
        scales [N, 3] (linear) or log_scales [N, 3]: exactly one of the two.
        colors: RGB [N, 3], or SH coefficients [N, K, 3] together with ``sh_degree`` (0..3).
        features: optional extra channels [N, C]; cost is linear in C and negligible for C = 0.
        background: RGB [3] composited behind the Gaussians (default black).
        backend: "cpu" (numba kernels: projection and colour, then compositing; float32 inputs, float64 ones take
            the torch projection), "torch" (reference), "gsplat" (CUDA), or "auto".
        feature_pixels: optional [H, W] bool, the pixels whose ``features`` the caller reads: the features are
            composited only in the tile rows (a 16x16 tile's pixels on one image row, the compositor's unit of
            work) that hold one of them and are 0 elsewhere, so a loss on a few pixels pays for their rows only (on
            the cpu backend; the others compute all and zero the rest).
    """
    screen = prepare_render(
        means, quats, opacities, colors, camera, scales=scales, log_scales=log_scales, background=background,
        sh_degree=sh_degree, backend=backend, tile_size=tile_size,
    )
    return composite(screen, features, feature_pixels)
