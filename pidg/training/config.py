"""The run configuration: one dataclass per concern, composed into ``TrainConfig`` (saved with every run as
``config.json``; every leaf field is a ``--section.field`` option whose help is the field's docstring)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal, get_args

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, UNIT, Range, validate_config
from pidg.data.scene import DataConfig
from pidg.device import Device, resolve_device
from pidg.flow.config import FlowConfig
from pidg.models.deformation import DeformationConfig, HashGridConfig
from pidg.models.gaussians import GaussianModelConfig
from pidg.models.material_field import MaterialFieldConfig
from pidg.physics.config import PhysicsConfig
from pidg.render import RenderBackend
from pidg.training.densification import DensificationConfig


Preset = Literal["auto", "paper", "cpu", "none"]
DatasetLayout = Literal["dnerf", "pidg", "hypernerf"]
BudgetPolicy = Literal["stop", "fit", "fill"]
MotionStart = Literal["rest", "rigid_tracks"]


@dataclass
class GaussianOptimConfig:
    """Adam learning rates of the Gaussians' parameters (3DGS defaults); positions scale with the scene extent."""

    means_lr: Annotated[float, POSITIVE] = 1.6e-4
    """Initial position learning rate, times the scene extent (3DGS's spatial_lr_scale)."""
    means_lr_final: Annotated[float, POSITIVE] = 1.6e-6
    """Final position learning rate, times the scene extent."""
    means_lr_decay_steps: Annotated[int, NON_NEGATIVE] = 0
    """Steps of the log-linear decay from means_lr to means_lr_final (0: the run's iterations)."""
    quats_lr: Annotated[float, NON_NEGATIVE] = 1e-3
    """Rotation (quaternion) learning rate."""
    log_scales_lr: Annotated[float, NON_NEGATIVE] = 5e-3
    """Log-scale learning rate."""
    opacity_lr: Annotated[float, NON_NEGATIVE] = 5e-2
    """Opacity-logit learning rate."""
    sh_dc_lr: Annotated[float, NON_NEGATIVE] = 2.5e-3
    """Learning rate of the colour's SH DC term."""
    sh_rest_lr: Annotated[float, NON_NEGATIVE] = 2.5e-3 / 20.0
    """Learning rate of the higher SH bands."""
    betas: Annotated[tuple[float, float], Range(0, 1, hi_open=True)] = (0.9, 0.999)
    """Adam's beta1 beta2."""
    eps: Annotated[float, POSITIVE] = 1e-15
    """Adam's epsilon (3DGS: tiny, so that the normalised step is not damped for small-gradient parameters)."""

    def __post_init__(self) -> None:
        validate_config(self)


