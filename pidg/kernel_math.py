"""float32 building blocks for pidg's numba kernels: the arrays they take (and the zeroed buffers they fill sparsely),
and arithmetic that keeps their loops vectorisable (no libm call, no branch).

numba compiles ``math.exp`` to a scalar libm call per element (no SVML here), which stops a loop from being
vectorised; these helpers build the same results from arithmetic and bit operations that LLVM vectorises.
"""
from __future__ import annotations

import sys
import threading

import llvmlite.ir
import numba
import numpy as np
import torch
from numba import njit, prange
from numba.extending import intrinsic
from torch import Tensor

f32 = np.float32
_LOG2E = 1.4426950408889634
_LN2 = 0.6931471805599453
EXP_MIN_ARGUMENT = -87.0  # 2^n stays a normal float32 (n >= -126) for every x >= this


def float32_array(t: Tensor) -> np.ndarray:
    """What the kernels take: a tensor's values as a C-contiguous float32 numpy array, detached (a view of the
    tensor's memory when it is one already, else a copy). The view skips the no-op conversions: a full step makes
    ~250 of these calls, and each torch call costs microseconds (6.5 -> 2.3 us, 4.2 with a detach)."""
    if t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous():
        return (t.detach() if t.requires_grad else t).numpy()
    return t.detach().to(torch.float32).contiguous().numpy()


def round_robin_workers() -> int:
    """How many workers a kernel deals tasks of uneven cost to (task i to worker i mod W, a worker being one iteration
    of its ``prange``): the number of numba threads.

    numba's ``omp`` and ``workqueue`` threading layers cut a ``prange`` into one contiguous block of iterations per
    thread, whatever ``numba.parallel_chunksize`` says (measured here: a 625-iteration loop whose first half holds
    all the work ran on one thread with chunk size 0, 1 or 8 alike, 9.3 ms against 4.7 when the work alternates).
    Handed out in index order, a render's tiles (costly in the middle of the image) or a hash grid's levels (the
    hashed ones last) left one thread idle. Neighbouring tiles and levels cost about the same, so dealing them in
    turn balances the threads without a queue."""
    return numba.get_num_threads()


@njit(parallel=True, cache=True, nogil=True)
def _zero(flat):  # pragma: no cover - compiled
    for i in prange(flat.shape[0]):
        flat[i] = 0.0


class ZeroedBufferPool:
    """Reusable zeroed float32 buffers for kernels that fill a large array sparsely (a hash table's gradient, a render's
    extra channels at a few pixels, their gradient).

    A fresh 49 MB ``np.zeros`` per backward pass (Grid4D's spatial table) costs page faults on first touch: 6 ms
    of a 20 ms backward when the machine is quiet and up to 60 ms when it is not (measured); re-zeroing a buffer
    in place takes 1.3 ms. A buffer handed out as a gradient is reused only once nothing else refers to it
    (its tensor, e.g. a parameter's ``.grad``, was released), so a gradient still in use is never overwritten.
    A caller that writes only some rows (first-axis indices) says which (``rows``): the buffer's next user then
    gets those rows re-zeroed instead of the whole buffer (the flow loss's gradient image: ~2k of 160k rows).
    """

    def __init__(self, per_shape: int = 4) -> None:
        self.per_shape = per_shape
        # per shape: [buffer, the rows its last holder said it writes (None: any)] for each pooled buffer
        self._slots: dict[tuple[int, ...], list[list]] = {}
        self._lock = threading.Lock()

    def zeros(self, *shape: int, rows: np.ndarray | None = None) -> np.ndarray:
        """A zeroed C-contiguous float32 array of ``shape``. ``rows``: the only first-axis indices (int array, or a
        bool mask over that axis) the caller will write; None: any."""
        written = None if rows is None else np.array(rows, copy=True)
        with self._lock:
            slots = self._slots.setdefault(shape, [])
            for slot in slots:
                if sys.getrefcount(slot[0]) == _UNREFERENCED:  # only the pool holds it
                    buf, dirty = slot
                    if dirty is None:
                        _zero(buf.reshape(-1))
                    else:
                        buf[dirty] = 0.0
                    slot[1] = written
                    return buf
            buf = np.zeros(shape, dtype=np.float32)
            if len(slots) < self.per_shape:
                slots.append([buf, written])
            return buf


