"""``torch.optim.SparseAdam`` with its CPU update fused into one numba pass: the optimizer of the material field's
index embedding, whose gradient holds only the rows of the particles a step evaluated.

torch's SparseAdam runs about fifteen tensor operations a step (a coalesce that sorts the looked-up rows, two
``sparse_mask`` gathers, sparse additions). On the full method's CPU step the embedding's gradient is a few thousand
lookups of a few hundred distinct rows, and those operations cost 2.3 ms a step (profiled on 2 cores at 16k
Gaussians: 3.6k lookups, 169 distinct rows of 64); the kernel sums the duplicate rows and updates each distinct row
once. It is the same algorithm with the same state (``step``, ``exp_avg``, ``exp_avg_sq``), so checkpoints load into
either, and torch's own step runs wherever the kernel does not apply (CUDA, other dtypes, ``maximize``, gradients
that are not a row-sparse [P, H] table's). ``torch.optim.SparseAdam`` is the reference the tests compare against.

Per distinct row r of a step with summed gradient g (torch's order of operations, in float32):
    m_r <- m_r + (g - m_r)(1 - beta1),  v_r <- v_r + (g^2 - v_r)(1 - beta2)
    p_r <- p_r - lr sqrt(1 - beta2^step) / (1 - beta1^step) * m_r / (sqrt(v_r) + eps)
Rows the step did not look up are left untouched (lazy Adam: their moments do not decay).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.graph import increment_version

f32 = np.float32


@njit(cache=True, nogil=True)
def _sparse_adam_rows(rows, values, param, exp_avg, exp_avg_sq, one_minus_beta1, one_minus_beta2, eps, neg_step_size):  # pragma: no cover - compiled
    """One SparseAdam update of the table ``param`` [P, H] (and its moments) by the uncoalesced gradient rows
    ``rows`` [nnz] / ``values`` [nnz, H]: duplicates summed in lookup order, then each distinct row updated once."""
    nnz, width = values.shape
    slot = np.full(param.shape[0], -1, np.int64)  # table row -> its position among the distinct rows
    distinct = np.empty(nnz, np.int64)
    count = 0
    for k in range(nnz):
        r = rows[k]
        if slot[r] < 0:
            slot[r] = count
            distinct[count] = r
            count += 1
    grad = np.zeros((count, width), np.float32)
    for k in range(nnz):
        s = slot[rows[k]]
        for c in range(width):
            grad[s, c] += values[k, c]
    for s in range(count):
        r = distinct[s]
        for c in range(width):
            g = grad[s, c]
            m = exp_avg[r, c]
            v = exp_avg_sq[r, c]
            m += (g - m) * one_minus_beta1
            v += (g * g - v) * one_minus_beta2
            exp_avg[r, c] = m
            exp_avg_sq[r, c] = v
            param[r, c] += neg_step_size * (m / (np.sqrt(v) + eps))


def _row_sparse_float32_cpu(param: Tensor, grad: Tensor, state: dict) -> bool:
    """Whether the kernel applies: a contiguous float32 CPU table [P, H] (and moments, once there) whose gradient is
    row-sparse (sparse rows, dense H)."""
    return (
        param.device.type == "cpu" and param.dtype == torch.float32 and param.dim() == 2 and param.is_contiguous()
        and grad.is_sparse and grad.sparse_dim() == 1 and grad.dense_dim() == 1 and grad.dtype == torch.float32
        and all(state[k].is_contiguous() and state[k].dtype == torch.float32 for k in ("exp_avg", "exp_avg_sq") if k in state)
    )


class SparseAdam(torch.optim.SparseAdam):
    """``torch.optim.SparseAdam`` (same arguments, same state), its update one numba pass per parameter where every
    parameter with a gradient is a float32 CPU [P, H] table with a row-sparse gradient (torch's step otherwise)."""

    @torch.no_grad()
    def step(self, closure=None):  # noqa: ANN001, ANN201 - torch.optim.Optimizer.step's signature
        with_grad = [(p, group) for group in self.param_groups for p in group["params"] if p.grad is not None]
        if any(group.get("maximize", False) or not _row_sparse_float32_cpu(p, p.grad, self.state[p]) for p, group in with_grad):
            return super().step(closure)
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for p, group in with_grad:
            state = self.state[p]
            if len(state) == 0:  # as torch initialises it
                state["step"] = 0
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["step"] += 1
            grad = p.grad
            values = grad._values()
            if values.numel() == 0:  # torch skips an empty gradient after counting the step
                continue
            beta1, beta2 = group["betas"]
            lr = float(group["lr"])
            step = state["step"]
            step_size = lr * math.sqrt(1 - beta2**step) / (1 - beta1**step)
            _sparse_adam_rows(
                grad._indices()[0].numpy(), values.contiguous().numpy(), p.detach().numpy(),
                state["exp_avg"].numpy(), state["exp_avg_sq"].numpy(), f32(1 - beta1), f32(1 - beta2),
                f32(group["eps"]), f32(-step_size),
            )
            increment_version(p)  # written through numpy: tell autograd, as torch's in-place update would
        return loss
