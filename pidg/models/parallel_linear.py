"""Linear layers whose matrix products run on more torch threads than the rest of a CPU step.

A CPU run trains with torch on one thread (``TrainConfig.cpu_torch_threads``): on two cores, a parallel torch
operation paid more in thread wake-up than most of a step's small operations compute. Matrix products are the
exception: a [18000, 64] x [64, 64] product takes 2.3 ms on one thread and 1.3 ms on two (measured on the 2-core
machine; the thread count itself switches in under a microsecond). Inside :func:`matmul_threads`, :func:`linear`
(and :class:`Linear`, which the networks use) raises torch's thread count for its products only, forward and
backward, and puts it back. Outside it, they are ``F.linear`` and ``nn.Linear``, unchanged.

Only float32 CPU tensors take the switch. Its autograd node is once-differentiable and has no forward-mode rule:
torch.func's transforms (``pidg.models.jet.jet_from_function``) get plain ``F.linear`` outside the context.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

_threads: int | None = None  # set by matmul_threads; None: no switch


@contextmanager
def matmul_threads(threads: int | None) -> Iterator[None]:
    """Within the block, :func:`linear`'s products on CPU float32 tensors run on ``threads`` torch threads
    (None or 0: no switch)."""
    global _threads
    previous, _threads = _threads, (threads or None)
    try:
        yield
    finally:
        _threads = previous


@contextmanager
def _torch_threads(threads: int) -> Iterator[None]:
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class _LinearOnThreads(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, threads: int) -> Tensor:  # type: ignore[override]
        with _torch_threads(threads):
            out = F.linear(x, weight, bias)
        ctx.save_for_backward(x, weight)
        ctx.threads, ctx.has_bias = threads, bias is not None
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        x, weight = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        rows = grad_out.reshape(-1, grad_out.shape[-1])
        with _torch_threads(ctx.threads):
            if ctx.needs_input_grad[0]:
                grad_x = grad_out @ weight
            if ctx.needs_input_grad[1]:
                grad_weight = rows.T @ x.reshape(-1, x.shape[-1])
            if ctx.has_bias and ctx.needs_input_grad[2]:
                grad_bias = rows.sum(0)
        return grad_x, grad_weight, grad_bias, None


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``F.linear(x, weight, bias)`` (x [..., in], weight [out, in]); inside :func:`matmul_threads`, on float32 CPU
    tensors, its products forward and backward run on that many torch threads."""
    threads = _threads
    if threads is None or x.device.type != "cpu" or x.dtype != torch.float32 or threads == torch.get_num_threads():
        return F.linear(x, weight, bias)
    if not torch.is_grad_enabled():
        with _torch_threads(threads):
            return F.linear(x, weight, bias)
    return _LinearOnThreads.apply(x, weight, bias, threads)


class Linear(nn.Linear):
    """``nn.Linear`` (same parameters, same state-dict keys) through :func:`linear`."""

    def forward(self, x: Tensor) -> Tensor:
        return linear(x, self.weight, self.bias)
