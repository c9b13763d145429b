import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from pidg.models.deformation.base import Bounds
from pidg.models.material_field import MaterialField, MaterialFieldConfig
from pidg.physics import PhysicsConfig

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """../shared/data beside the repository; tests that need it skip cleanly without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


# ---- a tiny material field (tests of the field and of the momentum residual) ---------------------------------------
NUM_PARTICLES = 11
BOX = Bounds((0.5, -0.25, 1.0), (1.5, 1.0, 2.0))


def _tiny_material(**overrides) -> MaterialFieldConfig:
    """A field small enough for float64 finite differences in milliseconds."""
    small = MaterialFieldConfig(
        width=12, depth=2, plane_channels=2, spatial_resolution=5, time_resolution=4, time_frequencies=2,
        embedding_dim=3, velocity_init_scale=1.0, init_std=0.5,
    )
    return dataclasses.replace(small, **overrides)


def _tiny_config(**overrides) -> PhysicsConfig:
    """The residual's settings (CMR on)."""
    return PhysicsConfig(kind="cmr", **overrides)


@pytest.fixture
def tiny_field() -> Callable[..., MaterialField]:
    """Factory: a float64 field in the box centre (0.5, -0.25, 1), half-extent (1.5, 1, 2), with a random (non-zero)
    stress head unless ``zero_stress``; keyword overrides go to its MaterialFieldConfig."""

    def make(seed: int = 0, zero_stress: bool = False, **overrides) -> MaterialField:
        torch.manual_seed(seed)
        field = MaterialField(BOX, NUM_PARTICLES, _tiny_material(**overrides)).double()
        if not zero_stress:
            with torch.no_grad():
                field.head_stress.weight.normal_(0.0, 0.5)
                field.head_stress.bias.normal_(0.0, 0.5)
        return field

    return make


def _random_inputs(m: int, seed: int = 1, spread: float = 1.3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World positions (``spread`` > 1 puts some outside the tiny field's box), times in [0, 1], indices."""
    gen = torch.Generator().manual_seed(seed)
    unit = (torch.rand(m, 3, generator=gen, dtype=torch.float64) * 2 - 1) * spread
    x = torch.tensor(BOX.centre, dtype=torch.float64) + unit * torch.tensor(BOX.half_extent, dtype=torch.float64)
    t = torch.rand(m, generator=gen, dtype=torch.float64)
    index = torch.randint(0, NUM_PARTICLES, (m,), generator=gen)
    return x, t, index


@pytest.fixture
def tiny_config() -> Callable[..., PhysicsConfig]:
    return _tiny_config


@pytest.fixture
def random_inputs() -> Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    return _random_inputs


# ---- a numba kernel against its torch reference ------------------------------------------------------------------
def _kernel_and_reference(fn: Callable[..., tuple[torch.Tensor, ...]], inputs: tuple[torch.Tensor, ...],
                          output_grads: tuple[torch.Tensor, ...], read: tuple[int, ...]) -> list[tuple]:
    """``fn(*inputs, kernel=False)`` then ``kernel=True``, each on fresh leaf copies of ``inputs``, with autograd run
    from the outputs numbered in ``read`` only (the others get no gradient, as when a loss does not read them);
    -> per run (reference first): the outputs, detached, then the inputs' gradients (None where none arrived)."""
    results = []
    for kernel in (False, True):
        leaves = [t.clone().requires_grad_(True) for t in inputs]
        outputs = fn(*leaves, kernel=kernel)
        torch.autograd.backward([outputs[i] for i in read], [output_grads[i] for i in read])
        results.append((*(o.detach() for o in outputs), *(t.grad for t in leaves)))
    return results


@pytest.fixture
def kernel_and_reference() -> Callable[..., list[tuple]]:
    return _kernel_and_reference