@dataclass
class OptimConfig:
    """Run length, seed, loss weights and the learning rates of the deformation and material fields."""

    iterations: Annotated[int, AT_LEAST_ONE] = 20_000
    """Training steps; learning-rate schedules span them unless their own length is set."""
    seed: Annotated[int, NON_NEGATIVE] = 42
    """Seed of every random choice of the run (initialisation, frame order, samples)."""
    lambda_dssim: Annotated[float, UNIT] = 0.2
    """lambda_c: weight of D-SSIM against L1 in the photometric loss (3DGS, paper: 0.2)."""
    deformation_lr: Annotated[float, NON_NEGATIVE] = 2e-3
    """Learning rate of the deformation field's networks (paper: 2e-3); hash grids get grid_lr_factor times it."""
    grid_lr_factor: Annotated[float, NON_NEGATIVE] = 10.0
    """Hash grids' learning rate over the networks' (NOTES.md: 10-50x)."""
    deformation_lr_decay_every: Annotated[int, NON_NEGATIVE] = 0
    """Network and field learning rates fall x0.1 per this many steps, applied smoothly (0: the run's iterations)."""
    material_lr: Annotated[float, NON_NEGATIVE] = 2e-3
    """Learning rate of the material field's MLP trunk and heads (paper: 2e-3)."""
    material_grid_lr_factor: Annotated[float, NON_NEGATIVE] = 10.0
    """The material field's planes get material_lr times this (paper: 10-50x)."""
    # Each embedding row only gets a gradient when its particle is sampled (about M / N of the steps), so it gets a
    # larger step than the shared weights.
    material_embedding_lr: Annotated[float, NON_NEGATIVE] = 1e-2
    """Learning rate of the material field's particle-index embedding."""
    lambda_depth: Annotated[float, NON_NEGATIVE] = 0.0
    """Weight of a depth loss against the dataset's depth maps (``depth/``, camera z in world units): the mean relative
    error |d - d_gt| / d_gt of the rendered expected depth over the pixels that have a depth (0: off). A monocular
    video fixes each surface's depth at a time from one view only; measured depth removes that ambiguity."""
    static_warmup: Annotated[int, NON_NEGATIVE] = 0
    """Steps that train the canonical Gaussians only, before the deformation starts."""
    time_curriculum_steps: Annotated[int, NON_NEGATIVE] = 0
    """A time curriculum: over this many steps the training frames are drawn only from a window at the start of the
    recording that grows linearly from ``time_curriculum_start`` of the training times' span to all of it (0: off,
    every frame from the first step). With every time at once, a deformation field can rebuild a far-travelling
    object from other Gaussians at each time instead of carrying one set along (positions right, identity and
    motion lost: the 3D tracking error of ``pidg eval --motion-gt``); grown in time order, it has to follow."""
    time_curriculum_start: Annotated[float, UNIT] = 0.1
    """The curriculum's first window, as a share of the training times' span (read when time_curriculum_steps > 0)."""
    motion_start: MotionStart = "rest"
    """Where the deformation starts. rest: the identity (the paper). rigid_tracks (an extension, for scenes of rigid
    or keyframed bodies; needs the flow on, the dataset's depth maps and motion masks): before step 0 it is fitted to
    the moving surfaces tracked as rigid bodies through the cached optical flow and the depth maps, and to the still
    surface held still (pidg.flow.rigid_tracks; docs/motion.md, "Rigid-body tracks that hold"). Training from rest
    hands a moving body from Gaussian to Gaussian and learns neither its path nor its turn; from a start near the true
    motion the image losses keep it (the generated rigid and kinematic scenes, with grid_lr_factor 1 and
    physics.lambda_kinematic 1: the 3D tracking error about halved or better, +0.45-1.4 dB)."""
    motion_start_steps: Annotated[int, AT_LEAST_ONE] = 3000
    """Steps of the fit motion_start makes (rigid_tracks), at the run's deformation rates and their decay. 3000: with
    the bodies' later-seen sides in the tracks (6100 points on the generated kinematic scene) 1000 steps left the fit
    0.069 world units off, 3000 0.005, and the runs from it better in every val figure on both generated scenes
    (docs/motion.md, "Rigid-body tracks that hold"); ~2 minutes more on a 2-core CPU."""
    lambda_tracks: Annotated[float, NON_NEGATIVE] = 0.0
    """Weight of a tracks term (an extension; needs motion_start rigid_tracks; 0: off): through training, the mean
    absolute position error (world units) of the deformation carrying the points motion_start fitted it to (each
    body's tracked points and the still surface) to their tracks at the step frame's time, on up to
    ``losses.TRACK_POINTS_PER_STEP`` of them a step. The start alone is a place to begin: the image losses then move
    the deformation wherever one view a time cannot see (docs/motion.md, "Holding the tracks")."""
    time_budget_minutes: Annotated[float, POSITIVE] | None = None
    """Training time allowed, in minutes (steps only: evaluation, previews and checkpoint writes are not counted);
    none: no budget. What happens at the budget is time_budget_policy's choice."""
    time_budget_policy: BudgetPolicy = "stop"
    """"stop": stop (with a checkpoint) when the budget is spent, wherever the schedule is (its learning-rate decay may
    not have finished). "fit": once the model's size has settled (after densification and the static/dynamic split,
    or at a tenth of the run without them), measure the step time and shorten the run, never lengthen it, so that
    it ends inside the budget; the learning rates then decay over the shortened run. Two thirds of the way from the
    fit to the run's end the fit is made once more, with the step time measured since, so that a machine whose speed
    drifted still ends the run inside the budget with its schedules complete (the budget itself stops a run that
    slows further). The run's length then depends on the machine's speed (it is logged, saved in the
    checkpoint's config and in train_summary.json as ``schedule_fit``; give --optim.iterations with
    --optim.time_budget_minutes none to repeat a run exactly). "fill": as "fit", and a machine faster than the
    planned run needs lengthens it as well, up to time_budget_max_stretch times its planned steps, so that the
    budget buys steps instead of ending early."""
    time_budget_max_stretch: Annotated[float, AT_LEAST_ONE] = 1.5
    """time_budget_policy "fill": the longest a run is made, as a multiple of its planned iterations (a bound for
    machines much faster than the budget assumes: a GPU would otherwise train many times the planned steps; the cpu
    preset's D-NeRF schedule sets its own, CPU_DNERF_SCHEDULE's, sized for its 30 minutes: raise it with a longer
    budget)."""
    dynamic_vote: Annotated[float, UNIT] = 0.4
    """Static/dynamic decoupling: a Gaussian is dynamic if inside the motion mask in more than this share of the
    training views that see it."""
    motion_split_px: Annotated[float, NON_NEGATIVE] = 2.0
    """Static/dynamic decoupling of data without motion masks (D-NeRF, HyperNeRF): a Gaussian counts as moving in a
    training view when the deformation puts its centre at least this many pixels from where its time-averaged
    position projects (dynamic: moving in more than dynamic_vote of the views that see it); 0: no split without masks."""
    max_rollbacks: Annotated[int, NON_NEGATIVE] = 3
    """A step with a non-finite loss, gradient or parameter rolls the run back to its last good checkpoint, at most
    this many times; then training stops with a clear message (0: stop at the first)."""
    rollback_lr_factor: Annotated[float, Range(0, 1, lo_open=True)] = 0.5
    """Every learning rate is multiplied by this at each rollback (a smaller step through the divergence)."""

    def __post_init__(self) -> None:
        validate_config(self)


