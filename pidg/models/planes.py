"""Bilinear lookup of feature planes with its first derivatives: the material field's planes (XY ... ZT), with a
numba kernel and a torch reference.

K planes [K, Ra, Rb, C] are looked up at continuous cell coordinates (pa, pb) [M, K] (0 and R - 1 are the first and
last grid lines). With the cell ``i = clamp(floor(p), 0, R - 2)`` and the *unclamped* fraction ``f = p - i`` (outside
the plane the border cell's bilinear function continues linearly: values stay continuous and the derivatives
non-zero where deformed particles leave the box), and the cell's corners v00, v01 (b + 1), v10 (a + 1), v11:

    value = v00 (1 - fa)(1 - fb) + v01 (1 - fa) fb + v10 fa (1 - fb) + v11 fa fb
    d/dpa = (v10 - v00)(1 - fb) + (v11 - v01) fb
    d/dpb = (v01 - v00)(1 - fa) + (v11 - v10) fa

The cell index is piecewise constant (no gradient), so d f / d p = 1. The backward, for incoming gradients
(gv, ga, gb) of the three outputs and the cross difference ``x = v11 - v10 - v01 + v00``:

    corners:  g00 = gv (1-fa)(1-fb) - ga (1-fb) - gb (1-fa)     g01 = gv (1-fa) fb - ga fb + gb (1-fa)
              g10 = gv fa (1-fb) + ga (1-fb) - gb fa            g11 = gv fa fb + ga fb + gb fa
    coords:   g_pa = sum_c gv d/dpa + gb x                      g_pb = sum_c gv d/dpb + ga x

Two implementations behind :func:`lookup_planes`:
  * :func:`plane_lookup`: readable torch (autograd, any device and dtype, any order of derivatives). CUDA uses it.
  * ``_PlaneLookupCPU``: numba, float32, first derivatives of the outputs only (which is all the material field's
    forward and its jet need: the jet's tangents are outputs here, and L_CMR is differentiated once). In torch one
    lookup of 8k particles is ~30 small ops forward and a scatter-add backward: 40 % of the material field's
    forward + backward at the cpu preset's width (``pidg bench step``); the kernel is one pass each way.
The kernel's backward runs one parallel task per block of particles, each adding into its own copy of the (small:
24k entries at the defaults) table gradient, which are then summed in a fixed order: no atomics, and the same result
on any number of threads. Tests compare both passes with the reference in float64.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from pidg.kernel_math import float32_array
from pidg.models.deformation.hash_grid import HashGridBackend, resolve_backend

f32 = np.float32
_CHUNK = 256  # particles per parallel task of the point-parallel kernels


def plane_lookup(planes: Tensor, pa: Tensor, pb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The torch reference: values, d/dpa and d/dpb, each [M, K, C], of planes [K, Ra, Rb, C] at pa, pb [M, K]
    (module docstring)."""
    k, ra, rb, c = planes.shape
    ia = pa.detach().floor().clamp(0, ra - 2)
    ib = pb.detach().floor().clamp(0, rb - 2)
    fa, fb = (pa - ia).unsqueeze(-1), (pb - ib).unsqueeze(-1)
    first = torch.arange(k, device=planes.device) * (ra * rb) + ia.long() * rb + ib.long()  # [M, K]
    corner_offsets = torch.tensor([0, 1, rb, rb + 1], device=planes.device)  # (a, b), (a, b+1), (a+1, b), (a+1, b+1)
    rows = (first.unsqueeze(-1) + corner_offsets).reshape(-1)
    corners = planes.reshape(k * ra * rb, c).index_select(0, rows).reshape(*first.shape, 4, c)
    v00, v01, v10, v11 = corners.unbind(-2)
    along_a_low, along_a_high = v10 - v00, v11 - v01
    d_pa = along_a_low + fb * (along_a_high - along_a_low)
    d_pb = (v01 - v00) + fa * (along_a_high - along_a_low)
    value = v00 + fb * (v01 - v00) + fa * d_pa
    return value, d_pa, d_pb


# ----------------------------------------------------------------------------------------------------------------
# numba kernels


@njit(cache=True, inline="always")
def _cell(p, r):  # pragma: no cover - compiled
    """(cell index, fraction) of a coordinate on an axis of r grid lines: index clamped to [0, r - 2], fraction not."""
    i = np.floor(p)
    i = i if i >= f32(0.0) else f32(0.0)  # NaN lands here too: the index stays in range
    hi = f32(r - 2)
    i = i if i <= hi else hi
    return np.int64(i), p - i


