"""CUDA backend: a thin adapter over gsplat's documented ``gsplat.rasterization`` (gsplat >= 1.4).

Colours arrive already evaluated (SH is done in torch by the caller) and are concatenated with the extra feature
channels into gsplat's N-D colours; ``render_mode="RGB+D"`` appends the accumulated depth sum_i w_i z_i, the same
quantity the CPU backends return. The background is added here, not by gsplat, so feature channels stay
background-free exactly as on CPU. Same conventions as ours: OpenCV world-to-camera, pixel centres at +0.5,
0.3 px^2 dilation ("classic" mode), alpha >= 1/255.

Densification reads the view-space positional gradient where gsplat's backward writes it: ``meta["means2d"]``
[1, N, 2] (``packed=False`` keeps it aligned with our Gaussian indices), in pixels like the CPU path's.
"""
from __future__ import annotations

import torch
from torch import Tensor

from pidg.render.camera import Camera
from pidg.render.output import RenderOutput

GSPLAT_MISSING = "the gsplat backend needs `pip install gsplat` (CUDA only)"


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device is present."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    rgb: Tensor,
    camera: Camera,
    features: Tensor | None,
    background: Tensor,
) -> RenderOutput:
    """Render with gsplat on CUDA; outputs match ``rasterize`` on CPU (see module docstring)."""
    try:
        from gsplat import rasterization
    except ImportError as err:  # depends on the install; the trainer checks before it starts
        raise ImportError(GSPLAT_MISSING) from err

    n_feat = 0 if features is None else features.shape[1]
    colors = rgb if features is None else torch.cat([rgb, features], dim=-1)
    viewmat = camera.world_to_camera.to(means.device, means.dtype)[None]
    ks = camera.intrinsics.to(means.device, means.dtype)[None]
    renders, alphas, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmat,
        Ks=ks,
        width=camera.width,
        height=camera.height,
        near_plane=camera.near,
        far_plane=camera.far,
        eps2d=0.3,
        sh_degree=None,
        packed=False,  # per-Gaussian [1, N, ...] outputs, aligned with our indices
        tile_size=16,
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    image, alpha = renders[0], alphas[0, ..., 0]
    source = meta["means2d"]  # [1, N, 2]: gsplat's backward writes the positional gradient here
    if source.requires_grad:
        source.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 1:  # gsplat < 1.5 returns one isotropic radius per Gaussian
        radii = radii.unsqueeze(-1).expand(-1, 2)
    return RenderOutput(
        rgb=image[..., :3] + (1.0 - alpha).unsqueeze(-1) * background,
        alpha=alpha,
        depth=image[..., -1],
        features=image[..., 3 : 3 + n_feat] if n_feat else None,
        means2d=source[0],
        radii=radii.to(torch.int32),
        depths=meta["depths"][0],
        means2d_source=source,
    )