@dataclass
class OutputConfig:
    """Where a run writes, and how often."""

    dir: Path = Path("outputs/run")
    """The run folder: config.json, checkpoint.pt, tensorboard/, train_summary.json."""
    checkpoint_every: Annotated[int, NON_NEGATIVE] = 1000
    """Steps between checkpoints (0: only at the end); a checkpoint is always written when training stops."""
    log_every: Annotated[int, AT_LEAST_ONE] = 25
    """Steps between logged scalars (TensorBoard, history)."""
    preview_every: Annotated[int, NON_NEGATIVE] = 1000
    """Steps between TensorBoard image previews of a training view (0: none)."""
    progress: bool = True
    """Show a tqdm progress bar."""

    def __post_init__(self) -> None:
        validate_config(self)


@dataclass
class TrainConfig:
    """Everything a run depends on."""

    data: DataConfig = field(default_factory=lambda: DataConfig(path=""))
    """The dataset."""
    gaussians: GaussianModelConfig = field(default_factory=GaussianModelConfig)
    """Initialisation of the canonical Gaussians."""
    gaussian_optim: GaussianOptimConfig = field(default_factory=GaussianOptimConfig)
    """Learning rates of the Gaussians."""
    densify: DensificationConfig = field(default_factory=DensificationConfig)
    """Adaptive density control."""
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """The deformation field."""
    material: MaterialFieldConfig = field(default_factory=MaterialFieldConfig)
    """The material field (built when physics or flow needs it)."""
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    """The momentum-residual loss."""
    flow: FlowConfig = field(default_factory=FlowConfig)
    """The flow-matching loss and its optical flow."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Run length, loss weights, network learning rates."""
    output: OutputConfig = field(default_factory=OutputConfig)
    """The run folder."""
    device: Device = "auto"
    """Where everything computes: cuda (an NVIDIA GPU, rendering with gsplat), cpu (pidg's numba kernels), auto (CUDA
    when available). Asking for cuda without one is an error, never a silent fall-back."""
    backend: RenderBackend = "auto"
    """Rasterizer: cpu (numba kernel), gsplat (CUDA), torch (the readable reference, any device; also switches the
    SSIM loss to its torch form), auto (gsplat on CUDA, cpu on a CPU)."""
    cpu_torch_threads: Annotated[int, NON_NEGATIVE] = 1
    """Threads for torch's own operations while a CPU run trains (0: torch's default, one per core); pidg's numba
    kernels keep theirs (one per core) either way. 1 by default: on the 2-core machine this was measured on, each
    parallel torch operation paid ~0.1 ms of thread wake-up (OMP_WAIT_POLICY=PASSIVE), more than most of a step's
    small operations compute, and one thread made the step x1.10 (base) and x1.16 (full method) faster although its
    matrix products ran x1.3-1.5 slower (which ``cpu_matmul_threads`` gives back). Restored when training returns."""
    flush_denormals: bool = True
    """Flush denormal floats (magnitudes below 1.2e-38) to zero while training (``torch.set_flush_denormal``: the x86
    FTZ/DAZ modes of the training thread, where the optimisers run; restored when training returns). Adam's first
    moment of an entry whose gradient stays exactly zero (a hash-table row no Gaussian reaches, a weight behind an
    idle ReLU unit) decays by 0.9 a step into the denormal range, where 1-4 units of the last place are fixed points
    of that decay (round to nearest) and never reach zero: a default bouncingballs run ended with 31-49 % of its
    hash tables' moments denormal, and the processor's slow path on them tripled the optimiser's time (24-26 against
    8.5 ms a step, whole step x1.14-1.22, measured resuming that run). The flushed values are below any update's
    resolution: an entry's update moves by under 1e-38 times the learning rate."""
    cpu_matmul_threads: Annotated[int, NON_NEGATIVE] = 0
    """Threads for the networks' matrix products (forward and backward) while a CPU run trains with
    ``cpu_torch_threads`` (0: torch's count when training starts, by default one per core): products parallelise
    where small operations do not (:mod:`pidg.models.parallel_linear`)."""
    preset: Preset = field(default="none", metadata={"command_line_default": "auto"})
    """Defaults the other values start from, applied before every other option: cpu (model sizes for a CPU step),
    paper (the published schedule and sizes for the dataset's kind), auto (paper on CUDA, else cpu), none (the
    values as listed here). The commands apply auto unless told; config.json records the preset applied."""

    def __post_init__(self) -> None:
        validate_config(self)

    @property
    def needs_material_field(self) -> bool:
        """The momentum residual and the flow loss both need velocities."""
        return self.physics.enabled or self.flow.enabled


