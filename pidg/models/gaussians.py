"""Canonical 3D Gaussians: the parameters the deformation field warps and the rasterizer draws.

Parameters are stored unconstrained (log-scales, opacity logits, unnormalised quaternions) in a plain
``dict[str, nn.Parameter]`` so that the densification strategy can swap rows in and out and keep the optimizers in
step (as gsplat does). Besides the parameters, every Gaussian carries *per-Gaussian buffers*: non-trainable rows that
densification copies to children and drops with pruned Gaussians. ``particle_index`` is always one of them: the
index of the initial particle a Gaussian descends from, which PIDG's index embedding, velocity and stress identity
are keyed on, so it must survive cloning, splitting, pruning and checkpoints.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, Iterable, Mapping

import torch
from torch import Tensor, nn

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, Range, validate_config
from pidg.data.scene import PointCloud, SceneData
from pidg.render.camera import Camera
from pidg.render.sh import num_sh_bases, rgb_to_sh_dc

#: Names of the parameters every model has; other modules may add more with :meth:`GaussianModel.add_param`.
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
PARTICLE_INDEX = "particle_index"
MIN_SQ_DIST = 1e-7  # 3DGS clamps the squared kNN distance here so that duplicate points get a finite scale


@dataclass
class GaussianModelConfig:
    """How Gaussians are initialised and how their colour model grows."""

    sh_degree: Annotated[int, Range(0, 3)] = 3
    """Maximum spherical-harmonics degree of the colours (0..3); coefficient tensors are sized for it."""
    sh_degree_interval: Annotated[int, AT_LEAST_ONE] = 1000
    """The active SH degree rises by one every this many steps (3DGS)."""
    init_opacity: Annotated[float, Range(0, 1, lo_open=True, hi_open=True)] = 0.1
    """Opacity of every initial Gaussian, in (0, 1)."""
    knn_neighbors: Annotated[int, AT_LEAST_ONE] = 3
    """Initial scale = RMS distance to this many nearest neighbours (3DGS's distCUDA2)."""
    random_init_points: Annotated[int, AT_LEAST_ONE] = 100_000
    """Points of the random initialisation, used when the scene has no point cloud (3DGS: 100k in [-1.3, 1.3]^3
    for Blender scenes)."""
    random_init_box: Annotated[tuple[tuple[float, float, float], tuple[float, float, float]], Range()] | None = None
    """World box (min xyz, max xyz) of the random initialisation; none: a cube centred where the training cameras
    look, of half-size random_init_box_fraction x their median distance to that point."""
    random_init_box_fraction: Annotated[float, POSITIVE] = 0.33
    """Half-size of the automatic random-initialisation cube as a fraction of the camera distance (0.33 x 4.0 ~
    1.3 for D-NeRF rigs)."""
    max_init_points: Annotated[int, NON_NEGATIVE] = 0
    """Keep at most this many points of a dataset point cloud, a seeded random subset (0 = all). Dry Ice ships
    100k points: on a CPU a 20-30k subset trains ~3x faster per step and densification adds detail back."""
    seed: Annotated[int, NON_NEGATIVE] = 42
    """Seed of the random initialisation and of the point-cloud subset."""

    def __post_init__(self) -> None:
        validate_config(self)
        if self.random_init_box is not None and not all(lo < hi for lo, hi in zip(*self.random_init_box)):
            raise ValueError(f"GaussianModelConfig.random_init_box must be (min xyz, max xyz) with min < max, got {self.random_init_box}")


def subsample_points(points: PointCloud, max_points: int, seed: int) -> PointCloud:
    """A seeded random subset of at most ``max_points`` points (all of them when ``max_points`` is 0)."""
    if max_points <= 0 or len(points) <= max_points:
        return points
    keep = torch.randperm(len(points), generator=torch.Generator().manual_seed(seed))[:max_points].sort().values
    return PointCloud(points.xyz[keep], None if points.rgb is None else points.rgb[keep])


# ---------------------------------------------------------------------------------------------------------------
# k nearest neighbours without a KD-tree
# ---------------------------------------------------------------------------------------------------------------
def _brute_force_knn(queries: Tensor, query_ids: Tensor, points: Tensor, k: int, max_elements: int = 8_000_000) -> Tensor:
    """Exact k smallest squared distances [Q, k] from ``queries`` to ``points`` excluding each query's own row."""
    out = queries.new_empty(queries.shape[0], k)
    step = max(1, max_elements // max(1, points.shape[0]))
    for s in range(0, queries.shape[0], step):
        q = queries[s : s + step]
        # no matmul trick: |a|^2 + |b|^2 - 2ab loses near-duplicate distances to cancellation
        d = torch.cdist(q, points, compute_mode="donot_use_mm_for_euclid_dist").square_()
        d.scatter_(1, query_ids[s : s + step, None], math.inf)
        out[s : s + step] = torch.topk(d, k, dim=1, largest=False).values
    return out


def _cell_keys(pts: Tensor, lo: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """Linear int64 key of each point's grid cell and the grid size; cells are offset by one so that the
    keys of neighbouring cells (offsets -1..1 per axis) never wrap."""
    cells = torch.floor((pts - lo).double() / h).long() + 1
    dims = cells.max(dim=0).values + 2
    return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2], dims


def knn_sq_dists(points: Tensor, k: int = 3, target_occupancy: float = 1.5, max_pairs: int = 4_000_000) -> Tensor:
    """Squared distances [P, k] (ascending) from every point to its k nearest *other* points, exactly.

    A uniform grid replaces the KD-tree: points are bucketed in cells of size h, each point is compared with the
    points of its 27 surrounding cells (in chunks of at most ``max_pairs`` pairs), and the result is exact whenever
    the k-th distance found is <= h (anything outside the 3x3x3 block is farther than h). Points where it is not
    (sparse regions, outliers) are searched again on grids twice as coarse; brute force finishes any rest. h is
    tuned so that a point's own cell holds about ``target_occupancy`` points, which keeps the work near-linear for
    both volumes and surface-like clouds (100k points: about a second on two cores).
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"knn_sq_dists: points must be [P, 3], got {list(points.shape)}")
    n = points.shape[0]
    k_eff = min(k, n - 1)
    pts = points.detach()
    if k_eff <= 0:
        return pts.new_zeros(n, 0)
    ids = torch.arange(n, device=pts.device)
    if n <= 2048:
        return _brute_force_knn(pts, ids, pts, k_eff)

    lo, hi = pts.min(dim=0).values, pts.max(dim=0).values
    extent = (hi - lo).double()
    diag = float(extent.norm())
    if diag == 0.0:
        return pts.new_zeros(n, k_eff)
    # int64 cell keys must not overflow: at most ~1.5e6 cells per axis.
    h_min = float(extent.max()) / 1.5e6
    volume = float(extent.clamp_min(diag * 1e-3).prod())
    h = max((volume / n * target_occupancy) ** (1.0 / 3.0), h_min)
    key = _cell_keys(pts, lo, h)[0]
    for _ in range(8):
        counts = torch.unique(key, return_counts=True)[1]
        occupancy = float((counts.double() ** 2).sum()) / n  # mean number of points in a point's own cell
        if target_occupancy / 2 <= occupancy <= target_occupancy * 2:
            break
        h_new = max(h * (target_occupancy / occupancy) ** (1.0 / 3.0), h_min)
        if h_new == h:
            break
        h = h_new
        key = _cell_keys(pts, lo, h)[0]

    out = pts.new_full((n, k_eff), math.inf)
    remaining = ids
    for _ in range(12):
        out[remaining] = _grid_pass(pts, lo, h, remaining, k_eff, max_pairs)
        # exact where the k-th neighbour lies within h; also catches inf (fewer than k candidates in the block)
        remaining = remaining[~(out[remaining, -1] <= h * h)]
        if remaining.numel() == 0 or h > float(extent.max()):
            break
        h *= 2.0  # sparse points: search again on a coarser grid, only for them
    if remaining.numel():
        out[remaining] = _brute_force_knn(pts[remaining], remaining, pts, k_eff)
    return out


def _grid_pass(pts: Tensor, lo: Tensor, h: float, query_ids: Tensor, k: int, max_pairs: int) -> Tensor:
    """k smallest squared distances [Q, k] from the query points to the other points in their 27 grid cells."""
    device = pts.device
    key, dims = _cell_keys(pts, lo, h)
    order = torch.argsort(key)
    ukeys, counts = torch.unique_consecutive(key[order], return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    o = torch.tensor([-1, 0, 1], device=device)
    offsets = ((o[:, None, None] * dims[1] + o[None, :, None]) * dims[2] + o[None, None, :]).reshape(-1)  # [27]

    neighbour_keys = key[query_ids, None] + offsets  # [Q, 27]
    slot = torch.searchsorted(ukeys, neighbour_keys).clamp_max(len(ukeys) - 1)
    cell_count = torch.where(ukeys[slot] == neighbour_keys, counts[slot], 0)  # [Q, 27]
    cell_start = starts[slot]
    per_query = cell_count.sum(dim=1)
    ends = torch.cumsum(per_query, 0)

    nq_all = query_ids.shape[0]
    out = pts.new_full((nq_all, k), math.inf)
    s = 0
    while s < nq_all:
        # as many queries as fit in max_pairs (at least one)
        e = int(torch.searchsorted(ends, ends[s] - per_query[s] + max_pairs, right=True))
        e = min(max(e, s + 1), nq_all)
        cnt = cell_count[s:e].reshape(-1)
        seg = torch.repeat_interleave(torch.arange(cnt.numel(), device=device), cnt)
        within = torch.arange(seg.numel(), device=device) - (torch.cumsum(cnt, 0) - cnt)[seg]
        cand = order[cell_start[s:e].reshape(-1)[seg] + within]
        qi = seg // 27  # local query index, non-decreasing
        q = query_ids[s:e][qi]
        d = (pts[q] - pts[cand]).square().sum(dim=-1)
        d = torch.where(cand == q, math.inf, d)
        nq, big = e - s, d.numel()
        pos = torch.arange(big, device=device)
        for r in range(k):  # k rounds of "take each query's minimum, then knock it out"
            m = pts.new_full((nq,), math.inf).scatter_reduce(0, qi, d, "amin")
            out[s:e, r] = m
            if r + 1 < k:
                first = torch.full((nq,), big, device=device).scatter_reduce(0, qi, torch.where(d == m[qi], pos, big), "amin")
                d[first[first < big]] = math.inf
        s = e
    return out


def knn_init_scales(points: Tensor, k: int = 3) -> Tensor:
    """Initial isotropic scale per point [P]: RMS distance to its k nearest neighbours (3DGS's ``distCUDA2``).

    A lone point has nothing to measure against and gets 0.01.
    """
    if points.shape[0] < 2:
        return points.new_full((points.shape[0],), 0.01)
    sq = knn_sq_dists(points, k).mean(dim=1)
    return sq.clamp_min(MIN_SQ_DIST).sqrt()


def _look_at_center(cameras: Iterable[Camera]) -> tuple[Tensor, float] | None:
    """The point closest (least squares) to all optical axes and the median camera distance to it.

    For an orbiting rig this is the object the cameras look at. ``None`` when the axes are nearly parallel
    (forward-facing captures), where the point is undetermined.
    """
    centers, dirs = [], []
    for cam in cameras:
        w2c = cam.world_to_camera.to(torch.float64)
        rot, t = w2c[:3, :3], w2c[:3, 3]
        centers.append(-rot.T @ t)
        dirs.append(rot[2])  # camera +z (forward) in world coordinates
    if len(centers) < 2:
        return None
    c, d = torch.stack(centers), torch.stack(dirs)
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]  # projectors orthogonal to each axis
    a, b = proj.sum(0), (proj @ c[:, :, None]).sum(0).squeeze(-1)
    eig = torch.linalg.eigvalsh(a)
    if float(eig[0]) < 1e-3 * float(eig[-1]):
        return None
    x = torch.linalg.solve(a, b)
    return x.to(torch.float32), float((c - x).norm(dim=1).median())


# ---------------------------------------------------------------------------------------------------------------
# the model
# ---------------------------------------------------------------------------------------------------------------
class GaussianModel:
    """Canonical Gaussians: a dict of parameters plus per-Gaussian buffers (always including ``particle_index``).

    ``params`` and ``buffers`` are mutated in place by densification (rows replaced, dict objects kept), so code
    that holds ``model.params`` sees the current Gaussians. ``num_particles`` is the number of initial particles,
    i.e. the size an index-embedding table needs.
    """

    def __init__(
        self,
        means: Tensor,
        quats: Tensor,
        log_scales: Tensor,
        opacity_logits: Tensor,
        sh_dc: Tensor,
        sh_rest: Tensor,
        particle_index: Tensor | None = None,
        sh_degree: int = 3,
        sh_degree_interval: int = 1000,
        num_particles: int | None = None,
    ) -> None:
        n = means.shape[0]
        k = num_sh_bases(sh_degree)
        expected = {
            "means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,), "sh_dc": (n, 1, 3),
            "sh_rest": (n, k - 1, 3),
        }  # fmt: skip
        given = dict(means=means, quats=quats, log_scales=log_scales, opacity_logits=opacity_logits, sh_dc=sh_dc, sh_rest=sh_rest)
        for name, shape in expected.items():
            if tuple(given[name].shape) != shape:
                raise ValueError(f"GaussianModel: {name} must have shape {list(shape)}, got {list(given[name].shape)}")
        self.params: dict[str, nn.Parameter] = {
            name: nn.Parameter(given[name].detach().to(torch.float32).contiguous()) for name in PARAM_NAMES
        }
        if particle_index is None:
            particle_index = torch.arange(n, device=means.device)
        if tuple(particle_index.shape) != (n,):
            raise ValueError(f"GaussianModel: particle_index must have shape [{n}], got {list(particle_index.shape)}")
        self.buffers: dict[str, Tensor] = {PARTICLE_INDEX: particle_index.to(torch.int64).clone()}
        self.max_sh_degree = sh_degree
        self.sh_degree_interval = sh_degree_interval
        self.active_sh_degree = 0
        self.num_particles = int(num_particles) if num_particles is not None else (int(particle_index.max()) + 1 if n else 0)

    # ---- constructors -------------------------------------------------------------------------------------
    @classmethod
    def from_points(cls, xyz: Tensor, rgb: Tensor | None, config: GaussianModelConfig | None = None) -> "GaussianModel":
        """3DGS initialisation: identity rotations, isotropic kNN scales, colour in the SH DC term, low opacity.

        Points without colour start mid-grey.
        """
        config = config or GaussianModelConfig()
        xyz = xyz.detach().to(torch.float32).clone()  # own the storage: Adam updates parameters in place
        n = xyz.shape[0]
        if n == 0:
            raise ValueError("GaussianModel.from_points: the point cloud is empty")
        rgb = torch.full_like(xyz, 0.5) if rgb is None else rgb.detach().to(torch.float32).clamp(0.0, 1.0)
        log_scales = knn_init_scales(xyz, config.knn_neighbors).log().unsqueeze(-1).repeat(1, 3)
        quats = torch.zeros(n, 4, device=xyz.device)
        quats[:, 0] = 1.0
        logit = math.log(config.init_opacity / (1.0 - config.init_opacity))
        return cls(
            means=xyz,
            quats=quats,
            log_scales=log_scales,
            opacity_logits=torch.full((n,), logit, device=xyz.device),
            sh_dc=rgb_to_sh_dc(rgb).unsqueeze(1),
            sh_rest=torch.zeros(n, num_sh_bases(config.sh_degree) - 1, 3, device=xyz.device),
            sh_degree=config.sh_degree,
            sh_degree_interval=config.sh_degree_interval,
        )

    @classmethod
    def from_point_cloud(cls, cloud: PointCloud, config: GaussianModelConfig | None = None) -> "GaussianModel":
        return cls.from_points(cloud.xyz, cloud.rgb, config)

    @classmethod
    def from_random(
        cls, box_min: Tensor, box_max: Tensor, config: GaussianModelConfig | None = None
    ) -> "GaussianModel":
        """``config.random_init_points`` uniform points with uniform random colours in an axis-aligned box."""
        config = config or GaussianModelConfig()
        gen = torch.Generator().manual_seed(config.seed)
        lo, hi = torch.as_tensor(box_min, dtype=torch.float32), torch.as_tensor(box_max, dtype=torch.float32)
        xyz = lo + (hi - lo) * torch.rand(config.random_init_points, 3, generator=gen)
        rgb = torch.rand(config.random_init_points, 3, generator=gen)
        return cls.from_points(xyz, rgb, config)

    @classmethod
    def from_scene(cls, scene: SceneData, config: GaussianModelConfig | None = None) -> "GaussianModel":
        """From the scene's point cloud if it has one, otherwise random points in a box around the scene."""
        config = config or GaussianModelConfig()
        if scene.points3d is not None and len(scene.points3d) > 0:
            return cls.from_point_cloud(subsample_points(scene.points3d, config.max_init_points, config.seed), config)
        lo, hi = random_init_box(scene, config)
        return cls.from_random(lo, hi, config)

    # ---- sizes and per-Gaussian rows ----------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def particle_index(self) -> Tensor:
        """[N] int64: the initial particle each Gaussian descends from."""
        return self.buffers[PARTICLE_INDEX]

    def add_buffer(self, name: str, values: Tensor) -> None:
        """Register a non-trainable per-Gaussian tensor [N, ...]; densification copies it to children."""
        self._check_rows(name, values)
        self.buffers[name] = values

    def add_param(self, name: str, values: Tensor) -> nn.Parameter:
        """Register an extra trainable per-Gaussian tensor [N, ...]; densification treats it like the others
        (children copy the parent's row). Add it to an optimizer yourself."""
        self._check_rows(name, values)
        self.params[name] = nn.Parameter(values.detach().clone())
        return self.params[name]

    def _check_rows(self, name: str, values: Tensor) -> None:
        if name in self.params or name in self.buffers:
            raise ValueError(f"GaussianModel: {name!r} is already registered")
        if values.ndim == 0 or values.shape[0] != self.num_gaussians:
            raise ValueError(f"GaussianModel: {name!r} must have {self.num_gaussians} rows, got {list(values.shape)}")

    # ---- activated values ---------------------------------------------------------------------------------
    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def quats(self) -> Tensor:
        """[N, 4] unit quaternions (w, x, y, z)."""
        q = self.params["quats"]
        return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.params["log_scales"])

    @property
    def opacities(self) -> Tensor:
        """[N] in (0, 1)."""
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def sh(self) -> Tensor:
        """[N, (max_degree+1)^2, 3] all SH coefficients, DC first."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    # ---- SH schedule --------------------------------------------------------------------------------------
    def update_sh_degree(self, step: int) -> int:
        """Set the active SH degree for a training step: one more band every ``sh_degree_interval`` steps.

        A function of the step rather than a counter, so a resumed run gets the same degree.
        """
        self.active_sh_degree = min(self.max_sh_degree, max(0, step) // self.sh_degree_interval)
        return self.active_sh_degree

    # ---- rendering ----------------------------------------------------------------------------------------
    def render_inputs(self) -> dict[str, Any]:
        """Keyword arguments for :func:`pidg.render.rasterize` (add ``camera=``, ``backend=`` ...).

        A deformation model replaces ``means``/``quats``/``scales`` with its warped values and keeps the rest.
        """
        return {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colors": self.sh,
            "sh_degree": self.active_sh_degree,
        }

    # ---- persistence --------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild the model, as detached tensors and ints (``torch.save``-able)."""
        return {
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "buffers": {k: v.detach().clone() for k, v in self.buffers.items()},
            "active_sh_degree": self.active_sh_degree,
            "max_sh_degree": self.max_sh_degree,
            "sh_degree_interval": self.sh_degree_interval,
            "num_particles": self.num_particles,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict`; the number of Gaussians may differ from the current one.

        Every parameter becomes a new Parameter object (replacing ``.data`` of one that autograd has seen, with
        another shape, breaks the next backward): build the optimizers after loading.
        """
        params, buffers = state["params"], state["buffers"]
        missing = [k for k in PARAM_NAMES if k not in params] + ([PARTICLE_INDEX] if PARTICLE_INDEX not in buffers else [])
        if missing:
            raise KeyError(f"GaussianModel.load_state_dict: missing {missing}")
        n = params["means"].shape[0]
        for name, value in {**params, **buffers}.items():
            if value.shape[0] != n:
                raise ValueError(f"GaussianModel.load_state_dict: {name!r} has {value.shape[0]} rows, means has {n}")
        device = self.device
        for name, value in params.items():
            requires_grad = self.params[name].requires_grad if name in self.params else True
            self.params[name] = nn.Parameter(value.to(device).clone(), requires_grad=requires_grad)
        for name in [k for k in self.params if k not in params]:
            del self.params[name]
        self.buffers.clear()
        self.buffers.update({k: v.to(device).clone() for k, v in buffers.items()})
        self.max_sh_degree = int(state["max_sh_degree"])
        self.sh_degree_interval = int(state.get("sh_degree_interval", self.sh_degree_interval))
        self.active_sh_degree = int(state["active_sh_degree"])
        self.num_particles = int(state["num_particles"])

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Any]) -> "GaussianModel":
        p = state["params"]
        model = cls(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["sh_dc"], p["sh_rest"],
            particle_index=state["buffers"][PARTICLE_INDEX], sh_degree=int(state["max_sh_degree"]),
            num_particles=int(state["num_particles"]),
        )  # fmt: skip
        model.load_state_dict(state)
        return model

    def to(self, device: torch.device | str) -> "GaussianModel":
        """Move in place (new Parameter objects: build optimizers after moving)."""
        self.params.update({k: nn.Parameter(v.detach().to(device), requires_grad=v.requires_grad) for k, v in self.params.items()})
        self.buffers.update({k: v.to(device) for k, v in self.buffers.items()})
        return self


def random_init_box(scene: SceneData, config: GaussianModelConfig) -> tuple[Tensor, Tensor]:
    """The box random initial points are drawn from (see :class:`GaussianModelConfig`)."""
    if config.random_init_box is not None:
        lo, hi = config.random_init_box
        return torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)
    frames = scene.splits.get("train") or next((f for f in scene.splits.values() if f), [])
    found = _look_at_center(f.camera for f in frames)
    if found is not None:
        center, distance = found
        half = config.random_init_box_fraction * distance
    else:  # forward-facing or a single camera: a cube of the camera extent around the rig
        center, half = scene.bounds.center.to(torch.float32), config.random_init_box_fraction * scene.bounds.radius
    return center - half, center + half