_UNREFERENCED = 2  # sys.getrefcount of an array held only by the pool's slot: the slot and the call's argument
ZEROED_BUFFERS = ZeroedBufferPool()  # the process's pool


class _SelectDistinctRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, source: Tensor, index: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(index)
        ctx.shape = source.shape
        return source.index_select(0, index)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        (index,) = ctx.saved_tensors
        if grad.device.type == "cpu" and grad.dtype == torch.float32:
            # a pooled buffer: a fresh zeroed one faults its pages in (2.3 ms a step for a 400x400 render's 8 flow
            # channels, torch.zeros); only the rows written here are re-zeroed for its next user
            full = torch.from_numpy(ZEROED_BUFFERS.zeros(*ctx.shape, rows=index.numpy()))
            # held here until the graph is freed: autograd adds another gradient of the same tensor in place into a
            # gradient only it refers to, which would write rows the pool does not re-zero
            ctx.pooled_gradient = full
        else:
            full = grad.new_zeros(ctx.shape)
        return full.index_copy_(0, index, grad), None


def select_distinct_rows(source: Tensor, index: Tensor) -> Tensor:
    """``source.index_select(0, index)`` for distinct indices [K] (no row repeats, so the gradient copies each row
    back in its place instead of adding), with the gradient [N, ...] on the CPU one of :data:`ZEROED_BUFFERS`,
    reused once the previous one is released and re-zeroed at the rows written only: a few rows of a large tensor
    (the flow loss's pixels of a render, the flow's Gaussians' features) cost a few rows, not a zero-filled copy."""
    return _SelectDistinctRows.apply(source, index)


@njit(parallel=True, cache=True, nogil=True)
def _quotient_where_at_least(numerator, denominator, floor, out):  # pragma: no cover - compiled
    for i in prange(numerator.shape[0]):
        d = denominator[i]
        out[i] = numerator[i] / d if d >= floor else f32(0.0)


def quotient_where_at_least(numerator: Tensor, denominator: Tensor, floor: float) -> Tensor:
    """numerator / denominator where denominator >= ``floor`` (> 0), else 0, for float32 CPU tensors of one shape,
    without a gradient, in one pass (a render's opaque depth at 400x400, one thread: 0.1 ms against the torch form's
    four full-image operations' 1.1)."""
    out = np.empty(numerator.numel(), dtype=np.float32)
    _quotient_where_at_least(float32_array(numerator).reshape(-1), float32_array(denominator).reshape(-1), f32(floor), out)
    return torch.from_numpy(out).reshape(numerator.shape)


@intrinsic
def float32_from_bits(typingctx, bits):  # pragma: no cover - compiled
    """Reinterpret an int32's bits as a float32 (LLVM bitcast): 2^n built in a register, where a table lookup
    made the lane loops gather."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], llvmlite.ir.FloatType())

    return numba.types.float32(numba.types.int32), codegen


@njit(cache=True, inline="always")
def exp_nonpositive_unclamped(x):  # pragma: no cover - compiled
    """exp(x) for x in [EXP_MIN_ARGUMENT, 0] (the caller keeps it there), branch-free: 2^n * Estrin(6) on
    [-ln2/2, ln2/2]. Relative error below 5e-7 on [-5.6, 0] (the compositor's alphas), growing by up to 1e-7 per
    unit of |x| beyond (the float32 rounding of x log2(e)): 4e-6 at x = -87."""
    t = x * f32(_LOG2E)
    n = np.floor(t + f32(0.5))
    r = (t - n) * f32(_LN2)
    r2 = r * r
    poly = (f32(1.0) + r) + r2 * ((f32(0.5) + r * f32(1.0 / 6.0)) + r2 * ((f32(1.0 / 24.0) + r * f32(1.0 / 120.0)) + r2 * f32(1.0 / 720.0)))
    return poly * float32_from_bits((np.int32(n) + np.int32(127)) << np.int32(23))  # 2^n, n in [-126, 0]


@njit(cache=True, inline="always")
def exp_nonpositive(x):  # pragma: no cover - compiled
    """exp(x) for any x <= 0: below EXP_MIN_ARGUMENT it returns exp(EXP_MIN_ARGUMENT) ~ 1.6e-38, under every
    float32 that matters next to 1."""
    return exp_nonpositive_unclamped(max(x, f32(EXP_MIN_ARGUMENT)))