#: What a variant without LPFM sets: no flow loss, and nothing else made from the optical flow either (the rigid
#: tracks are chained through it, so a base config's ``optim.motion_start rigid_tracks`` and tracks term go with it).
#: The defaults already are so; a base config that tracks bodies gets its w/o-LPFM row without the flow's tracks.
WITHOUT_FLOW: dict[str, str] = {"flow.kind": "none", "optim.motion_start": "rest", "optim.lambda_tracks": "0"}

#: The paper's ablation rows (and two more), each a set of option overrides on one base config: rows differ
#: only by these options.
ABLATION_VARIANTS: dict[str, dict[str, str]] = {
    "base": {"physics.kind": "none", **WITHOUT_FLOW},  # PIDG w/o (CMR + LPFM)
    "cmr": {"physics.kind": "cmr", **WITHOUT_FLOW},  # PIDG w/o LPFM
    "full": {"physics.kind": "cmr", "flow.kind": "lpfm"},  # PIDG
    "nostress": {"physics.kind": "cmr", "material.stress": "false", **WITHOUT_FLOW},  # sigma == 0 ablation
    "lpfm": {"physics.kind": "none", "flow.kind": "lpfm"},  # flow matching without the momentum residual
    # the paper's plug-in rows: the material field with L_CMR on another deformation network (Deformable-3DGS's MLP),
    # trained as that method is: the Gaussians fit a static scene first, then the MLP at a lower rate. Without the
    # warm-up the MLP learns within ~20 steps a global translation that moves the random-init floaters, and with them
    # every Gaussian, out of view (bouncingballs 200x200: mean displacement ~2,000 world units at lr 2e-3, ~10 at 1e-4).
    "mlp": {"deformation.kind": "mlp", "optim.deformation_lr": "1e-4", "optim.static_warmup": "500",
            "physics.kind": "none", **WITHOUT_FLOW},
    "mlp_cmr": {"deformation.kind": "mlp", "optim.deformation_lr": "1e-4", "optim.static_warmup": "500",
                "physics.kind": "cmr", **WITHOUT_FLOW},
}

