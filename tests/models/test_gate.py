"""Grid4D's attention gate: the numba kernels against the torch reference (values and autograd's gradients)."""
import pytest
import torch

from pidg.models.deformation.gate import attention, attention_reference, gate, gate_reference


def _inputs(rows: int = 257, width: int = 64):
    gen = torch.Generator().manual_seed(0)
    z_spatial = 4.0 * torch.randn(rows, width, generator=gen)
    z_temporal = torch.randn(rows, width, generator=gen)
    # the odd cases: zeros of both signs, tiny, saturated and huge arguments; the ReLU's kink
    z_spatial[0, :8] = torch.tensor([0.0, -0.0, 1e-8, -1e-8, 30.0, -30.0, 200.0, -200.0])
    z_temporal[1, :3] = torch.tensor([0.0, -0.0, 1e-30])
    return z_spatial, z_temporal, torch.randn(rows, width, generator=gen), torch.randn(rows, width, generator=gen)


@pytest.mark.parametrize("reads", ["both", "gated only", "attention only"])
def test_gate_kernel_matches_the_reference(reads, kernel_and_reference):
    """Values and the gradients of both inputs, whichever outputs the loss reads (autograd sends None for the
    other); the kernel's a = tanh(z / 2) form is within float32 rounding of 2 sigmoid(z) - 1."""
    z_spatial, z_temporal, grad_a, grad_h = _inputs()
    read = {"both": (0, 1), "gated only": (1,), "attention only": (0,)}[reads]
    results = kernel_and_reference(gate, (z_spatial, z_temporal), (grad_a, grad_h), read)
    for name, ref, got in zip(["a", "h", "d z_spatial", "d z_temporal"], *results):
        if got is None or ref is None:
            assert got is None and ref is None and name == "d z_temporal" and reads == "attention only", name
            continue
        torch.testing.assert_close(got, ref, rtol=0, atol=2e-6, msg=name)
    a = results[1][0]
    assert a.abs().max() <= 1.0 and a[0, 6] == 1.0 and a[0, 7] == -1.0  # saturates without overflow


def test_attention_kernel_matches_the_reference(kernel_and_reference):
    z_spatial, _, grad_a, _ = _inputs()
    results = kernel_and_reference(lambda z, kernel: (attention(z, kernel=kernel),), (z_spatial,), (grad_a,), (0,))
    for name, ref, got in zip(["a", "d z"], *results):
        torch.testing.assert_close(got, ref, rtol=0, atol=2e-6, msg=name)
    assert torch.equal(attention_reference(z_spatial), 2.0 * torch.sigmoid(z_spatial) - 1.0)


def test_gate_reference_is_attention_times_relu():
    z_spatial, z_temporal, _, _ = _inputs(5, 8)
    a, h = gate_reference(z_spatial, z_temporal)
    assert torch.equal(h, a * z_temporal.clamp_min(0.0))
    with pytest.raises(ValueError, match="one shape"):
        gate(z_spatial, z_temporal[:, :2])


def test_float64_inputs_take_the_reference():
    z_spatial, z_temporal, _, _ = _inputs(4, 8)
    a, h = gate(z_spatial.double(), z_temporal.double())
    assert a.dtype == h.dtype == torch.float64
    assert torch.equal(a, attention_reference(z_spatial.double()))
