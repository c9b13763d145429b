"""The flow loss at its supervised pixels (:func:`pidg.flow.model_flow.supervised_flow_loss`) as one numba pass each
way, for float32 CPU tensors.

Why: at the ~4k pixels a training step supervises, decoding the rendered channels and scoring them is ~60 small torch
operations forward and ~25 autograd nodes backward (1.5 ms of the full step's flow loss, nearly all of it per-op
overhead), for a few dozen scalar operations per pixel. Per pixel k, with the channels gathered at it
(m = the 2x2 map, b_g, b_v), its alpha a and centre c (:func:`pidg.flow.gaussian_flow.decode_flows_at`):

    inv = 1 / a where a > DECODE_MIN_ALPHA, else 0
    flow_g = (m c + b_g) inv,   flow_v = (m c + b_v) inv
    L = (lambda_g sum_k s_k |flow_g - gt|_1 + lambda_v sum_k s_k |flow_v - gt|_1) / max(sum_k s_k, 1)

with s_k the target's validity and a > ``FlowConfig.min_alpha`` (:func:`pidg.flow.lpfm.lpfm_loss`). The backward is
the chain rule through these lines, with torch's conventions: |x|' = sign(x) (0 at 0), no gradient through s_k.
Sums run in float64. The torch functions stay the readable reference; tests compare the two.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from pidg.kernel_math import float32_array

f32 = np.float32


@njit(cache=True, nogil=True)
def _flow_l1_forward(features, alpha, centers, gt, valid, min_decode, min_alpha, velocity, lambda_g, lambda_v, diagnostics):  # pragma: no cover - compiled
    """The loss; ``diagnostics`` [4] <- (count, sum |flow_g - gt|_2, sum |flow_v - gt|_2, sum |gt|_2) over s."""
    count = 0
    l1_g = 0.0
    l1_v = 0.0
    epe_g = 0.0
    epe_v = 0.0
    size = 0.0
    for k in range(alpha.shape[0]):
        a = alpha[k]
        if not (valid[k] and a > min_alpha):
            continue
        inv = f32(1.0) / a if a > min_decode else f32(0.0)
        cx, cy = centers[k, 0], centers[k, 1]
        mx = features[k, 0] * cx + features[k, 1] * cy
        my = features[k, 2] * cx + features[k, 3] * cy
        gx, gy = gt[k, 0], gt[k, 1]
        dx = (mx + features[k, 4]) * inv - gx
        dy = (my + features[k, 5]) * inv - gy
        count += 1
        l1_g += abs(dx) + abs(dy)
        epe_g += math.sqrt(dx * dx + dy * dy)
        size += math.sqrt(gx * gx + gy * gy)
        if velocity:
            ex = (mx + features[k, 6]) * inv - gx
            ey = (my + features[k, 7]) * inv - gy
            l1_v += abs(ex) + abs(ey)
            epe_v += math.sqrt(ex * ex + ey * ey)
    diagnostics[0] = count
    diagnostics[1] = epe_g
    diagnostics[2] = epe_v
    diagnostics[3] = size
    return (lambda_g * l1_g + lambda_v * l1_v) / max(count, 1)


@njit(cache=True, inline="always")
def _sign(x):  # pragma: no cover - compiled
    return f32(1.0) if x > 0 else (f32(-1.0) if x < 0 else f32(0.0))


@njit(cache=True, nogil=True)
def _flow_l1_backward(features, alpha, centers, gt, valid, min_decode, min_alpha, velocity, weight_g, weight_v, g_features, g_alpha):  # pragma: no cover - compiled
    """dL/dfeatures [K, C] and dL/dalpha [K] for weights lambda * dL_out / max(count, 1) (rows of unsupervised pixels
    left as they are: zero)."""
    for k in range(alpha.shape[0]):
        a = alpha[k]
        if not (valid[k] and a > min_alpha) or not a > min_decode:
            continue
        inv = f32(1.0) / a
        cx, cy = centers[k, 0], centers[k, 1]
        mx = features[k, 0] * cx + features[k, 1] * cy
        my = features[k, 2] * cx + features[k, 3] * cy
        ux, uy = mx + features[k, 4], my + features[k, 5]  # flow_g before the division by alpha
        sx = weight_g * _sign(ux * inv - gt[k, 0])
        sy = weight_g * _sign(uy * inv - gt[k, 1])
        g_features[k, 4] = sx * inv
        g_features[k, 5] = sy * inv
        gmx, gmy = sx, sy  # d/d(m c): through both flows
        g_inv = sx * ux + sy * uy
        if velocity:
            vx, vy = mx + features[k, 6], my + features[k, 7]
            tx = weight_v * _sign(vx * inv - gt[k, 0])
            ty = weight_v * _sign(vy * inv - gt[k, 1])
            g_features[k, 6] = tx * inv
            g_features[k, 7] = ty * inv
            gmx += tx
            gmy += ty
            g_inv += tx * vx + ty * vy
        g_features[k, 0] = gmx * inv * cx
        g_features[k, 1] = gmx * inv * cy
        g_features[k, 2] = gmy * inv * cx
        g_features[k, 3] = gmy * inv * cy
        g_alpha[k] = -g_inv * inv * inv


class _FlowL1AtPixels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features: Tensor, alpha: Tensor, centers: Tensor, gt: Tensor, valid: Tensor,  # type: ignore[override]
                min_decode: float, min_alpha: float, lambda_g: float, lambda_v: float) -> tuple[Tensor, Tensor]:
        arrays = (float32_array(features), float32_array(alpha), float32_array(centers), float32_array(gt), valid.contiguous().numpy())
        velocity = features.shape[1] == 8
        diagnostics = np.zeros(4, dtype=np.float64)
        loss = _flow_l1_forward(*arrays, f32(min_decode), f32(min_alpha), velocity, lambda_g, lambda_v if velocity else 0.0, diagnostics)
        ctx.arrays, ctx.settings = arrays, (f32(min_decode), f32(min_alpha), velocity)
        ctx.weights, ctx.count = (lambda_g, lambda_v if velocity else 0.0), diagnostics[0]
        out = torch.from_numpy(diagnostics)
        ctx.mark_non_differentiable(out)
        return features.new_tensor(loss), out

    @staticmethod
    def backward(ctx, grad_loss: Tensor, _grad_diagnostics: Tensor):  # type: ignore[override]
        features, alpha = ctx.arrays[0], ctx.arrays[1]
        g_features = np.zeros(features.shape, dtype=np.float32)
        g_alpha = np.zeros(alpha.shape, dtype=np.float32)
        scale = float(grad_loss) / max(ctx.count, 1.0)
        if ctx.count:
            _flow_l1_backward(*ctx.arrays, *ctx.settings, f32(ctx.weights[0] * scale), f32(ctx.weights[1] * scale), g_features, g_alpha)
        return torch.from_numpy(g_features), torch.from_numpy(g_alpha), None, None, None, None, None, None, None


def flow_l1_at_pixels_cpu(
    features: Tensor, alpha: Tensor, centers: Tensor, gt: Tensor, valid: Tensor, min_decode: float, min_alpha: float,
    lambda_gaussian: float, lambda_velocity: float,
) -> tuple[Tensor, int, float, float | None, float]:
    """The loss of the module docstring at K pixels (``features`` [K, 6 or 8], ``alpha`` [K], ``centers`` [K, 2],
    ``gt`` [K, 2], ``valid`` [K] bool; float32 CPU), differentiable in ``features`` and ``alpha``, and its diagnostics:
    (loss, supervised pixels, mean EPE of flow_g, of flow_v (None with 6 channels), mean |gt|), EPEs in pixels."""
    if features.dim() != 2 or features.shape[1] not in (6, 8):
        raise ValueError(f"the fused flow loss takes [K, 6 or 8] channels (none for depth changes), got {list(features.shape)}")
    loss, diagnostics = _FlowL1AtPixels.apply(features, alpha, centers, gt, valid, min_decode, min_alpha, lambda_gaussian, lambda_velocity)
    count, epe_g, epe_v, size = diagnostics.tolist()
    n = max(count, 1.0)
    return loss, int(count), epe_g / n, (epe_v / n if features.shape[1] == 8 else None), size / n