#: The cpu preset's schedule for D-NeRF scenes (``layout`` "dnerf"), chosen on the validation split of bouncingballs
#: and jumpingjacks at 400x400 (docs/cpu-quality.md): densification until 5000 with an opacity reset every 2000
#: steps leaves 3000 steps to recover from each reset; the earlier 3600-step schedule densified until 2000 with a
#: reset at 1000, whose pruning took 22k Gaussians down to 4k and left bouncingballs blurred (33.4 dB on val; 36.2
#: with this schedule at 16 temporal cells). Uncapped, lego grew past 120k Gaussians (1.5 it/s): densification stops
#: adding at 30k. The temporal grids' finest resolution along t was first 32 here (16 elsewhere), chosen on the val
#: split of all three scenes: D-NeRF scenes have 50-200 training times, and at 16 cells a bouncing ball's position
#: between them was blurred (val PSNR at 16 / 32 / 64 cells: bouncingballs 36.2 / 39.8 / 38.7, jumpingjacks 34.1 /
#: 34.0 / 31.9, lego 26.3 / 26.7 / 26.3). 12000 steps rather than 8000 (learning rates over the longer run;
#: densification as above): val PSNR bouncingballs 39.63 vs 39.75, jumpingjacks 34.98 vs 34.04, lego 26.90 vs 26.67,
#: in 20-26 minutes. It is 64 cells along t since the warp's translation and log-scale change are soft-bounded (1 box
#: half-extent, e^2): the field no longer throws Gaussians tens of half-extents away early in a run (what collapsed
#: jumpingjacks at 64 cells once a NaN stopped rolling it back); val PSNR against 32 cells unbounded: bouncingballs
#: 40.17 vs 39.63 (12000 steps), jumpingjacks 34.61 vs 34.04 and lego 26.69 vs 26.67 (8000 steps).
#: The cpu preset's share of the flow loss's tiles read per step (``FlowConfig.tile_fraction``; the paper preset reads
#: all): half a band of tiles takes the full method's step from x1.61 to x1.48 of the base step (bouncingballs, 18k
#: trained Gaussians, 400x400), and on the three scenes with true motion (the demo, make-scene kinematic and rigid)
#: PSNR and flow errors moved by less than one run's own noise (docs/cpu-speed.md).
#: The schedule is fitted to a 30-minute budget (``OptimConfig.time_budget_policy`` "fill"): the same 12000 steps took
#: 20-28 minutes on one processor of this machine and 31.6-39.5 on another, so a fixed count cannot promise the
#: budget; fitted, a slow machine shortens the run once the model's size settles, and a fast one lengthens it (up
#: to a bound) to use the budget: bouncingballs, seed 42, the same run to step 5200 (the fit), then 12000 or 14633
#: steps: val PSNR 39.92 -> 40.99; the longer run fits the first quarter of the recording (training views at
#: t < 0.2: 37.3 / 36.0 -> 41.3 / 43.1 dB), where the 12000-step model still lagged the balls' fall by 1-2 frames.
#: The bound on that lengthening was x2: with a x1.10 faster step the x1.5 bound (18000 steps) cut runs minutes short
#: of the budget, and two seeds run again to x2 (the same runs to the fit) scored higher on val: bouncingballs seed 8
#: 18000 -> 20304 steps, 41.06 -> 41.24 dB; seed 9 17891 -> 22873 steps, 41.05 -> 41.53 (docs/cpu-quality.md).
#: Now x3: on a faster processor every scene reached the x2 bound 2-13 minutes inside the budget, and the same runs to
#: the fit lengthened to x3 scored higher on val: bouncingballs seed 42 24000 -> 36000 steps, 41.30 -> 42.00 dB; lego
#: seed 42 24000 -> 36000, 28.16 -> 28.33 (docs/cpu-quality.md). A run too slow for 24000 steps in the budget runs
#: as before.
CPU_FLOW_TILE_FRACTION = 0.5
CPU_DNERF_SCHEDULE = {"iterations": 12_000, "densify_start": 300, "densify_stop": 5000, "opacity_reset_every": 2000,
                      "random_init_points": 20_000, "max_gaussians": 30_000, "temporal_finest": (32, 32, 64),
                      "max_translation": 1.0, "max_log_scale_change": 2.0,
                      "time_budget_minutes": 30.0, "time_budget_policy": "fill", "time_budget_max_stretch": 3.0}


