"""The material field's plane lookup: the numba kernel against autograd through the torch reference (float64),
values, derivatives and every gradient, inside the planes and beyond their borders; and the field itself with the
kernel against the field with the reference."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.models.material_field import MaterialField, MaterialFieldConfig
from pidg.models.planes import lookup_planes, plane_lookup


def inputs(m: int = 300, k: int = 3, ra: int = 7, rb: int = 5, c: int = 4, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    planes = torch.randn(k, ra, rb, c, generator=gen)
    # about a fifth of the coordinates lie outside [0, R - 1], where the border cell continues linearly
    pa = torch.rand(m, k, generator=gen) * (ra + 1) - 1.0
    pb = torch.rand(m, k, generator=gen) * (rb + 1) - 1.0
    return planes, pa, pb


def run(fn, planes, pa, pb, upstream):
    leaves = [t.clone().requires_grad_(True) for t in (planes, pa, pb)]
    outs = [o for o in fn(*leaves) if o is not None]
    sum((o * u).sum() for o, u in zip(outs, upstream)).backward()
    return [o.detach() for o in outs], [leaf.grad for leaf in leaves]


@pytest.mark.parametrize("derivatives", [True, False])
def test_the_kernel_matches_autograd_through_the_reference(derivatives):
    planes, pa, pb = inputs()
    gen = torch.Generator().manual_seed(3)
    upstream = [torch.randn(pa.shape[0], 3, 4, generator=gen) for _ in range(3 if derivatives else 1)]
    kernel = lambda *a: lookup_planes(*a, derivatives=derivatives, backend="cpu")  # noqa: E731
    outs, grads = run(kernel, planes, pa, pb, upstream)
    ref_outs, ref_grads = run(plane_lookup, planes.double(), pa.double(), pb.double(), [u.double() for u in upstream])
    for got, want in zip(outs, ref_outs):
        assert got.dtype == torch.float32
        torch.testing.assert_close(got.double(), want, atol=1e-5, rtol=1e-5)
    for name, got, want in zip(("planes", "pa", "pb"), grads, ref_grads):
        torch.testing.assert_close(got.double(), want, atol=1e-4, rtol=1e-5, msg=lambda m, n=name: f"grad {n}: {m}")


@pytest.mark.parametrize("used", [(0,), (1,), (2,), (1, 2)])
def test_unused_outputs_send_no_gradient_and_change_nothing(used):
    """A loss that reads only some of the outputs (the field's forward reads the values only, the jet all three)
    gets the gradients of those: the kernel's skipped terms are exactly the ones whose gradient is absent."""
    planes, pa, pb = inputs(m=64, seed=1)
    leaves = [t.clone().requires_grad_(True) for t in (planes, pa, pb)]
    outs = lookup_planes(*leaves, backend="cpu")
    sum(outs[i].square().sum() for i in used).backward()
    ref = [t.double().requires_grad_(True) for t in (planes, pa, pb)]
    ref_outs = plane_lookup(*ref)
    sum(ref_outs[i].square().sum() for i in used).backward()
    for got, want in zip(leaves, ref):  # the reference leaves an input unconnected (None) where its gradient is 0
        want_grad = torch.zeros_like(want) if want.grad is None else want.grad
        torch.testing.assert_close(got.grad.double(), want_grad, atol=1e-4, rtol=1e-5)


def test_the_value_on_grid_lines_is_the_stored_entry_and_bad_shapes_are_named():
    planes, _, _ = inputs()
    value, _, _ = lookup_planes(planes, torch.tensor([[2.0, 6.0, 0.0]]), torch.tensor([[3.0, 4.0, 0.0]]), backend="cpu")
    torch.testing.assert_close(value[0], torch.stack([planes[0, 2, 3], planes[1, 6, 4], planes[2, 0, 0]]))
    with pytest.raises(ValueError, match=r"pa, pb \[M, K\]"):
        lookup_planes(planes, torch.zeros(4, 2), torch.zeros(4, 2))


def test_the_field_with_the_kernel_matches_the_field_with_the_reference():
    """Forward, jet and the parameters' and positions' gradients of a loss on both: the kernel changes no value."""
    config = MaterialFieldConfig(width=32, plane_channels=4, spatial_resolution=9, time_resolution=6, embedding_dim=8,
                                 velocity_init_scale=1.0)
    torch.manual_seed(0)
    fields = {b: MaterialField(None, 20, MaterialFieldConfig(**{**config.__dict__, "backend": b})) for b in ("cpu", "torch")}
    fields["torch"].load_state_dict(fields["cpu"].state_dict())
    with torch.no_grad():  # a non-zero stress head, so the stress derivatives carry gradients too
        for f in fields.values():
            f.head_stress.weight.copy_(torch.linspace(-1, 1, f.head_stress.weight.numel()).reshape(f.head_stress.weight.shape))
    x = torch.rand(50, 3) * 2.6 - 1.3
    index = torch.arange(50) % 20
    grads = {}
    for name, f in fields.items():
        xx = x.clone().requires_grad_(True)
        v, sigma = f(xx, 0.35, index)
        jet = f.jet(xx, 0.35, index)
        loss = v.square().sum() + sigma.square().sum() + jet.dv_dx.square().sum() + jet.dv_dt.square().sum() + jet.dsigma_dx.square().sum()
        loss.backward()
        grads[name] = [xx.grad] + [p.grad.to_dense() for p in f.parameters()]
    for got, want in zip(grads["cpu"], grads["torch"]):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


def test_the_kernel_gives_the_same_bits_on_any_number_of_threads():
    """The backward sums fixed particle blocks in a fixed order (no atomics): 1 and 2 threads agree bit for bit."""
    import numba

    planes, pa, pb = inputs(m=2000, seed=5)
    upstream = [torch.randn(2000, 3, 4, generator=torch.Generator().manual_seed(6)) for _ in range(3)]
    kernel = lambda *a: lookup_planes(*a, backend="cpu")  # noqa: E731
    before = numba.get_num_threads()
    try:
        results = []
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(threads)
            results.append(run(kernel, planes, pa, pb, upstream))
    finally:
        numba.set_num_threads(before)
    (outs_1, grads_1), (outs_2, grads_2) = results
    assert all(torch.equal(a, b) for a, b in zip(outs_1 + grads_1, outs_2 + grads_2))
