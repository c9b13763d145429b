"""Random Gaussian scenes with controlled screen-space sizes, for tests, benchmarks and the demo."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.render.camera import Camera


@dataclass
class GaussianScene:
    """Plain rasterizer inputs (linear scales, opacities in [0, 1], RGB or SH colours)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    features: Tensor | None = None

    def params(self) -> list[Tensor]:
        return [t for t in (self.means, self.quats, self.scales, self.opacities, self.colors, self.features) if t is not None]

    def requires_grad_(self) -> "GaussianScene":
        for t in self.params():
            t.requires_grad_(True)
        return self


def orbit_camera(
    width: int, height: int, fov_x_deg: float = 60.0, distance: float = 4.0, azimuth_deg: float = 0.0, elevation: float = 0.6
) -> Camera:
    """Camera on a horizontal circle around the origin at height ``elevation``, looking at it (world z up)."""
    az = math.radians(azimuth_deg)
    eye = (distance * math.sin(az), -distance * math.cos(az), elevation)
    return Camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width, height, math.radians(fov_x_deg))


def random_scene(
    n: int,
    camera: Camera,
    pixel_sigma: tuple[float, float] = (0.7, 10.0),
    opacity: tuple[float, float] = (0.1, 0.98),
    extent: float = 1.0,
    n_features: int = 0,
    sh_degree: int | None = None,
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
) -> GaussianScene:
    """``n`` Gaussians uniform in a cube of half-size ``extent`` around the origin.

    World scales are chosen so that each Gaussian's projected standard deviation is log-uniform in
    ``pixel_sigma`` (pixels) for ``camera``: realistic footprints whatever the resolution.
    """
    gen = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * extent
    w2c = camera.world_to_camera.to(torch.float64)
    z = (means @ w2c[:3, :3].T + w2c[:3, 3])[:, 2].clamp_min(1e-3)
    lo, hi = math.log(pixel_sigma[0]), math.log(pixel_sigma[1])
    sigma_px = torch.exp(lo + (hi - lo) * torch.rand(n, generator=gen, dtype=torch.float64))
    anisotropy = 0.4 + 1.2 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    scales = (sigma_px * z / camera.fx).unsqueeze(-1) * anisotropy
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    opac = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=gen, dtype=torch.float64)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    else:
        colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=torch.float64)
    feats = torch.randn(n, n_features, generator=gen, dtype=torch.float64) if n_features else None
    cast = lambda t: None if t is None else t.to(dtype)  # noqa: E731
    return GaussianScene(cast(means), cast(quats), cast(scales), cast(opac), cast(colors), cast(feats))

