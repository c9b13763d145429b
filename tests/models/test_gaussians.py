"""GaussianModel: kNN scale initialisation, activations, SH schedule, rendering inputs, state_dict round trip."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import io
import math
import time
from pathlib import Path

import pytest
import torch

from pidg.data.scene import Frame, PointCloud, SceneBounds, SceneData
from pidg.models.gaussians import (
    GaussianModel,
    GaussianModelConfig,
    knn_init_scales,
    knn_sq_dists,
    random_init_box,
    subsample_points,
)
from pidg.render import rasterize
from pidg.render.scenes import orbit_camera
from pidg.render.sh import sh_to_rgb


def brute_knn(points: torch.Tensor, k: int) -> torch.Tensor:
    p = points.double()
    d = torch.cdist(p, p, compute_mode="donot_use_mm_for_euclid_dist").square()
    d.fill_diagonal_(math.inf)
    return torch.topk(d, k, dim=1, largest=False).values


CLOUDS = {
    "uniform": lambda g: torch.rand(5000, 3, generator=g) * 2 - 1,
    "surface": lambda g: torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=1),
    # dense clusters plus far outliers: exercises the coarser-grid passes and the brute-force fallback
    "clusters": lambda g: torch.cat(
        [0.02 * torch.randn(4500, 3, generator=g) + torch.randn(9, 3, generator=g).repeat_interleave(500, 0),
         30 * torch.randn(500, 3, generator=g)]
    ),
    # exact duplicates: zero distances must be found, not skipped with the point itself
    "duplicates": lambda g: (torch.rand(1500, 3, generator=g)).repeat(2, 1),
    "flat": lambda g: torch.cat([torch.rand(4000, 2, generator=g), torch.zeros(4000, 1)], dim=1),
}


@pytest.mark.parametrize("name", sorted(CLOUDS))
def test_knn_matches_brute_force(name):
    pts = CLOUDS[name](torch.Generator().manual_seed(0))
    got = knn_sq_dists(pts, 3).double()
    ref = brute_knn(pts, 3)
    torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-9)


def test_knn_small_and_degenerate_clouds():
    torch.testing.assert_close(knn_sq_dists(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]), 3), torch.tensor([[25.0], [25.0]]))
    assert knn_sq_dists(torch.zeros(1, 3), 3).shape == (1, 0)
    assert knn_init_scales(torch.zeros(1, 3)).tolist() == pytest.approx([0.01])
    assert (knn_sq_dists(torch.ones(3000, 3), 3) == 0).all()


def test_knn_init_scales_are_rms_distance():
    pts = CLOUDS["uniform"](torch.Generator().manual_seed(1))
    ref = brute_knn(pts, 3).mean(dim=1).clamp_min(1e-7).sqrt()
    torch.testing.assert_close(knn_init_scales(pts).double(), ref, rtol=1e-4, atol=1e-7)


def test_knn_100k_points_is_fast():
    pts = torch.rand(100_000, 3, generator=torch.Generator().manual_seed(2)) * 2.6 - 1.3
    t0 = time.perf_counter()
    d = knn_sq_dists(pts, 3)
    elapsed = time.perf_counter() - t0
    assert torch.isfinite(d).all() and (d[:, 0] <= d[:, 1]).all() and (d[:, 1] <= d[:, 2]).all()
    idx = torch.arange(0, 100_000, 997)
    ref = torch.cdist(pts[idx].double(), pts.double()).square()
    ref[torch.arange(len(idx)), idx] = math.inf
    torch.testing.assert_close(d[idx].double(), torch.topk(ref, 3, largest=False).values, rtol=1e-4, atol=1e-9)
    assert elapsed < 10.0, f"kNN of 100k points took {elapsed:.1f} s"


def test_from_point_cloud_initialisation():
    gen = torch.Generator().manual_seed(3)
    xyz, rgb = torch.rand(300, 3, generator=gen), torch.rand(300, 3, generator=gen)
    model = GaussianModel.from_point_cloud(PointCloud(xyz, rgb))
    assert len(model) == 300 and model.num_particles == 300
    assert model.particle_index.dtype == torch.int64 and model.particle_index.tolist() == list(range(300))
    shapes = {k: tuple(v.shape) for k, v in model.params.items()}
    assert shapes == {
        "means": (300, 3), "quats": (300, 4), "log_scales": (300, 3), "opacity_logits": (300,), "sh_dc": (300, 1, 3),
        "sh_rest": (300, 15, 3),
    }
    assert all(isinstance(p, torch.nn.Parameter) and p.requires_grad for p in model.params.values())
    torch.testing.assert_close(model.opacities, torch.full((300,), 0.1))
    torch.testing.assert_close(model.quats, torch.tensor([1.0, 0, 0, 0]).expand(300, 4))
    torch.testing.assert_close(model.scales[:, 0], knn_init_scales(xyz))
    assert (model.scales == model.scales[:, :1]).all()  # isotropic
    # the DC term alone reproduces the point colours from any direction
    torch.testing.assert_close(sh_to_rgb(model.sh, torch.randn(300, 3, generator=gen), 0), rgb, atol=1e-6, rtol=0)
    assert (model.params["sh_rest"] == 0).all()
    grey = GaussianModel.from_point_cloud(PointCloud(xyz), GaussianModelConfig(sh_degree=1))
    assert grey.params["sh_rest"].shape == (300, 3, 3)
    torch.testing.assert_close(sh_to_rgb(grey.sh, xyz, 1), torch.full((300, 3), 0.5))


def _scene(points: PointCloud | None) -> SceneData:
    frames = [
        Frame(orbit_camera(8, 8, distance=4.0, azimuth_deg=a, elevation=1.5), 0.0, torch.zeros(8, 8, 3, dtype=torch.uint8))
        for a in range(0, 360, 45)
    ]
    bounds = SceneBounds(torch.tensor([0.0, 0.0, 1.5]), 4.7)
    return SceneData(root=Path("scene"), kind="blender", splits={"train": frames},
                     background=torch.zeros(3), bounds=bounds, time_source="json", points3d=points)


def test_subsample_points_is_a_seeded_subset():
    g = torch.Generator().manual_seed(0)
    cloud = PointCloud(torch.randn(1000, 3, generator=g), torch.rand(1000, 3, generator=g))
    assert subsample_points(cloud, 0, seed=1) is cloud and subsample_points(cloud, 5000, seed=1) is cloud
    a, b = subsample_points(cloud, 300, seed=1), subsample_points(cloud, 300, seed=1)
    assert len(a) == 300 and torch.equal(a.xyz, b.xyz)
    rows = (a.xyz[:, None, :] == cloud.xyz[None, :, :]).all(-1).nonzero()[:, 1]
    assert len(rows.unique()) == 300 and torch.equal(a.rgb, cloud.rgb[rows])
    with pytest.raises(ValueError, match="max_init_points"):
        GaussianModelConfig(max_init_points=-1)


def test_random_initialisation_in_the_box_the_cameras_look_at():
    config = GaussianModelConfig(random_init_points=2000)
    lo, hi = random_init_box(_scene(None), config)
    # the cameras orbit the origin at distance sqrt(4^2 + 1.5^2); the box is centred there, not at the rig's centre
    torch.testing.assert_close(lo + hi, torch.zeros(3), atol=1e-4, rtol=0)
    torch.testing.assert_close(hi - lo, torch.full((3,), 2 * 0.33 * math.hypot(4.0, 1.5)), atol=1e-4, rtol=0)
    model = GaussianModel.from_scene(_scene(None), config)
    assert len(model) == 2000
    assert ((model.means >= lo - 1e-6) & (model.means <= hi + 1e-6)).all()
    again = GaussianModel.from_scene(_scene(None), config)
    torch.testing.assert_close(model.means, again.means)  # seeded
    explicit = GaussianModelConfig(random_init_points=10, random_init_box=((0.0, 0.0, 0.0), (1.0, 2.0, 3.0)))
    assert torch.equal(torch.stack(random_init_box(_scene(None), explicit)), torch.tensor([[0.0, 0, 0], [1.0, 2, 3]]))
    with_points = GaussianModel.from_scene(_scene(PointCloud(torch.rand(50, 3))), config)
    assert len(with_points) == 50


def test_sh_degree_schedule():
    model = GaussianModel.from_points(torch.rand(10, 3), None)
    assert model.active_sh_degree == 0
    assert [model.update_sh_degree(s) for s in (0, 999, 1000, 2500, 3000, 99_000)] == [0, 0, 1, 2, 3, 3]
    small = GaussianModel.from_points(torch.rand(10, 3), None, GaussianModelConfig(sh_degree=1, sh_degree_interval=10))
    assert small.update_sh_degree(100) == 1


def test_render_inputs_feed_rasterize_and_gradients_reach_every_parameter():
    gen = torch.Generator().manual_seed(4)
    model = GaussianModel.from_points(0.5 * torch.randn(200, 3, generator=gen), torch.rand(200, 3, generator=gen))
    model.update_sh_degree(3000)
    with torch.no_grad():
        model.params["sh_rest"].normal_(0, 0.1, generator=gen)
    inputs = model.render_inputs()
    assert inputs["sh_degree"] == 3 and inputs["colors"].shape == (200, 16, 3)
    out = rasterize(**inputs, camera=orbit_camera(32, 24), backend="cpu")
    out.rgb.sum().backward()
    for name, p in model.params.items():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert out.means2d.grad is not None


def test_state_dict_round_trip():
    gen = torch.Generator().manual_seed(5)
    model = GaussianModel.from_points(torch.randn(40, 3, generator=gen), torch.rand(40, 3, generator=gen))
    model.buffers["particle_index"] = torch.arange(40).flip(0) % 7
    model.add_buffer("dynamic", torch.rand(40, generator=gen) > 0.5)
    model.add_param("embedding", torch.randn(40, 8, generator=gen))
    model.update_sh_degree(2100)
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf)

    restored = GaussianModel.from_state_dict(state)
    assert restored.active_sh_degree == 2 and restored.max_sh_degree == 3 and restored.num_particles == 40
    assert set(restored.params) == set(model.params) and set(restored.buffers) == set(model.buffers)
    for k in model.params:
        assert torch.equal(restored.params[k], model.params[k]) and isinstance(restored.params[k], torch.nn.Parameter)
    for k in model.buffers:
        assert torch.equal(restored.buffers[k], model.buffers[k]) and restored.buffers[k].dtype == model.buffers[k].dtype

    # loading into a model of another size, whose parameters a graph still holds (a rolled-back step), gives new
    # Parameter objects that train: reusing the old ones with new .data broke the next backward
    other = GaussianModel.from_points(torch.rand(7, 3), None)
    means_param = other.params["means"]
    stale_graph = (other.sh.sum() + other.means.sum())  # noqa: F841  (kept alive, as an exception's frame would)
    other.load_state_dict(state)
    assert other.params["means"] is not means_param and other.params["means"].shape == (40, 3)
    (other.sh.sum() + other.means.sum()).backward()
    assert other.params["sh_dc"].grad.shape == (40, 1, 3)
    assert torch.equal(other.particle_index, model.particle_index) and other.active_sh_degree == 2
    assert torch.equal(other.buffers["dynamic"], model.buffers["dynamic"])


def test_bad_inputs_raise():
    model = GaussianModel.from_points(torch.rand(5, 3), None)
    with pytest.raises(ValueError, match="rows"):
        model.add_buffer("mask", torch.zeros(4))
    with pytest.raises(ValueError, match="already"):
        model.add_buffer("particle_index", torch.zeros(5))
    with pytest.raises(ValueError, match="empty"):
        GaussianModel.from_points(torch.zeros(0, 3), None)
    with pytest.raises(ValueError, match="sh_degree"):
        GaussianModelConfig(sh_degree=4)
