"""The numba hash-grid kernel against the torch reference, and the reference against finite differences."""
import numpy as np
import pytest
import torch

from pidg.models.deformation.hash_grid import (
    GRID4D_TEMPORAL,
    HashGrid,
    HashGridConfig,
    grid_layout,
    hash_encode,
    hash_encode_cpu,
    hash_encode_reference,
    hash_encode_with_smoothness,
    resolve_backend,
    spatial_hash,
)

# non-power-of-two, per-axis resolutions; levels 0-1 dense, 2-4 hashed into 2^10 rows; 3 features per level
MIXED = HashGridConfig(n_levels=5, n_features=3, log2_table_size=10, base_resolution=(3, 5, 2), finest_resolution=(29, 17, 11))


def random_grid(config: HashGridConfig, seed: int = 0, dtype=torch.float32) -> HashGrid:
    grid = HashGrid(config)
    with torch.no_grad():
        grid.table.copy_(torch.rand(grid.table.shape, generator=torch.Generator().manual_seed(seed)) * 2 - 1)
    return grid.to(dtype)


def hard_points(config: HashGridConfig, n_random: int, seed: int = 0) -> torch.Tensor:
    """Random points plus the awkward ones: on cell boundaries of every level, box corners and faces, outside."""
    gen = torch.Generator().manual_seed(seed)
    layout = grid_layout(config)
    pts = [torch.rand(n_random, 3, generator=gen)]
    for lvl in range(layout.n_levels):  # p = u * s + 0.5 on an integer: u = (k - 0.5) / s
        scale = torch.from_numpy(layout.scales[lvl]).to(torch.float32)
        k = torch.randint(1, 40, (8, 3), generator=gen).to(torch.float32)
        pts.append(((k - 0.5) / scale).clamp(0, 1))
    corners = torch.tensor([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    faces = torch.tensor([[0.0, 0.3, 0.7], [0.2, 1.0, 0.5], [0.5, 0.5, 0.0]])
    outside = torch.tensor([[-0.2, 0.5, 0.5], [0.5, 1.3, 0.4], [1.5, -0.5, 2.0], [0.3, 0.6, -1e-3]])
    return torch.cat(pts + [corners, faces, outside])


def test_layout_by_hand():
    # base 2 -> finest 5 over 2 levels, table 2^5 = 32 rows
    layout = grid_layout(HashGridConfig(n_levels=2, n_features=2, log2_table_size=5, base_resolution=2, finest_resolution=5))
    np.testing.assert_allclose(layout.scales, [[1, 1, 1], [4, 4, 4]])  # base * growth^l - 1
    np.testing.assert_array_equal(layout.sizes, [[3, 3, 3], [6, 6, 6]])  # floor(s + 0.5) + 2 vertices per axis
    np.testing.assert_array_equal(layout.hashed, [False, True])  # 27 rows fit in 32, 216 do not
    np.testing.assert_array_equal(layout.offsets, [0, 27, 59])
    # per-axis growth: (8, 8, 8) -> (32, 32, 16) over 32 levels
    temporal = grid_layout(GRID4D_TEMPORAL)
    np.testing.assert_allclose(temporal.scales[0], [7, 7, 7])
    np.testing.assert_allclose(temporal.scales[-1], [31, 31, 15], rtol=1e-6)
    assert not temporal.hashed.any()  # every temporal level fits in 2^19 rows: dense


def test_spatial_hash_by_hand():
    # vertex (1, 2, 3), table 2^19. uint32 products: 2 * 2654435761 = 5308871522 = 1013904226 (mod 2^32),
    # 3 * 805459861 = 2416379583. Low 19 bits: 1013904226 = 455522, 2416379583 = 460479 (mod 2^19), and
    # 1 ^ 455522 ^ 460479 = 128476.
    got = spatial_hash(torch.tensor([1]), torch.tensor([2]), torch.tensor([3]), 2**19)
    assert int(got) == 128476
    # large coordinates: int64 products keep the same low bits as uint32 ones
    gen = torch.Generator().manual_seed(0)
    v = torch.randint(0, 5000, (100, 3), generator=gen)
    got = spatial_hash(v[:, 0], v[:, 1], v[:, 2], 2**10)
    by_hand = [((x * 1) % 2**32 ^ (y * 2654435761) % 2**32 ^ (z * 805459861) % 2**32) % 2**10 for x, y, z in v.tolist()]
    assert got.tolist() == by_hand


def test_kernel_uses_the_hash_rows():
    """A table that is zero except on one hashed row reads back that row's value at its vertex only."""
    config = HashGridConfig(n_levels=1, n_features=1, log2_table_size=6, base_resolution=20, finest_resolution=20)
    layout = grid_layout(config)
    assert layout.hashed[0]
    vertex = (7, 11, 13)
    row = int(spatial_hash(*(torch.tensor([c]) for c in vertex), layout.table_size))
    table = torch.zeros(layout.n_rows, 1)
    table[row] = 1.0
    scale = torch.from_numpy(layout.scales[0])
    u = ((torch.tensor(vertex, dtype=torch.float32) - 0.5) / scale)[None]  # p = u * s + 0.5 = the vertex
    assert float(hash_encode_cpu(u, table, layout)) == pytest.approx(1.0, abs=1e-5)
    assert float(hash_encode_reference(u, table, layout)) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("config", [MIXED, GRID4D_TEMPORAL], ids=["mixed", "grid4d_temporal"])
def test_kernel_matches_reference(config):
    grid = random_grid(config)
    pts = hard_points(config, 9000)  # the forward's tasks are (level, 4096 points): two whole chunks and a partial one
    gen = torch.Generator().manual_seed(3)
    upstream = torch.randn(pts.shape[0], grid.out_dim, generator=gen)

    def run(backend):
        coords = pts.clone().requires_grad_(True)
        grid.table.grad = None
        out = hash_encode(coords, grid.table, grid.layout, backend)
        (out * upstream).sum().backward()
        return out.detach(), coords.grad, grid.table.grad.clone()

    out_k, gc_k, gt_k = run("cpu")
    out_r, gc_r, gt_r = run("torch")
    assert (out_k - out_r).abs().max() < 1e-5
    assert (gt_k - gt_r).abs().max() / gt_r.abs().max() < 1e-4
    assert (gc_k - gc_r).abs().max() / gc_r.abs().max() < 1e-4
    outside = ((pts < 0) | (pts > 1))
    assert outside.any() and (gc_k[outside] == 0).all() and (gc_r[outside] == 0).all()


@pytest.mark.parametrize("config", [MIXED, GRID4D_TEMPORAL], ids=["three_features", "two_features"])
def test_kernel_backward_reads_a_column_block_of_a_wider_gradient(config):
    """Features concatenated with others get a strided gradient (a column block); the kernel reads it in place
    (both of the table gradient's paths: two features per level, and any other count)."""
    grid = random_grid(config)
    pts = hard_points(config, 300)
    gen = torch.Generator().manual_seed(4)
    upstream = torch.randn(pts.shape[0], 3 * grid.out_dim, generator=gen)
    grads = []
    for backend in ("cpu", "torch"):
        coords = pts.clone().requires_grad_(True)
        grid.table.grad = None
        out = hash_encode(coords, grid.table, grid.layout, backend)
        (torch.cat([out.detach(), out, out.detach()], dim=-1) * upstream).sum().backward()
        grads.append((coords.grad, grid.table.grad.clone()))
    (gc_k, gt_k), (gc_r, gt_r) = grads
    assert (gt_k - gt_r).abs().max() / gt_r.abs().max() < 1e-4
    assert (gc_k - gc_r).abs().max() / gc_r.abs().max() < 1e-4


@pytest.mark.parametrize("config", [MIXED, GRID4D_TEMPORAL], ids=["three_features", "two_features"])
def test_smoothness_node_matches_the_reference(config):
    """Grid4D's regulariser on the kernels (one node: the sample's features taken from the pass, N + M points
    encoded, one table gradient) against the torch path that encodes points, sample and copies separately:
    features, the term, and the gradients of the table and of the coordinates (through the features only: the
    sample is detached). Rows repeat and some points lie outside the box."""
    grid = random_grid(config)
    pts = hard_points(config, 400)
    gen = torch.Generator().manual_seed(6)
    rows = torch.cat([torch.randperm(pts.shape[0], generator=gen)[:60], torch.tensor([5, 5, pts.shape[0] - 1])])
    jittered = pts[rows] + (torch.rand(rows.shape[0], 3, generator=gen) * 2 - 1) * 0.05
    upstream = torch.randn(pts.shape[0], grid.out_dim, generator=gen)

    def run(backend):
        coords = pts.clone().requires_grad_(True)
        grid.table.grad = None
        features, term = hash_encode_with_smoothness(coords, jittered, rows, grid.table, grid.layout, backend)
        ((features * upstream).sum() + 3.0 * term).backward()
        return features.detach(), term.detach(), coords.grad, grid.table.grad.clone()

    f_k, term_k, gc_k, gt_k = run("cpu")
    f_r, term_r, gc_r, gt_r = run("torch")
    assert torch.equal(f_k, hash_encode_cpu(pts, grid.table.detach(), grid.layout))
    assert (f_k - f_r).abs().max() < 1e-5
    expected = (hash_encode_reference(jittered, grid.table.detach(), grid.layout)
                - hash_encode_reference(pts[rows], grid.table.detach(), grid.layout)).square().sum()
    assert float(term_r) > 0 and torch.allclose(term_k, expected, rtol=1e-5) and torch.allclose(term_r, expected, rtol=1e-5)
    assert (gt_k - gt_r).abs().max() / gt_r.abs().max() < 1e-4
    assert (gc_k - gc_r).abs().max() / gc_r.abs().max() < 1e-4
    # the term's own table gradient is there (the features' alone would differ)
    grid.table.grad = None
    (hash_encode(pts, grid.table, grid.layout, "cpu") * upstream).sum().backward()
    assert (grid.table.grad - gt_k).abs().max() / gt_k.abs().max() > 1e-3


def test_outside_points_clamp_onto_the_box():
    grid = random_grid(MIXED)
    inside = torch.tensor([[0.0, 0.5, 1.0], [1.0, 1.0, 0.0]])
    outside = torch.tensor([[-0.3, 0.5, 1.7], [4.0, 1.2, -2.0]])
    for backend in ("cpu", "torch"):
        with torch.no_grad():
            assert torch.equal(hash_encode(outside, grid.table, grid.layout, backend), hash_encode(inside, grid.table, grid.layout, backend))


def test_reference_gradients_match_finite_differences():
    config = HashGridConfig(n_levels=3, n_features=2, log2_table_size=6, base_resolution=(2, 3, 2), finest_resolution=(7, 5, 9))
    layout = grid_layout(config)
    assert layout.hashed.any() and not layout.hashed.all()
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(200, 3, generator=gen, dtype=torch.float64) * 0.9 + 0.05
    # keep points away from cell boundaries, where the interpolant's derivative jumps
    p = pts[:, None, :] * torch.from_numpy(layout.scales).double() + 0.5
    frac = p - p.floor()
    pts = pts[((frac > 0.02) & (frac < 0.98)).all(dim=(1, 2))][:15]
    table = torch.rand(layout.n_rows, 2, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda c, t: hash_encode_reference(c, t, layout), (pts.requires_grad_(True), table.requires_grad_(True))
    )


def test_kernel_backward_is_deterministic():
    grid = random_grid(GRID4D_TEMPORAL)
    pts = torch.rand(3000, 3, generator=torch.Generator().manual_seed(1))
    upstream = torch.randn(3000, grid.out_dim, generator=torch.Generator().manual_seed(2))
    grads = []
    for _ in range(2):
        grid.table.grad = None
        (hash_encode_cpu(pts, grid.table, grid.layout) * upstream).sum().backward()
        grads.append(grid.table.grad.clone())
    assert torch.equal(grads[0], grads[1])


def test_kernel_survives_nan_and_empty_inputs():
    grid = random_grid(MIXED)
    pts = torch.tensor([[float("nan"), 0.5, 0.5], [0.2, 0.3, 0.4]])
    out = hash_encode_cpu(pts, grid.table, grid.layout)
    assert torch.isnan(out[0]).any() and torch.isfinite(out[1]).all()
    empty = hash_encode_cpu(torch.zeros(0, 3), grid.table, grid.layout)
    assert empty.shape == (0, grid.out_dim)


def test_backend_selection():
    grid = HashGrid(MIXED)
    assert resolve_backend("auto", grid.table) == "cpu"
    assert resolve_backend("auto", grid.table.double()) == "torch"  # float64 checks use the reference
    assert resolve_backend("auto", torch.empty(1, device="meta")) == "torch"  # any non-CPU device, e.g. CUDA
    with pytest.raises(ValueError):
        resolve_backend("cpu", torch.empty(1, device="meta"))
    with pytest.raises(ValueError):
        hash_encode(torch.rand(4, 2), grid.table, grid.layout)
    out64 = HashGrid(MIXED).double()(torch.rand(4, 3, dtype=torch.float64))
    assert out64.dtype == torch.float64


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_uses_the_reference():
    grid = random_grid(MIXED)
    pts = torch.rand(100, 3)
    expected = hash_encode_reference(pts, grid.table, grid.layout)
    got = grid.cuda()(pts.cuda()).cpu()
    assert (got - expected).abs().max() < 1e-5


def test_gradient_buffers_are_reused_only_when_released():
    grid = random_grid(MIXED)
    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(4))
    upstream = torch.randn(500, grid.out_dim, generator=torch.Generator().manual_seed(5))

    def backward():
        (hash_encode_cpu(pts, grid.table, grid.layout) * upstream).sum().backward()

    backward()
    single = grid.table.grad.clone()
    backward()  # .grad still holds the first buffer: the second pass must not overwrite it
    backward()
    assert torch.allclose(grid.table.grad, 3 * single, rtol=1e-5, atol=1e-6)
    grid.table.grad = None
    backward()
    first = grid.table.grad.data_ptr()
    grid.table.grad = None  # released: the next pass may reuse that memory, zeroed
    backward()
    assert grid.table.grad.data_ptr() == first and torch.equal(grid.table.grad, single)


@pytest.mark.parametrize("workers", [1, 3])
def test_the_kernels_give_the_same_bits_for_any_number_of_workers(monkeypatch, workers):
    """The forward's (level, chunk) tasks and the table gradient's levels are dealt round-robin to the workers
    (``kernel_math.round_robin_workers``); each task is computed whole by one worker, so features and gradients do not
    depend on how many there are (here 1 or 3 against the machine's count), with and without the smoothness term."""
    import pidg.models.deformation.hash_grid as hash_grid

    grid = random_grid(GRID4D_TEMPORAL)
    pts = hard_points(GRID4D_TEMPORAL, 9000)  # two whole chunks of points per level and a partial one
    gen = torch.Generator().manual_seed(8)
    rows = torch.randperm(pts.shape[0], generator=gen)[:700]
    jittered = pts[rows] + (torch.rand(rows.shape[0], 3, generator=gen) * 2 - 1) * 0.01
    upstream = torch.randn(pts.shape[0], grid.out_dim, generator=gen)

    def run():
        results = []
        for smooth in (False, True):
            grid.table.grad = None
            if smooth:
                features, term = hash_encode_with_smoothness(pts, jittered, rows, grid.table, grid.layout, "cpu")
                ((features * upstream).sum() + term).backward()
            else:
                features = hash_encode(pts, grid.table, grid.layout, "cpu")
                (features * upstream).sum().backward()
            results += [features.detach(), grid.table.grad.clone()]
        return results

    default = run()
    monkeypatch.setattr(hash_grid, "round_robin_workers", lambda: workers)
    for a, b in zip(default, run(), strict=True):
        assert torch.equal(a, b)
