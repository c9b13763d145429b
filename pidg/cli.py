"""The ``pidg`` command: a thin layer that parses arguments and calls library functions."""
from __future__ import annotations

from pidg import _env  # noqa: F401  (must precede torch)

import argparse
import contextlib
import json
import logging
import sys
import warnings
from pathlib import Path
from typing import Iterator, NoReturn, get_args

from tqdm.contrib.logging import logging_redirect_tqdm

from pidg.bench.cmr import VARIANTS as CMR_BENCH_VARIANTS
from pidg.bench.cmr import CMRBenchConfig, run_cmr_bench
from pidg.bench.executors import ExecutorName, make_executor
from pidg.bench.motion_fit import MotionFitConfig, run_motion_fit
from pidg.bench.rigid_tracks import run_rigid_tracks_bench
from pidg.bench.quality import run_quality_bench
from pidg.bench.suite import SUITES, discover_scenes, run_suite, suite_config
from pidg.bench.render import RenderBenchCase, RenderBenchConfig, run_render_bench
from pidg.bench.step import run_step_bench
from pidg.bench.views import run_views_bench
from pidg.checkpoint import CHECKPOINT_FILE, CONFIG_FILE
from pidg.config_tools import MISSING_OPTION, add_config_arguments, apply_overrides, load_config, overrides_from_args
from pidg.data import dataset_layout, detect_format, load_scene, parse_downscale
from pidg.export import check_time, export_ply, export_ply_sequence
from pidg.device import Device, resolve_device
from pidg.flow import run_preprocess
from pidg.flow.config import FlowKind
from pidg.metrics import NetName
from pidg.models.material_field import Activation, MaterialFieldConfig
from pidg.physics import PhysicsConfig, PhysicsKind
from pidg.pipeline import DEMO_DEPTH_WEIGHT, evaluate_run, render_run, run_demo
from pidg.report import build_report
from pidg.scenes import KINDS as SCENE_KINDS
from pidg.scenes import TEXTURES as SCENE_TEXTURES
from pidg.scenes import SceneOptions, make_scene, parse_resolution, summary_lines
from pidg.viewer import Quality, ViewerOptions, serve_run
from pidg.viewer.server import measure_run
from pidg.training.config import ABLATION_VARIANTS, TrainConfig, apply_preset
from pidg.training.run_folder import claim_run_folder, resume_config
from pidg.training.trainer import Trainer


def _train_config(args: argparse.Namespace, data_path: str | None = None) -> TrainConfig:
    """The run config: a saved config.json (already resolved: no preset), or the defaults with ``--preset`` (auto
    unless given) for the device and the dataset's layout (``data_path`` when --data.path is not given); then
    every --section.field option."""
    overrides = overrides_from_args(args)
    if getattr(args, "config", None):
        return apply_overrides(load_config(TrainConfig, Path(args.config)), overrides)
    first = {k: overrides[k] for k in ("device", "data.path", "preset") if k in overrides}
    base = apply_overrides(TrainConfig(), first)
    path = Path(str(base.data.path) or data_path or "")
    layout = dataset_layout(path) if str(path) not in ("", ".") and path.is_dir() else None
    base = apply_preset(base, base.preset if "preset" in overrides else "auto", layout)  # type: ignore[arg-type]
    return apply_overrides(base, {k: v for k, v in overrides.items() if k != "preset"})


def _cmd_train(args: argparse.Namespace) -> int:
    if args.resume:
        trainer = _resumed_trainer(args)
    else:
        config = _train_config(args)
        if not str(config.data.path):
            raise ValueError("give the dataset folder with --data.path DIR")
        detect_format(config.data.root)  # a missing or unknown dataset folder fails before the run folder is touched
        claim_run_folder(config.output.dir, overwrite=args.overwrite)  # before loading the images: fail fast
        trainer = Trainer(config, load_scene(config.data))
    summary = trainer.train()
    print(f"trained {summary['iterations']} iterations in {summary['train_minutes']:.1f} min "
          f"({summary['iterations_per_second']:.2f} it/s), {summary['gaussians']} Gaussians -> {trainer.config.output.dir}")
    return 0


