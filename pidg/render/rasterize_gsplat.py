"""CUDA backend: a thin adapter over gsplat's documented ``gsplat.rasterization`` (gsplat >= 1.4).

Colours arrive already evaluated (SH is done in torch by the caller) and are concatenated with the extra feature
channels into gsplat's N-D colours; ``render_mode="RGB+D"`` appends the accumulated depth sum_i w_i z_i, the same
quantity the CPU backends return. The background is added here, not by gsplat, so feature channels stay
background-free exactly as on CPU. Same conventions as ours: OpenCV world-to-camera, pixel centres at +0.5,
0.3 px^2 dilation ("classic" mode), alpha >= 1/255.

Densification reads the view-space positional gradient where gsplat's backward writes it: ``meta["means2d"]``
[1, N, 2] (``packed=False`` keeps it aligned with our Gaussian indices), in pixels like the CPU path's.

gsplat compiles its CUDA code on a process's first use, deleting and rebuilding one shared build folder, so two
processes that start at once break each other's build. Every first use through pidg (this adapter, and the
run's check before training) renders one Gaussian while holding an inter-process lock, :data:`GSPLAT_BUILD_LOCK`.
"""
from __future__ import annotations

import contextlib
import fcntl
import functools
import tempfile
from pathlib import Path

import torch
from torch import Tensor

from pidg.errors import DeviceUnavailable
from pidg.render.camera import Camera
from pidg.render.output import RenderOutput

GSPLAT_MISSING = "the gsplat backend needs `pip install gsplat` (CUDA only)"
GSPLAT_BUILD_LOCK = Path(tempfile.gettempdir()) / "pidg-gsplat-build.lock"


@contextlib.contextmanager
def _exclusive(path: Path):
    """An inter-process lock (flock) held for the block."""
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@functools.cache
def gsplat_load_error(device: torch.device) -> str | None:
    """Why gsplat cannot render on ``device`` (None when it can), found by rendering one Gaussian through its
    documented ``rasterization`` while holding :data:`GSPLAT_BUILD_LOCK` (the first use builds its CUDA code: about a
    minute on 16 cores). A build that fails (compiler, CUDA toolkit) would otherwise surface as an ImportError in the
    middle of the work."""
    try:
        with _exclusive(GSPLAT_BUILD_LOCK):
            _render_one_gaussian(device)
    except Exception as err:  # noqa: BLE001  (any failure of the third-party build is reported, with its type)
        return f"{type(err).__name__}: {str(err).strip().splitlines()[-1] if str(err).strip() else 'no message'}"
    return None


def require_gsplat(device: torch.device) -> None:
    """Raise :class:`DeviceUnavailable`, naming the reason, unless gsplat renders on ``device`` (see
    :func:`gsplat_load_error`)."""
    error = gsplat_load_error(device)
    if error is not None:
        raise DeviceUnavailable(
            f"gsplat is installed but cannot render on {device} ({error}): see gsplat's install notes for its CUDA "
            "build, or use --backend torch for the slow reference compositor"
        )


def _render_one_gaussian(device: torch.device) -> None:
    from gsplat import rasterization

    one = torch.ones(1, device=device)
    rasterization(
        means=torch.tensor([[0.0, 0.0, 2.0]], device=device), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device),
        scales=one.expand(1, 3) * 0.1, opacities=one * 0.5, colors=one.expand(1, 3), viewmats=torch.eye(4, device=device)[None],
        Ks=torch.tensor([[[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]], device=device), width=8, height=8,
    )


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
    if means.is_cuda:  # the process's first use builds gsplat's CUDA code under the lock; later calls: a cache lookup
        require_gsplat(means.device)

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
