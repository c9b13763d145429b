"""The footprint test's numba kernel against its torch reference, and the reference against a brute-force count of
the masked pixel centres inside each box (the renderer-level check is in tests/models/test_dynamic_gaussians.py)."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.render.footprint import footprints_touching, footprints_touching_reference


def boxes(n: int, width: int, height: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres over and around the image (some far outside, some NaN or infinite) and radii from 0 (culled) up."""
    gen = torch.Generator().manual_seed(seed)
    means2d = torch.rand(n, 2, generator=gen) * torch.tensor([width + 60.0, height + 60.0]) - 30.0
    means2d[::23] = float("nan")
    means2d[7::29, 0] = float("inf")
    means2d[11::31, 1] = -1e9
    radii = torch.randint(0, 12, (n, 2), generator=gen)
    return means2d, radii


def brute_force(means2d: torch.Tensor, radii: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The definition, pixel by pixel: a masked pixel centre within the box plus one pixel of slack."""
    ys, xs = mask.nonzero(as_tuple=True)
    centres = torch.stack([xs, ys], dim=-1).to(torch.float64) + 0.5
    out = torch.zeros(means2d.shape[0], dtype=torch.bool)
    for g in range(means2d.shape[0]):
        m, r = means2d[g].double(), radii[g].double()
        if not (torch.isfinite(m).all() and (r > 0).all()) or centres.numel() == 0:
            continue
        out[g] = bool(((centres - m).abs() <= r + 1.0 + 1e-9).all(dim=-1).any())
    return out


@pytest.mark.parametrize("density", [0.0, 0.02, 0.3, 1.0])
def test_the_kernel_matches_the_reference(density):
    width, height = 61, 37  # not multiples of anything
    means2d, radii = boxes(3000, width, height, seed=int(density * 100))
    gen = torch.Generator().manual_seed(1)
    mask = torch.rand(height, width, generator=gen) < density
    got, want = footprints_touching(means2d, radii, mask), footprints_touching_reference(means2d, radii, mask)
    assert torch.equal(got, want)
    if density > 0:
        assert 0 < int(got.sum()) < got.numel()  # a test that can tell a wrong box from a right one


def test_the_reference_finds_the_boxes_that_hold_a_masked_pixel_centre():
    """Conservative by at most the one pixel of slack: never misses a box holding a masked centre, and finds
    nothing the slack does not explain."""
    width, height = 40, 30
    means2d, radii = boxes(400, width, height, seed=3)
    mask = torch.zeros(height, width, dtype=torch.bool)
    mask[5:9, 10:13] = True
    mask[20, 33] = True
    found = footprints_touching_reference(means2d, radii, mask)
    exact = brute_force(means2d, radii, mask)
    assert exact.sum() > 10
    assert not (exact & ~found).any()
    near = brute_force(means2d, radii + 1, mask)  # one more pixel on every side bounds the slack
    assert not (found & ~near).any()


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match=r"means2d and radii \[N, 2\]"):
        footprints_touching(torch.zeros(5, 3), torch.zeros(5, 2), torch.zeros(4, 4, dtype=torch.bool))