def _resumed_trainer(args: argparse.Namespace) -> Trainer:
    """The run in --output.dir continued with the options given now (see pidg.training.run_folder)."""
    overrides = overrides_from_args(args)
    if args.config or args.overwrite or "preset" in overrides:
        raise ValueError("--resume continues a run with its saved config: --config, --overwrite and --preset do not apply")
    run_dir = Path(overrides.get("output.dir", str(TrainConfig().output.dir)))
    checkpoint = run_dir / CHECKPOINT_FILE
    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: no checkpoint to resume (give the run folder with --output.dir)")
    config, changes = resume_config(load_config(TrainConfig, run_dir / CONFIG_FILE), overrides)
    for name, old, new in changes:
        print(f"resume: {name} {old} -> {new}")
    trainer = Trainer.from_checkpoint(checkpoint, load_scene(config.data), config)
    print(f"resuming from step {trainer.step} ({checkpoint})")
    return trainer


def _cmd_preprocess(args: argparse.Namespace) -> int:
    config = _train_config(args)
    if not str(config.data.path):
        raise ValueError("give the dataset folder with --data.path DIR")
    summary = run_preprocess(config.data, config.flow, Path(args.cache_root) if args.cache_root else None)
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    result = evaluate_run(Path(args.run), split=args.split, lpips_nets=tuple(n for n in args.lpips if n != "none"), device=args.device,
                          motion_gt=args.motion_gt, motion_radius=args.motion_radius,
                          views_from=args.views_from)
    mean = result["mean"]
    print(" ".join(f"{k}={v:.4f}" for k, v in mean.items() if v is not None) + f" fps={result['render_fps']:.1f}")
    for name, future in result.get("future", {}).items():
        print(f"future ({name} after t={future['t_last']:.3f}): "
              + " ".join(f"{k}={v:.4f}" for k, v in future["mean"].items() if v is not None))
    if "motion_gt" in result:
        print(f"{result['motion_gt'].summary()} -> {Path(result['folder']) / 'motion_gt.json'}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    for path in render_run(Path(args.run), split=args.split, fps=args.fps, device=args.device):
        print(f"wrote {path}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    run_demo(
        Path(args.out), iterations=args.iterations, minutes=args.minutes, physics=args.physics, flow=args.flow,
        device=args.device, depth_weight=args.depth_weight,
    )
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    quality = Quality(preview_scale=args.preview_scale, max_side=args.max_size)
    if args.measure is not None:
        size = parse_downscale(args.measure)
        if not isinstance(size, tuple) or min(size) < 16:
            raise ValueError(f"--measure {args.measure}: give a size such as 800x800 (at least 16 px a side)")
        m = measure_run(Path(args.run), size, device=args.device, repeats=args.repeats, quality=quality)
        print(f"{args.run}: {m['gaussians']} Gaussians on {m['device']}, median of {m['repeats']} frames (render + JPEG, no network)")
        for name, w, h in (("full", m["width"], m["height"]), ("preview", m["preview_width"], m["preview_height"])):
            print(f"  {name} {w}x{h}: {m[f'{name}_camera_moves_ms']:.0f} ms while the camera moves, "
                  f"{m[f'{name}_time_changes_ms']:.0f} ms when the time changes too")
        for mode, times in m["modes"].items():
            print(f"  {mode}: {times['full_ms']:.0f} ms full, {times['preview_ms']:.0f} ms preview")
        return 0
    serve_run(Path(args.run), ViewerOptions(host=args.host, port=args.port, device=args.device, quality=quality, cameras=not args.no_cameras))
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    if args.time is not None:
        path = export_ply(Path(args.run), check_time(args.time), args.out, device=args.device, sh_degree=args.sh_degree)
        print(f"wrote {path} (Gaussians at t = {args.time:g}, positions in the dataset's world units)")
        return 0
    paths = export_ply_sequence(Path(args.run), args.times, args.out, device=args.device, sh_degree=args.sh_degree)
    print(f"wrote {len(paths)} PLY files and frames.json to {paths[0].parent}")
    return 0


def _cmd_make_scene(args: argparse.Namespace) -> int:
    width, height = parse_resolution(args.resolution)
    options = SceneOptions(args.kind, frames=args.frames, width=width, height=height, samples=args.samples,
                           static_camera=args.static_camera, held_out_on_orbit=args.held_out_on_orbit, texture=args.texture,
                           seed=args.seed, denoise=not args.no_denoise, points=args.points, verify=args.verify)
    summary = make_scene(options, Path(args.out), overwrite=args.overwrite)
    t, images = summary["timings"], summary["images"]
    print(f"{args.kind} scene -> {args.out}: {images['train']} train / {images['val']} val / {images['test']} test images of "
          f"{width}x{height} ({summary['render']['engine']}, {args.samples} samples); {t['total_s']:.1f} s in all, "
          f"{t['render_s_per_image']:.2f} s a render")
    for line in summary_lines(summary["verify"]) if args.verify else []:
        print(f"  verify: {line}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    out = build_report([Path(p) for p in args.paths], Path(args.out), str(resolve_device(args.device)), not args.no_pictures)
    print(f"report -> {out}")
    return 0


def _cmd_bench_render(args: argparse.Namespace) -> int:
    config = RenderBenchConfig(repeats=args.repeats)
    if args.quick:
        config = RenderBenchConfig(
            cases=[RenderBenchCase("a", 2_000, 128), RenderBenchCase("b", 5_000, 128)], repeats=2, reference_repeats=1, feature_channels=(0, 8)
        )
    run_render_bench(config, Path(args.out) if args.out else None)
    return 0


def _cmd_bench_quality(args: argparse.Namespace) -> int:
    minutes = args.minutes if args.minutes and args.minutes > 0 else None
    config = _train_config(args, data_path=args.scenes[0])  # the preset follows the first scene's layout
    run_quality_bench([Path(p) for p in args.scenes], Path(args.out), config, args.downscale, minutes, args.variants,
                      seeds=args.seeds)
    return 0


def _cmd_bench_suite(args: argparse.Namespace) -> int:
    spec = SUITES[args.name]
    scenes = discover_scenes(args.data, spec.layout)  # the preset follows the suite's kind of scene
    explicit = set(overrides_from_args(args))
    config = suite_config(args.name, _train_config(args, data_path=str(scenes[0])), explicit)
    executor = make_executor(args.executor, args.workers, args.ray_address, args.gpus_per_job, args.cpus_per_job)
    minutes = args.minutes if args.minutes and args.minutes > 0 else None
    run_suite(args.name, Path(args.data), Path(args.out or f"outputs/suite/{args.name}"), config, minutes=minutes,
              variants=args.variants, scenes=args.scenes, downscale=args.downscale, ssim=args.ssim, executor=executor,
              integrator=args.integrator)
    return 0


def _cmd_bench_step(args: argparse.Namespace) -> int:
    run_step_bench(
        Path(args.scene), _train_config(args, data_path=args.scene), args.variants, args.downscale, args.gaussians, args.iterations,
        out=Path(args.out) if args.out else None, from_run=Path(args.from_run) if args.from_run else None,
    )
    return 0


def _cmd_bench_views(args: argparse.Namespace) -> int:
    run_views_bench(Path(args.run), every=args.every, device=args.device)
    return 0


def _cmd_bench_motion_fit(args: argparse.Namespace) -> int:
    config = MotionFitConfig(steps=args.steps, surface_points=args.points, static_points=args.static_points, seed=args.seed)
    run_motion_fit(Path(args.run), config, Path(args.out) if args.out else None)
    return 0


def _cmd_bench_rigid_tracks(args: argparse.Namespace) -> int:
    run_rigid_tracks_bench(Path(args.dataset), args.seed, Path(args.out) if args.out else None)
    return 0


def _cmd_bench_cmr(args: argparse.Namespace) -> int:
    config = CMRBenchConfig(
        tuple(args.samples), tuple(args.particles), tuple(args.variants), args.repeats,
        physics=PhysicsConfig(kind="cmr", block_size=args.block_size),
        material=MaterialFieldConfig(width=args.width, activation=args.activation), device=str(resolve_device(args.device)),
    )
    run_cmr_bench(config, Path(args.out) if args.out else None)
    return 0


def _add_run_options(parser: argparse.ArgumentParser, positional: str = "") -> None:
    """--config and --preset, the paper's ablation switches as short forms of --physics.kind / --flow.kind, and one
    --section.field option per config field (the usage line names them in general: they are listed below it)."""
    parser.usage = f"%(prog)s {positional}[options] [--SECTION.FIELD VALUE ...]"
    parser.add_argument("--config", help="a config.json to start from (e.g. one written by an earlier run); it is "
                        "already resolved, so no preset applies")
    parser.add_argument("--physics", choices=get_args(PhysicsKind), dest="cfg::physics.kind", default=MISSING_OPTION,
                        help="cmr: the Cauchy momentum residual on the material field (same as --physics.kind)")
    parser.add_argument("--flow", choices=get_args(FlowKind), dest="cfg::flow.kind", default=MISSING_OPTION,
                        help="lpfm: Lagrangian particle flow matching against preprocessed optical flow (same as --flow.kind)")
    add_config_arguments(parser, TrainConfig)  # --preset and --device among them


def _add_device_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", choices=get_args(Device), default="auto",
                        help="where to compute: cuda (rendering with gsplat), cpu, or auto (CUDA when available)")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, like every other error of the command."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="pidg", description="Physics-Informed Deformable Gaussian Splatting")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error (else one line)")
    sub = parser.add_subparsers(dest="command", required=True)

    train = sub.add_parser("train", help="train on a dataset folder (D-NeRF, PIDG/BlenderNeRF, HyperNeRF)",
                           description="Train on a dataset folder. Every config field is an option; the resolved config "
                           "is saved as RUN/config.json.")
    train.add_argument("--resume", action="store_true", help="continue the run in --output.dir from its checkpoint, with its saved "
                       "config and the options given now (changes of data or model are refused)")
    train.add_argument("--overwrite", action="store_true", help="replace the run that --output.dir already holds")
    _add_run_options(train)
    train.set_defaults(func=_cmd_train)

    pre = sub.add_parser(
        "preprocess", help="optical flow of consecutive training frames (forward, backward, consistency), cached on disk"
    )
    pre.add_argument("--cache-root", default=None, help="cache folder (default: DATASET/<flow.cache_dir>)")
    _add_run_options(pre)
    pre.set_defaults(func=_cmd_preprocess)

    ev = sub.add_parser("eval", help="metrics of a trained run on a split (JSON in RUN/eval_SPLIT)")
    ev.add_argument("run", help="the run's output folder")
    ev.add_argument("--split", default="test", help="train, val or test")
    ev.add_argument("--lpips", nargs="*", default=["alex", "vgg"], choices=[*get_args(NetName), "none"],
                    help="LPIPS backbones; `none` (or no value) skips LPIPS")
    ev.add_argument("--motion-gt", action="store_true",
                    help="also score the learned motion against the dataset's ground-truth motion (DATASET/motion_gt): "
                    "flow end-point errors and 3D velocity errors -> RUN/eval_SPLIT/motion_gt.json")
    ev.add_argument("--motion-radius", type=float, default=None, metavar="R",
                    help="--motion-gt: largest distance (world units) from a ground-truth vertex to its Gaussian "
                    "(default: 2%% of the diagonal of the ground-truth vertices' bounding box)")
    ev.add_argument("--views-from", type=Path, default=None, metavar="DIR",
                    help="score the split of DIR, a twin of the run's dataset (the same training frames, checked), "
                    "instead of the run's own: e.g. `pidg make-scene --held-out-on-orbit` of the same scene, whose "
                    "held-out views are novel times only -> RUN/eval_SPLIT@DIRNAME")
    _add_device_option(ev)
    ev.set_defaults(func=_cmd_eval)

    rd = sub.add_parser("render", help="videos and frames of a trained run: fixed view over time, test trajectory, depth")
    rd.add_argument("run", help="the run's output folder")
    rd.add_argument("--split", default="test", help="train, val or test")
    rd.add_argument("--fps", type=int, default=24, help="frames per second of the videos over time")
    _add_device_option(rd)
    rd.set_defaults(func=_cmd_render)

    demo = sub.add_parser("demo", help="train on the embedded procedural scene and write metrics, renders and a video")
    demo.add_argument("--out", default="outputs/demo", help="output folder")
    demo.add_argument("--iterations", type=int, default=1200, help="training steps")
    demo.add_argument("--minutes", type=float, default=5.0, help="training time budget (stops early, with a checkpoint)")
    demo.add_argument("--physics", choices=get_args(PhysicsKind), default="none", help="add the Cauchy momentum residual")
    demo.add_argument("--flow", choices=get_args(FlowKind), default="none", help="add flow matching (optical flow is computed first)")
    demo.add_argument(
        "--depth-weight", type=float, default=DEMO_DEPTH_WEIGHT,
        help=f"weight of the loss against the scene's true depth maps (default {DEMO_DEPTH_WEIGHT}; 0 = RGB only, "
        "monocular); with --flow lpfm, > 0 also matches the depth change of the flow (--flow.lambda_depth_change 1)",
    )
    _add_device_option(demo)
    demo.set_defaults(func=_cmd_demo)

    scene = sub.add_parser("make-scene", help="a dynamic dataset from Blender's solvers with ground-truth motion (needs bpy)",
                           description="Build, simulate and render a PIDG-style scene with Blender (bpy: pip install -e "
                           "\".[scenes]\"): one monocular camera orbiting it, train/val/test interleaved in time, motion "
                           "masks, depth, points3d.ply and the ground truth in DIR/motion_gt (vertex positions and velocities, "
                           "object-motion flow per image).")
    scene.add_argument("kind", choices=SCENE_KINDS, help="rigid: objects falling and colliding; cloth: a cloth draping over a "
                       "sphere; soft: a soft ball bouncing; kinematic: a keyframed object on a smooth path")
    scene.add_argument("--out", required=True, help="the dataset folder to write (must not exist unless --overwrite)")
    scene.add_argument("--frames", type=int, default=60, help="images, one per simulation frame at 24 fps (4-2000)")
    scene.add_argument("--resolution", default="200x200", metavar="WxH", help="image size in pixels")
    scene.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (denoised)")
    scene.add_argument("--no-denoise", action="store_true", help="no OpenImageDenoise pass")
    scene.add_argument("--static-camera", action="store_true", help="a fixed camera instead of one orbiting the scene")
    scene.add_argument("--held-out-on-orbit", action="store_true", help="val and test views where the training camera "
                       "is at their time (novel times only) instead of 30 degrees of azimuth off the orbit (novel views "
                       "too); the same simulation, training images and ground truth otherwise")
    scene.add_argument("--texture", choices=SCENE_TEXTURES, default="cells", help="surface pattern: cells (random-coloured "
                       "Voronoi cells, not periodic) or checker (the scenes of docs/motion.md's earlier tables, whose "
                       "period a tumbling object's surface moves by in a frame)")
    scene.add_argument("--seed", type=int, default=0, help="placement, colours and camera start")
    scene.add_argument("--points", type=int, default=10_000, help="points sampled for points3d.ply")
    scene.add_argument("--verify", action="store_true", help="check the ground truth independently; residuals -> "
                       "DIR/motion_gt/verify.json")
    scene.add_argument("--overwrite", action="store_true", help="replace DIR when it holds an earlier make-scene output")
    scene.set_defaults(func=_cmd_make_scene)

    report = sub.add_parser("report", help="one HTML page: suite tables, runs' metrics, PSNR curves, velocity/stress/flow pictures")
    report.add_argument("paths", nargs="+", metavar="RUN_OR_SUITE", help="run folders, suite folders (suite.json) or "
                        "bench quality folders (quality.json)")
    report.add_argument("--out", default="outputs/report/report.html", help="the HTML file (pictures also as PNGs beside it)")
    report.add_argument("--no-pictures", action="store_true", help="tables and curves only (no model is loaded)")
    _add_device_option(report)
    report.set_defaults(func=_cmd_report)

    view = sub.add_parser("view", help="interactive web viewer of a trained run (viser): free camera, time slider, fields",
                          description="Serve a web page showing the run: a free camera rendered by pidg's renderer, a time "
                          "slider (dataset time in [0, 1]) with play/pause, the training cameras, and velocity, stress, the "
                          "dynamic/static split and depth where the run has them. Needs viser: pip install 'pidg[view]'.")
    view.add_argument("run", help="the run's output folder")
    view.add_argument("--port", type=int, default=8080, help="port to serve on (0: any free port)")
    view.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every network interface)")
    view.add_argument("--preview-scale", type=float, default=0.25,
                      help="resolution while the camera moves, as a fraction of the browser's canvas (0.05-1)")
    view.add_argument("--max-size", type=int, default=1600, help="largest side of a full-quality frame, in pixels")
    view.add_argument("--no-cameras", action="store_true", help="do not read the dataset for the training cameras")
    view.add_argument("--measure", nargs="?", const="800x800", default=None, metavar="WxH",
                      help="print the frame times at this size (default 800x800) and exit, without a server")
    view.add_argument("--repeats", type=int, default=5, help="frames timed per case with --measure")
    _add_device_option(view)
    view.set_defaults(func=_cmd_view)

    export = sub.add_parser("export", help="the Gaussians at a time as a standard 3DGS PLY (SuperSplat, gsplat, 3DGS viewers)",
                            description="Write the run's Gaussians at dataset time T in the 3DGS PLY layout (positions in "
                            "the dataset's world units, logit opacity, log scales, wxyz quaternions, SH colour).")
    when = export.add_mutually_exclusive_group(required=True)
    when.add_argument("--time", type=float, default=None, metavar="T", help="dataset time in [0, 1] (0: first frame, 1: last)")
    when.add_argument("--times", type=float, nargs="*", default=None, metavar="T",
                      help="a sequence, one PLY per time, with frames.json; without values: one per training-frame interval")
    export.add_argument("run", help="the run's output folder")
    export.add_argument("--format", choices=["ply"], default="ply", help="file format (the 3DGS PLY layout)")
    export.add_argument("--out", default=None, help="the PLY file (--time; default RUN/export/gaussians_tT.ply) or the "
                        "folder (--times; default RUN/export/sequence)")
    export.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], default=3,
                        help="SH bands written (3: 45 f_rest values, what the original viewers expect)")
    _add_device_option(export)
    export.set_defaults(func=_cmd_export)

    bench = sub.add_parser("bench", help="benchmarks (not tests)")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    render = bench_sub.add_parser("render", help="rasterizer speed and memory: CPU kernel vs torch reference (CPU only)")
    render.add_argument("--repeats", type=int, default=7, help="timed repeats per case")
    render.add_argument("--out", default="outputs/bench/render.json", help="JSON with all figures ('' for none)")
    render.add_argument("--quick", action="store_true", help="tiny cases, for a smoke test")
    render.set_defaults(func=_cmd_bench_render)

    quality = bench_sub.add_parser("quality", help="train + evaluate several scenes with one budget; one table")
    quality.add_argument("scenes", nargs="+", help="dataset folders")
    quality.add_argument("--out", default="outputs/bench/quality", help="output folder (one run folder per scene and variant)")
    quality.add_argument("--downscale", default=None, help="factor or WxH, e.g. 400x400")
    quality.add_argument("--minutes", type=float, default=30.0, help="training time budget per run (0: none, --optim.iterations only)")
    quality.add_argument("--variants", nargs="*", default=None, choices=list(ABLATION_VARIANTS),
                         help="ablation rows per scene (default: the config as given)")
    quality.add_argument("--seeds", nargs="+", type=int, default=None,
                         help="train every scene x variant once per seed and print each row's spread over them "
                              "(mean +- sd, min-max; runs in OUT/SCENE/VARIANT/seedS; default: --optim.seed only)")
    _add_run_options(quality, "SCENE [SCENE ...] ")
    quality.set_defaults(func=_cmd_bench_quality)

    suite = bench_sub.add_parser("suite", help="the paper's tables: a named set of scenes x variants, one budget and seed")
    suite.add_argument("name", choices=list(SUITES), help="; ".join(f"{k}: {v.description}" for k, v in SUITES.items()))
    suite.add_argument("--data", required=True, help="folder holding the suite's scenes (each sub-folder that is a "
                       "dataset of the suite's kind is a scene), or one scene folder")
    suite.add_argument("--scenes", nargs="+", default=None, help="only these scenes (folder names)")
    suite.add_argument("--variants", nargs="+", default=None, choices=list(ABLATION_VARIANTS), help="rows (default: the suite's)")
    suite.add_argument("--out", default=None, help="output folder (default outputs/suite/NAME): suite.md, suite.json, one run per job")
    suite.add_argument("--minutes", type=float, default=30.0, help="training time budget per job (0: none, --optim.iterations only)")
    suite.add_argument("--downscale", default=None, help="factor or WxH, e.g. 400x400")
    suite.add_argument("--ssim", choices=["zeros", "valid"], default="zeros",
                       help="SSIM convention of the tables: zeros (zero-padded window, the 3DGS family's tables) or valid")
    suite.add_argument("--integrator", choices=["midpoint", "rk4"], default="rk4", help="future suite: advection integrator")
    suite.add_argument("--executor", choices=list(get_args(ExecutorName)), default="local",
                       help="local: one job at a time here; process: a local process pool; ray: Ray tasks (pip install ray)")
    suite.add_argument("--workers", type=int, default=2, help="process executor: jobs at a time")
    suite.add_argument("--ray-address", default=None, help="ray executor: cluster address (auto: this machine's cluster; "
                       "default: start a local Ray instance)")
    suite.add_argument("--gpus-per-job", type=float, default=None, help="ray executor: GPUs per task (default 1 when the cluster has GPUs)")
    suite.add_argument("--cpus-per-job", type=float, default=1.0, help="ray executor: CPUs per task")
    _add_run_options(suite, "NAME --data DIR ")
    suite.set_defaults(func=_cmd_bench_suite)

    views = bench_sub.add_parser("views", help="a procedural-scene run's error split into novel time and novel viewpoint")
    views.add_argument("run", help="a run trained on the embedded procedural scene (e.g. outputs/demo/run)")
    views.add_argument("--every", type=int, default=1, help="score every k-th time of each probe set")
    _add_device_option(views)
    views.set_defaults(func=_cmd_bench_views)

    step = bench_sub.add_parser("step", help="training-step rate and its breakdown per variant, interleaved, fixed Gaussian count")
    step.add_argument("scene", help="dataset folder")
    step.add_argument("--variants", nargs="+", default=["base", "cmr", "full"], choices=list(ABLATION_VARIANTS), help="variants to time")
    step.add_argument("--downscale", default="400x400", help="factor or WxH")
    step.add_argument("--gaussians", type=int, default=20_000, help="Gaussians (random init / subsampled cloud), no densification")
    step.add_argument("--iterations", type=int, default=60, help="timed steps per variant (after 10 warm-up steps)")
    step.add_argument("--out", default="outputs/bench/step.json", help="JSON: the commit, the machine and each variant's figures ('' for none)")
    step.add_argument("--from-run", default=None, help="start from this run's trained Gaussians (its checkpoint) instead of a random init")
    _add_run_options(step, "SCENE ")
    step.set_defaults(func=_cmd_bench_step)

    fit = bench_sub.add_parser("motion-fit", help="a generated scene's run: can its deformation field represent the true "
                               "motion? (a fresh field fitted to the true 3D trajectories, beside the trained one)")
    fit.add_argument("run", help="a run folder trained on a scene from `pidg make-scene`")
    fit.add_argument("--steps", type=int, default=MotionFitConfig.steps, help="fitting steps (default: the run's optim.iterations)")
    fit.add_argument("--points", type=int, default=MotionFitConfig.surface_points, help="points sampled on the moving surfaces")
    fit.add_argument("--static-points", type=int, default=MotionFitConfig.static_points, help="still points held in place")
    fit.add_argument("--seed", type=int, default=MotionFitConfig.seed, help="seed of the sampling and of the fit")
    fit.add_argument("--out", default="outputs/bench/motion_fit.json", help="JSON with all figures ('' for none)")
    fit.set_defaults(func=_cmd_bench_motion_fit)

    tracks = bench_sub.add_parser("rigid-tracks", help="a generated scene: the rigid-body tracks that --optim.motion_start "
                                  "rigid_tracks fits the deformation to, against the true motion")
    tracks.add_argument("dataset", help="a dataset from `pidg make-scene` (with depth, motion masks and motion_gt/)")
    tracks.add_argument("--seed", type=int, default=TrainConfig().optim.seed, help="the run's --optim.seed (the tracker's sampling)")
    tracks.add_argument("--out", default="outputs/bench/rigid_tracks.json", help="JSON with all figures ('' for none)")
    tracks.set_defaults(func=_cmd_bench_rigid_tracks)

    cmr = bench_sub.add_parser("cmr", help="CMR loss cost: time per sample size, peak memory at 20k vs 200k particles")
    cmr.add_argument("--samples", type=int, nargs="+", default=list(CMRBenchConfig.samples), help="sample sizes M")
    cmr.add_argument("--particles", type=int, nargs="+", default=list(CMRBenchConfig.particles), help="particle counts N")
    cmr.add_argument("--variants", nargs="+", default=list(CMR_BENCH_VARIANTS), choices=CMR_BENCH_VARIANTS, help="how the jet is computed")
    cmr.add_argument("--block-size", type=int, default=PhysicsConfig.block_size, help="blocks for checkpointing")
    cmr.add_argument("--width", type=int, default=MaterialFieldConfig.width, help="material-field MLP width")
    cmr.add_argument("--activation", default=MaterialFieldConfig.activation, choices=get_args(Activation), help="trunk activation")
    cmr.add_argument("--repeats", type=int, default=CMRBenchConfig.repeats, help="timed repeats")
    cmr.add_argument("--out", default=None, help="JSON with all figures")
    _add_device_option(cmr)
    cmr.set_defaults(func=_cmd_bench_cmr)
    return parser


