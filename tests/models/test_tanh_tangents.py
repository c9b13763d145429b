"""The jet's tanh with tangents: the torch reference against central differences, the numba kernel against the
reference (values, and autograd's gradients whichever outputs the loss reads)."""
import pytest
import torch

from pidg.models.tanh_tangents import tanh_with_tangents, tanh_with_tangents_reference


def _inputs(directions: int = 4, rows: int = 129, width: int = 48, dtype=torch.float32):
    gen = torch.Generator().manual_seed(0)
    z = 2.0 * torch.randn(rows, width, generator=gen, dtype=dtype)
    z[0, :6] = torch.tensor([0.0, -0.0, 1e-8, 12.0, -12.0, 100.0], dtype=dtype)  # zero, tiny, saturated
    dz = torch.randn(directions, rows, width, generator=gen, dtype=dtype)
    grad_a = torch.randn(rows, width, generator=gen, dtype=dtype)
    grad_tangent = torch.randn(directions, rows, width, generator=gen, dtype=dtype)
    return z, dz, grad_a, grad_tangent


def test_reference_tangents_are_directional_derivatives_of_tanh():
    z, dz, _, _ = _inputs(dtype=torch.float64)
    _, tangent = tanh_with_tangents_reference(z, dz)
    h = 1e-6
    central = (torch.tanh(z + h * dz) - torch.tanh(z - h * dz)) / (2 * h)
    torch.testing.assert_close(tangent, central, atol=1e-8, rtol=1e-7)


def test_reference_gradient_matches_central_differences_of_a_loss_on_both_outputs():
    """The second-order term: a loss on the tangents differentiates (1 - tanh^2) with respect to z."""
    z, dz, grad_a, grad_tangent = _inputs(directions=2, rows=4, width=6, dtype=torch.float64)

    def loss(zz: torch.Tensor) -> torch.Tensor:
        a, t = tanh_with_tangents_reference(zz, dz)
        return (a * grad_a).sum() + (t * grad_tangent).sum()

    z_var = z.clone().requires_grad_(True)
    loss(z_var).backward()
    h = 1e-6
    central = torch.zeros_like(z)
    for i in range(z.shape[0]):
        for j in range(z.shape[1]):
            step = torch.zeros_like(z)
            step[i, j] = h
            central[i, j] = (loss(z + step) - loss(z - step)) / (2 * h)
    torch.testing.assert_close(z_var.grad, central, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("reads", ["both", "tangents only", "values only"])
def test_kernel_matches_the_reference(reads, kernel_and_reference):
    z, dz, grad_a, grad_tangent = _inputs()
    read = {"both": (0, 1), "tangents only": (1,), "values only": (0,)}[reads]
    results = kernel_and_reference(tanh_with_tangents, (z, dz), (grad_a, grad_tangent), read)
    for name, ref, got in zip(["a", "tangent", "d z", "d dz"], *results):
        if ref is None or got is None:
            assert ref is None and got is None and name == "d dz" and reads == "values only", name
            continue
        torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-6, msg=name)
    assert torch.equal(results[1][0], torch.tanh(z))  # the values are torch's tanh, bit for bit


def test_bad_shapes_name_both_inputs():
    z, dz, _, _ = _inputs()
    with pytest.raises(ValueError, match=r"z must be \[M, W\] and dz \[K, M, W\]"):
        tanh_with_tangents(z, dz[:, :-1])
