"""What a render returns: images and the per-Gaussian projection results (one type for every backend)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pidg.kernel_math import quotient_where_at_least

# A pixel's expected depth counts only where the render is mostly opaque: half-transparent pixels mix foreground and
# background depths, and empty ones have none. Shared by the flow target, the depth loss and generated depth maps.
OPAQUE_ALPHA = 0.5


@dataclass
class RenderOutput:
    """Images [H, W, ...] and the per-Gaussian projection results densification needs."""

    rgb: Tensor  # [H, W, 3], background included
    alpha: Tensor  # [H, W] accumulated opacity
    depth: Tensor  # [H, W] alpha-composited camera depth, sum_i w_i z_i (0 where nothing is drawn)
    features: Tensor | None  # [H, W, C] extra channels composited with the same weights (no background)
    means2d: Tensor  # [N, 2] pixel coordinates; its .grad after backward is the view-space positional gradient
    radii: Tensor  # [N, 2] int32 pixel half-extents, 0 for culled Gaussians
    depths: Tensor  # [N] camera-space z of the centres
    # The tensor backward writes the means2d gradient into, when it is not ``means2d`` itself: gsplat returns
    # [1, N, 2] and its backward fills that tensor, of which ``means2d`` is a view.
    means2d_source: Tensor | None = None

    def retain_means2d_grad(self) -> None:
        """Keep the view-space positional gradient after backward (it is not a leaf)."""
        source = self.means2d if self.means2d_source is None else self.means2d_source
        if source.requires_grad:
            source.retain_grad()

    def means2d_grad(self) -> Tensor | None:
        """dL / d means2d [N, 2] in pixels after ``backward()`` (None without one): what densification thresholds."""
        source = self.means2d if self.means2d_source is None else self.means2d_source
        return None if source.grad is None else source.grad.reshape(-1, 2)

    @property
    def visible(self) -> Tensor:
        """[N] bool: Gaussians that touch the image."""
        return (self.radii > 0).all(dim=-1)

    def depth_normalized(self, eps: float = 1e-6) -> Tensor:
        """Expected depth given that something was hit: depth / alpha (0 where alpha < eps)."""
        return torch.where(self.alpha > eps, self.depth / self.alpha.clamp_min(eps), torch.zeros_like(self.depth))

    def opaque_depth(self, min_alpha: float = OPAQUE_ALPHA) -> Tensor:
        """Expected depth [H, W] where alpha >= ``min_alpha``, else 0 (= unknown): the depth map a sensor would give."""
        if min_alpha <= 0:
            raise ValueError(f"opaque_depth: min_alpha must be > 0, got {min_alpha}")
        depth, alpha = self.depth, self.alpha
        needs_grad = torch.is_grad_enabled() and (depth.requires_grad or alpha.requires_grad)
        if not needs_grad and _float32_cpu(depth, alpha) and depth.shape == alpha.shape:  # a kept map: one pass
            return quotient_where_at_least(depth, alpha, min_alpha)
        # a product with the mask rather than torch.where (x4 slower on a CPU): the clamp keeps the masked-out
        # quotients finite, so they multiply to exact zeros, with zero gradients
        return depth / alpha.clamp_min(min_alpha) * (alpha >= min_alpha)


def _float32_cpu(*tensors: Tensor) -> bool:
    return all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