def _one_line(message: Warning | str, category: type[Warning], filename: str, lineno: int, line: str | None = None) -> str:
    return f"{category.__name__}: {message}"


@contextlib.contextmanager
def warnings_as_log_lines() -> Iterator[None]:
    """While a command runs, a warning (e.g. "ms_ssim reported as None" on small images) is one log line, "WARNING
    py.warnings: RuntimeWarning: ...", instead of Python's form with a file, a line number and a line of pidg's
    source, which reads like a crash to a user; ``pidg --debug`` keeps Python's form."""
    format_before = warnings.formatwarning
    warnings.formatwarning = _one_line
    logging.captureWarnings(True)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        warnings.formatwarning = format_before


def main(argv: list[str] | None = None) -> int:
    """Run a command. An error reaches the user as one line naming the input and the problem (exit status 2);
    ``pidg --debug ...`` shows the whole traceback instead."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.debug:
        return args.func(args)
    try:
        with warnings_as_log_lines(), logging_redirect_tqdm():  # a log line mid-bar goes above the bar
            return args.func(args)
    except KeyboardInterrupt:
        print(f"pidg {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - the one place every error becomes one line
        known = isinstance(err, (ValueError, OSError, RuntimeError, ImportError, KeyError))
        text = " ".join(str(err).split()) if known else f"{type(err).__name__}: {err}"
        print(f"pidg {args.command}: error: {text} (pidg --debug ... shows the traceback)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
