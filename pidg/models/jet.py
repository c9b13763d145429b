"""A field's values and first derivatives at M points ("jet"), and a generic way to get one from any function.

The residual (``pidg.physics.cmr``) only needs v, sigma and their first derivatives, so it takes a ``FieldJet``:
the material field supplies one from its hand-written tangents, tests and benchmarks supply one from analytic
fields through ``jet_from_function`` (torch.func forward mode), and the two can be compared.
"""
from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

#: the order of the six independent stress components, as the material field outputs them
STRESS_COMPONENTS = ("xx", "yy", "zz", "xy", "xz", "yz")
#: SYMMETRIC_INDEX[j][i]: which of the six components is sigma_ji
SYMMETRIC_INDEX = ((0, 3, 4), (3, 1, 5), (4, 5, 2))

FieldFunction = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]


@dataclass
class FieldJet:
    """Velocity and stress at M points with their derivatives.

    Units: x in world units; t is the dataset time in [0, 1] (the field's input); v in world units per physics
    time unit (:class:`pidg.models.time_axis.TimeAxis`), so ``dv_dt`` is per unit of t and the residual divides it
    by ``TimeAxis.physics_per_dataset``; sigma in (world units / physics time unit)^2 at unit density.

    Layout (Jacobian convention: output index first, input index last):
      v          [M, 3]
      sigma      [M, 6]     (xx, yy, zz, xy, xz, yz)
      dv_dx      [M, 3, 3]  dv_dx[m, j, i] = d v_j / d x_i
      dv_dt      [M, 3]
      dsigma_dx  [M, 6, 3]  dsigma_dx[m, c, i] = d sigma_c / d x_i
    """

    v: Tensor
    sigma: Tensor
    dv_dx: Tensor
    dv_dt: Tensor
    dsigma_dx: Tensor

    def __post_init__(self) -> None:
        m = self.v.shape[0] if self.v.dim() == 2 else -1
        expected = {"v": (m, 3), "sigma": (m, 6), "dv_dx": (m, 3, 3), "dv_dt": (m, 3), "dsigma_dx": (m, 6, 3)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                got = {k: list(getattr(self, k).shape) for k in expected}
                raise ValueError(f"FieldJet: expected shapes {expected} with M rows, got {got}")

    @property
    def num_points(self) -> int:
        return int(self.v.shape[0])


def stress_matrix(sigma: Tensor) -> Tensor:
    """Six components [..., 6] -> the symmetric 3x3 stress [..., 3, 3]."""
    index = torch.tensor(SYMMETRIC_INDEX, device=sigma.device)
    return sigma[..., index]


def jet_from_function(fn: FieldFunction, x: Tensor, t: Tensor | float) -> FieldJet:
    """FieldJet of ``fn(x [M, 3], t [M]) -> (v [M, 3], sigma [M, 6])`` by forward-mode AD (``torch.func.jvp``).

    ``fn`` must treat rows independently (row m of the outputs depends only on row m of the inputs), so one jvp
    per input direction, with that direction's tangent set on every row, yields every row's derivative at once:
    four jvps in all. Used for analytic fields in tests and to cross-check the material field's own tangents.
    """
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"jet_from_function: x must be [M, 3], got {list(x.shape)}")
    times = torch.as_tensor(t, dtype=x.dtype, device=x.device)
    times = times.expand(x.shape[0]) if times.numel() == 1 else times.reshape(x.shape[0])
    zeros_x, zeros_t = torch.zeros_like(x), torch.zeros_like(times)
    derivatives = []
    for k in range(4):
        tx, tt = zeros_x.clone(), zeros_t.clone()
        if k < 3:
            tx[:, k] = 1.0
        else:
            tt.fill_(1.0)
        with warnings.catch_warnings():  # torch's first forward-mode call scripts decompositions with a deprecated API
            warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*", category=DeprecationWarning)
            (v, sigma), (dv, dsigma) = torch.func.jvp(fn, (x, times), (tx, tt))
        derivatives.append((dv, dsigma))
    return FieldJet(
        v=v,
        sigma=sigma,
        dv_dx=torch.stack([derivatives[i][0] for i in range(3)], dim=-1),
        dv_dt=derivatives[3][0],
        dsigma_dx=torch.stack([derivatives[i][1] for i in range(3)], dim=-1),
    )
