"""pidg's fused SparseAdam against torch.optim.SparseAdam, the reference it must reproduce."""
from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from pidg.training.sparse_adam import SparseAdam


def _lookup_grads(rows: int, width: int, steps: int, lookups: int, seed: int = 0) -> list[torch.Tensor]:
    """Uncoalesced row-sparse gradients of an embedding lookup: repeated rows, some rows never looked up."""
    g = torch.Generator().manual_seed(seed)
    grads = []
    for _ in range(steps):
        index = torch.randint(0, rows // 2, (lookups,), generator=g) * 2  # odd rows are never looked up
        table = torch.zeros(rows, width, requires_grad=True)
        out = F.embedding(index, table, sparse=True)
        (out * torch.randn(out.shape, generator=g)).sum().backward()
        grads.append(table.grad)
    return grads


def _run(optimizer_class, start: torch.Tensor, grads: list[torch.Tensor], **kwargs) -> tuple[torch.Tensor, dict]:
    param = torch.nn.Parameter(start.clone())
    optimizer = optimizer_class([param], **kwargs)
    for k, grad in enumerate(grads):
        param.grad = grad.clone()
        for group in optimizer.param_groups:
            group["lr"] = 0.01 * 0.9**k  # a schedule, as ScheduledOptimizer sets it
        optimizer.step()
    return param.detach(), optimizer.state[param]


@pytest.mark.parametrize("lookups", [1, 37, 500])
def test_matches_torch_sparse_adam(lookups):
    start = torch.randn(64, 8, generator=torch.Generator().manual_seed(1))
    grads = _lookup_grads(64, 8, steps=12, lookups=lookups)
    kwargs = dict(betas=(0.9, 0.999), eps=1e-15)
    ours, our_state = _run(SparseAdam, start, grads, **kwargs)
    ref, ref_state = _run(torch.optim.SparseAdam, start, grads, **kwargs)
    assert our_state["step"] == ref_state["step"] == 12
    # duplicate rows are summed in another order than torch's coalesce: float32 rounding apart
    torch.testing.assert_close(our_state["exp_avg"], ref_state["exp_avg"], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(our_state["exp_avg_sq"], ref_state["exp_avg_sq"], rtol=1e-5, atol=1e-10)
    torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-6)
    assert not torch.equal(ours, start)
    assert torch.equal(ours[1::2], start[1::2])  # rows never looked up are untouched (lazy Adam)


def test_takes_the_kernel_on_float32_cpu(monkeypatch):
    """The float32 CPU step is the kernel's: torch's own step is not called (it would raise here)."""
    def refuse(self, closure=None):
        raise AssertionError("torch's SparseAdam step ran")

    monkeypatch.setattr(torch.optim.SparseAdam, "step", refuse)
    start = torch.randn(16, 4)
    param, state = _run(SparseAdam, start, _lookup_grads(16, 4, steps=2, lookups=9))
    assert state["step"] == 2 and not torch.equal(param, start)
    assert param._version == 2  # each update counted, as torch's in-place one is (a saved tensor is not silently stale)


def test_falls_back_to_torch_elsewhere():
    """float64 and maximize run torch's step: the results are torch's exactly."""
    start = torch.randn(16, 4, dtype=torch.float64)
    grads = [g.to(torch.float64) for g in _lookup_grads(16, 4, steps=3, lookups=9)]
    ours, _ = _run(SparseAdam, start, grads)
    ref, _ = _run(torch.optim.SparseAdam, start, grads)
    assert torch.equal(ours, ref)
    grads32 = _lookup_grads(16, 4, steps=3, lookups=9)
    ours, _ = _run(SparseAdam, start.float(), grads32, maximize=True)
    ref, _ = _run(torch.optim.SparseAdam, start.float(), grads32, maximize=True)
    assert torch.equal(ours, ref)


def test_an_empty_gradient_counts_the_step_and_changes_nothing():
    param = torch.nn.Parameter(torch.randn(8, 3))
    before = param.detach().clone()
    optimizer = SparseAdam([param], lr=0.1)
    param.grad = torch.sparse_coo_tensor(torch.zeros(1, 0, dtype=torch.long), torch.zeros(0, 3), (8, 3), check_invariants=True)
    optimizer.step()
    assert optimizer.state[param]["step"] == 1
    assert torch.equal(param.detach(), before)


def test_state_is_interchangeable_with_torch():
    """A checkpoint of either optimizer resumes in the other: the same state, the same continuation."""
    start = torch.randn(32, 6)
    grads = _lookup_grads(32, 6, steps=8, lookups=40, seed=3)
    param_ref = torch.nn.Parameter(start.clone())
    ref = torch.optim.SparseAdam([param_ref], lr=0.01)
    for grad in grads[:4]:
        param_ref.grad = grad.clone()
        ref.step()
    param_ours = torch.nn.Parameter(param_ref.detach().clone())
    ours = SparseAdam([param_ours], lr=0.01)
    ours.load_state_dict(copy.deepcopy(ref.state_dict()))
    for grad in grads[4:]:
        for p, opt in ((param_ref, ref), (param_ours, ours)):
            p.grad = grad.clone()
            opt.step()
    assert ours.state[param_ours]["step"] == ref.state[param_ref]["step"] == 8
    torch.testing.assert_close(param_ours.detach(), param_ref.detach(), rtol=1e-5, atol=1e-6)
    assert set(ours.state_dict()["state"][0]) == set(ref.state_dict()["state"][0])