def apply_preset(config: TrainConfig, preset: Preset = "auto", layout: DatasetLayout | None = None) -> TrainConfig:
    """The config with a preset's values (explicit options are applied after this, so they win).

    "cpu": model sizes for a CPU step, without measurable quality loss on D-NeRF at 400x400: hash tables of 2^16 /
    2^15 entries (Adam touches every entry every step), spatial resolution up to 1024, 64-wide layers, and 16
    instead of 32 levels on the temporal grids; a 64-wide material field (the 256-wide one's matrix products were
    most of what the full method adds to a step; on the demo scene, full method, 1200 steps: 24.03 against 23.76 dB,
    velocity-flow error 1.00 against 1.03 px, x1.30 the step rate); the flow loss on half of its tiles per step
    (``CPU_FLOW_TILE_FRACTION``); on D-NeRF scenes also a schedule for a CPU's budget
    (``CPU_DNERF_SCHEDULE``: 12000 steps, densification 300-5000 up to 30k Gaussians, opacity reset every 2000, 20k
    random points, temporal grids up to 64 cells along t, the warp's translation and log-scale change soft-bounded,
    shortened where needed to end inside 30 minutes of training).
    Their resolutions only grow from 8 to 32 (16 along t), so 32 levels sit 4.6% apart; 16 levels (9% apart) cover
    the same range at half the lookups (up to 64 along t on D-NeRF: 6.9% and 14.9% apart), and the temporal grids were
    the largest item of a CPU step (63 of ~260 ms at 23k Gaussians, 400x400).
    "paper": the published model sizes (the defaults) and schedule (paper Sec. 5 and supp. A, D): 50k iterations
    on synthetic scenes (``layout`` dnerf or pidg) and 40k on real ones (hypernerf), densification until 30k, the
    network learning rates x0.1 every 20k steps, decoder depth 1 on real scenes, and the 0.015 scale threshold for
    pruning on PIDG-style scenes. Without a ``layout`` it takes the synthetic schedule.
    "auto": "paper" when ``config.device`` resolves to CUDA, else "cpu". "none": nothing.
    """
    if preset == "auto":
        preset = "paper" if resolve_device(config.device).type == "cuda" else "cpu"
    if preset not in get_args(Preset):
        raise ValueError(f"unknown preset {preset!r}: expected one of {', '.join(get_args(Preset))}")
    if preset == "cpu":
        grid4d = replace(
            config.deformation.grid4d,
            spatial_grid=HashGridConfig(16, 2, 16, 16, 1024),
            temporal_grid=HashGridConfig(16, 2, 15, (8, 8, 8), (32, 32, 16)),
            width=64,
        )
        config = replace(config, deformation=replace(config.deformation, grid4d=grid4d), material=replace(config.material, width=64),
                         flow=replace(config.flow, tile_fraction=CPU_FLOW_TILE_FRACTION))
        if layout == "dnerf":
            temporal = replace(grid4d.temporal_grid, finest_resolution=CPU_DNERF_SCHEDULE["temporal_finest"])
            bounded = replace(grid4d, temporal_grid=temporal, max_translation=CPU_DNERF_SCHEDULE["max_translation"],
                              max_log_scale_change=CPU_DNERF_SCHEDULE["max_log_scale_change"])
            config = replace(
                config,
                deformation=replace(config.deformation, grid4d=bounded),
                optim=replace(config.optim, iterations=CPU_DNERF_SCHEDULE["iterations"],
                              time_budget_minutes=CPU_DNERF_SCHEDULE["time_budget_minutes"],
                              time_budget_policy=CPU_DNERF_SCHEDULE["time_budget_policy"],
                              time_budget_max_stretch=CPU_DNERF_SCHEDULE["time_budget_max_stretch"]),
                densify=replace(config.densify, start=CPU_DNERF_SCHEDULE["densify_start"], stop=CPU_DNERF_SCHEDULE["densify_stop"],
                                opacity_reset_every=CPU_DNERF_SCHEDULE["opacity_reset_every"],
                                max_gaussians=CPU_DNERF_SCHEDULE["max_gaussians"]),
                gaussians=replace(config.gaussians, random_init_points=CPU_DNERF_SCHEDULE["random_init_points"]),
            )
    elif preset == "paper":
        real = layout == "hypernerf"
        config = replace(
            config,
            optim=replace(config.optim, iterations=40_000 if real else 50_000, deformation_lr_decay_every=20_000),
            densify=replace(config.densify, stop=30_000, prune_world_scale=0.015 if layout == "pidg" else config.densify.prune_world_scale),
            deformation=replace(config.deformation, grid4d=replace(config.deformation.grid4d, decoder_depth=1 if real else 0)),
        )
    return replace(config, preset=preset)