@njit(cache=True, inline="always")
def _corners(pa, pb, i, k, ra, rb):  # pragma: no cover - compiled
    """Particle i's cell on plane k and its bilinear weights: (ia, ib, fa, fb, 1 - fa, 1 - fb)."""
    ia, fa = _cell(pa[i, k], ra)
    ib, fb = _cell(pb[i, k], rb)
    return ia, ib, fa, fb, f32(1.0) - fa, f32(1.0) - fb


@njit(parallel=True, cache=True, nogil=True)
def _lookup_forward(planes, pa, pb, value, d_pa, d_pb, derivatives):  # pragma: no cover - compiled
    """planes [K, Ra, Rb, C], pa / pb [M, K] -> value (and with ``derivatives`` d_pa, d_pb) [M, K, C]."""
    n_planes, ra, rb, n_ch = planes.shape
    m = pa.shape[0]
    for chunk in prange((m + _CHUNK - 1) // _CHUNK):
        for i in range(chunk * _CHUNK, min(m, (chunk + 1) * _CHUNK)):
            for k in range(n_planes):
                ia, ib, fa, fb, ga, gb = _corners(pa, pb, i, k, ra, rb)
                for c in range(n_ch):
                    v00, v01 = planes[k, ia, ib, c], planes[k, ia, ib + 1, c]
                    v10, v11 = planes[k, ia + 1, ib, c], planes[k, ia + 1, ib + 1, c]
                    value[i, k, c] = ga * (gb * v00 + fb * v01) + fa * (gb * v10 + fb * v11)
                    if derivatives:
                        d_pa[i, k, c] = (v10 - v00) * gb + (v11 - v01) * fb
                        d_pb[i, k, c] = (v01 - v00) * ga + (v11 - v10) * fa


_MAX_BACKWARD_TASKS = 16  # particle blocks of the backward pass, each with its own copy of the table gradient
_PARTICLES_PER_TASK = 512  # fewer particles share a block: zeroing and summing the copies would cost more than the work


def backward_tasks(m: int) -> int:
    """Particle blocks of the backward pass for ``m`` particles: a function of m alone, so that the order of the
    table gradient's sums (and its rounding) does not depend on the number of threads."""
    return max(1, min(_MAX_BACKWARD_TASKS, m // _PARTICLES_PER_TASK))


@njit(parallel=True, cache=True, nogil=True)
def _lookup_backward(planes, pa, pb, g_value, g_da, g_db, partial, grad_pa, grad_pb):  # pragma: no cover - compiled
    """Incoming gradients [M, K, C] -> each particle block's table gradient ``partial`` [T, K, Ra, Rb, C] (zeroed
    by the caller; the planes are small, so every block owns a copy and their sum is the gradient) and grad_pa,
    grad_pb [M, K] (empty arrays: not wanted). ``g_da`` and ``g_db`` are empty [0, 0, 0] when the lookup had no
    derivative outputs (or nobody used them): their terms are skipped, not multiplied by zeros."""
    n_planes, ra, rb, n_ch = planes.shape
    m = pa.shape[0]
    n_tasks = partial.shape[0]
    coords = grad_pa.shape[0] > 0
    slopes = g_da.shape[0] > 0
    per_task = (m + n_tasks - 1) // n_tasks
    for task in prange(n_tasks):
        grad = partial[task]
        for i in range(task * per_task, min(m, (task + 1) * per_task)):
            for k in range(n_planes):
                ia, ib, fa, fb, ga, gb = _corners(pa, pb, i, k, ra, rb)
                w00, w01, w10, w11 = ga * gb, ga * fb, fa * gb, fa * fb
                sa, sb = f32(0.0), f32(0.0)
                for c in range(n_ch):
                    gv = g_value[i, k, c]
                    g00, g01, g10, g11 = gv * w00, gv * w01, gv * w10, gv * w11
                    if slopes:
                        a, b = g_da[i, k, c], g_db[i, k, c]
                        g00 += -a * gb - b * ga
                        g01 += -a * fb + b * ga
                        g10 += a * gb - b * fa
                        g11 += a * fb + b * fa
                    grad[k, ia, ib, c] += g00
                    grad[k, ia, ib + 1, c] += g01
                    grad[k, ia + 1, ib, c] += g10
                    grad[k, ia + 1, ib + 1, c] += g11
                    if coords:
                        v00, v01 = planes[k, ia, ib, c], planes[k, ia, ib + 1, c]
                        v10, v11 = planes[k, ia + 1, ib, c], planes[k, ia + 1, ib + 1, c]
                        sa += gv * ((v10 - v00) * gb + (v11 - v01) * fb)
                        sb += gv * ((v01 - v00) * ga + (v11 - v10) * fa)
                        if slopes:
                            cross = v11 - v10 - v01 + v00
                            sa += g_db[i, k, c] * cross
                            sb += g_da[i, k, c] * cross
                if coords:
                    grad_pa[i, k] = sa
                    grad_pb[i, k] = sb


class _PlaneLookupCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, planes: Tensor, pa: Tensor, pb: Tensor, derivatives: bool):  # type: ignore[override]
        np_planes, np_pa, np_pb = float32_array(planes), float32_array(pa), float32_array(pb)
        m, (k, _, _, c) = np_pa.shape[0], np_planes.shape
        value = np.empty((m, k, c), dtype=np.float32)
        d_pa = np.empty((m, k, c) if derivatives else (0, 0, 0), dtype=np.float32)
        d_pb = np.empty_like(d_pa)
        _lookup_forward(np_planes, np_pa, np_pb, value, d_pa, d_pb, derivatives)
        ctx.save_for_backward(planes, pa, pb)
        ctx.set_materialize_grads(False)  # outputs nobody used send None: their terms are skipped
        outputs = tuple(torch.from_numpy(a).to(planes.dtype) for a in (value, d_pa, d_pb))
        return outputs if derivatives else outputs[0]

    @staticmethod
    def backward(ctx, g_value: Tensor | None, g_da: Tensor | None = None, g_db: Tensor | None = None):  # type: ignore[override]
        planes, pa, pb = ctx.saved_tensors
        np_pa, np_pb = float32_array(pa), float32_array(pb)
        m, (k, _, _, c) = np_pa.shape[0], planes.shape
        zeros = np.zeros((m, k, c), dtype=np.float32)
        no_slopes = np.empty((0, 0, 0), dtype=np.float32)
        gv = zeros if g_value is None else float32_array(g_value)
        if g_da is None and g_db is None:  # no derivative outputs, or none used
            ga = gb = no_slopes
        else:
            ga = zeros if g_da is None else float32_array(g_da)
            gb = zeros if g_db is None else float32_array(g_db)
        coords = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        partial = np.zeros((backward_tasks(m), *planes.shape), dtype=np.float32)
        out_a = np.empty((m, k) if coords else (0, k), dtype=np.float32)
        out_b = np.empty_like(out_a)
        _lookup_backward(float32_array(planes), np_pa, np_pb, gv, ga, gb, partial, out_a, out_b)
        grad_planes = torch.from_numpy(partial.sum(axis=0)).to(planes.dtype) if ctx.needs_input_grad[0] else None
        grad_pa = torch.from_numpy(out_a).to(pa.dtype) if ctx.needs_input_grad[1] else None
        grad_pb = torch.from_numpy(out_b).to(pb.dtype) if ctx.needs_input_grad[2] else None
        return grad_planes, grad_pa, grad_pb, None


def lookup_planes(
    planes: Tensor, pa: Tensor, pb: Tensor, derivatives: bool = True, backend: HashGridBackend = "auto"
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Values [M, K, C] of planes [K, Ra, Rb, C] at pa, pb [M, K], and with ``derivatives`` d/dpa and d/dpb (else
    None). ``backend``: "auto" runs the numba kernel on float32 CPU tensors and the torch reference otherwise."""
    if planes.dim() != 4 or pa.dim() != 2 or pa.shape != pb.shape or pa.shape[1] != planes.shape[0]:
        raise ValueError(f"lookup_planes: planes [K, Ra, Rb, C] with pa, pb [M, K], got {list(planes.shape)}, "
                         f"{list(pa.shape)}, {list(pb.shape)}")
    if min(planes.shape[1:3]) < 2:
        raise ValueError(f"lookup_planes: a plane needs at least 2 grid lines per axis, got {list(planes.shape)}")
    if resolve_backend(backend, planes) == "cpu" and pa.dtype == torch.float32 and pb.dtype == torch.float32:
        if derivatives:
            value, d_pa, d_pb = _PlaneLookupCPU.apply(planes, pa, pb, True)
            return value, d_pa, d_pb
        return _PlaneLookupCPU.apply(planes, pa, pb, False), None, None
    value, d_pa, d_pb = plane_lookup(planes, pa, pb)
    return (value, d_pa, d_pb) if derivatives else (value, None, None)
