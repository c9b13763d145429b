"""tanh of a layer's pre-activations together with their forward-mode tangents, as one numba pass each way.

The material field's jet (:meth:`pidg.models.material_field.MaterialField.jet`) pushes K tangent directions
(d/dx, d/dy, d/dz, d/dt) through each trunk layer next to the values:

    a   = tanh(z)                                   z: the layer's pre-activations [M, W]
    t_k = (1 - a^2) dz_k                            dz: their tangents [K, M, W]

and the momentum residual, which reads the tangents, is differentiated through both (phi'' = -2 a (1 - a^2)):

    dL/dz_k(tangent) = (1 - a^2) g_t_k
    dL/dz            = (1 - a^2) (g_a - 2 a sum_k g_t_k dz_k)

In torch that is a product, a reduction and about ten more passes over [K, M, W] or [M, W] floats, each on one
thread; these kernels make one pass each way on all threads. The torch function below is the readable reference
(and what CUDA runs); tests compare the two and check the reference against autograd.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import float32_array

f32 = np.float32


def tanh_with_tangents_reference(z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
    """(tanh(z) [M, W], its tangents (1 - tanh(z)^2) dz [K, M, W]), differentiable by autograd."""
    a = torch.tanh(z)
    return a, (1.0 - a * a) * dz


@njit(parallel=True, cache=True, nogil=True)
def _tangents_forward(a, dz, tangent):  # pragma: no cover - compiled
    directions, rows, width = dz.shape
    for i in prange(rows):
        for k in range(directions):
            for j in range(width):
                v = a[i, j]
                tangent[k, i, j] = (f32(1.0) - v * v) * dz[k, i, j]


@njit(parallel=True, cache=True, nogil=True)
def _tangents_backward(a, dz, grad_a, grad_tangent, has_grad_a, grad_z, grad_dz):  # pragma: no cover - compiled
    """grad_z [M, W] and grad_dz [K, M, W] from the gradients of a and of the tangents (see the module docstring);
    ``has_grad_a`` False: a's gradient is zero (``grad_a`` is then an empty placeholder)."""
    directions, rows, width = dz.shape
    for i in prange(rows):
        for j in range(width):
            grad_z[i, j] = f32(0.0)
        for k in range(directions):  # grad_z holds sum_k g_t_k dz_k for now
            for j in range(width):
                grad_z[i, j] += grad_tangent[k, i, j] * dz[k, i, j]
        for k in range(directions):
            for j in range(width):
                v = a[i, j]
                grad_dz[k, i, j] = grad_tangent[k, i, j] * (f32(1.0) - v * v)
        for j in range(width):
            v = a[i, j]
            through_a = grad_a[i, j] if has_grad_a else f32(0.0)
            grad_z[i, j] = (f32(1.0) - v * v) * (through_a - f32(2.0) * v * grad_z[i, j])


class _TanhTangentsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, z: Tensor, dz: Tensor):  # type: ignore[override]
        ctx.set_materialize_grads(False)  # an output the loss does not read sends None, not a tensor of zeros
        a = torch.tanh(z).contiguous()  # torch's tanh: the same values as the field's forward pass, bit for bit
        dz_np = float32_array(dz)
        tangent = np.empty_like(dz_np)
        _tangents_forward(float32_array(a), dz_np, tangent)
        ctx.save_for_backward(a, dz)
        return a, torch.from_numpy(tangent)

    @staticmethod
    def backward(ctx, grad_a: Tensor | None, grad_tangent: Tensor | None):  # type: ignore[override]
        a, dz = ctx.saved_tensors
        if grad_tangent is None:  # only the values were read
            return (None if grad_a is None else grad_a * (1.0 - a * a)), None
        a_np, dz_np = float32_array(a), float32_array(dz)
        grad_z, grad_dz = np.empty_like(a_np), np.empty_like(dz_np)
        g_a = np.empty((0, 0), dtype=np.float32) if grad_a is None else float32_array(grad_a)
        _tangents_backward(a_np, dz_np, g_a, float32_array(grad_tangent), grad_a is not None, grad_z, grad_dz)
        return torch.from_numpy(grad_z), torch.from_numpy(grad_dz)


def tanh_with_tangents(z: Tensor, dz: Tensor, kernel: bool | None = None) -> tuple[Tensor, Tensor]:
    """(tanh(z) [M, W], (1 - tanh(z)^2) dz [K, M, W]), differentiable with respect to z and dz. ``kernel``: the numba
    kernel (None: for float32 CPU tensors) or, False, :func:`tanh_with_tangents_reference`."""
    if z.dim() != 2 or dz.dim() != 3 or tuple(dz.shape[1:]) != tuple(z.shape):
        raise ValueError(f"tanh_with_tangents: z must be [M, W] and dz [K, M, W], got {list(z.shape)} and {list(dz.shape)}")
    if kernel is None:
        kernel = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in (z, dz))
    return _TanhTangentsCPU.apply(z, dz) if kernel else tanh_with_tangents_reference(z, dz)