#: How ``describe_schedule`` says what each budget policy does (``{}``: the longest stretch).
_BUDGET_POLICY_WORDS = {
    "stop": "the run stops there",
    "fit": "shortened to fit it if too slow",
    "fill": "the run fitted to it: shortened if too slow, lengthened up to x{:g} if fast",
}


def describe_schedule(config: TrainConfig) -> str:
    """One line with the values a preset sets, for the run's log."""
    g, o, d = config.deformation.grid4d, config.optim, config.densify
    decay = o.deformation_lr_decay_every or o.iterations
    return (
        f"preset {config.preset}: {o.iterations} iterations, densification {d.start}-{d.stop} every {d.every} "
        f"(opacity reset every {d.opacity_reset_every}, prune scale {d.prune_world_scale}), network learning rates x0.1 per {decay} steps; {config.deformation.kind} "
        f"deformation, Grid4D tables 2^{g.spatial_grid.log2_table_size}/2^{g.temporal_grid.log2_table_size}, "
        f"{g.temporal_grid.n_levels} temporal levels up to {g.temporal_grid.finest_resolution}, width {g.width}, decoder depth {g.decoder_depth}"
        + (f"; flow loss on {config.flow.tile_fraction:g} of its tiles a step" if config.flow.enabled else "")
        + (f"; time curriculum over {o.time_curriculum_steps} steps from {o.time_curriculum_start:g} of the recording"
           if o.time_curriculum_steps else "")
        + (f"; a {o.time_budget_minutes:g}-minute budget ({_BUDGET_POLICY_WORDS[o.time_budget_policy].format(o.time_budget_max_stretch)})"
           if o.time_budget_minutes is not None else "")
    )
