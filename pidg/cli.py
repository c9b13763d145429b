"""The ``pidg`` command: a thin layer that parses arguments and calls library functions."""
from __future__ import annotations

from pidg import _env  # noqa: F401  (must precede torch)

import argparse
import sys
from pathlib import Path


def _cmd_demo(args: argparse.Namespace) -> int:
    from pidg.demo import run_render_demo

    run_render_demo(Path(args.out), size=args.size, n_views=args.views)
    return 0


def _cmd_bench_render(args: argparse.Namespace) -> int:
    from pidg.evaluation.bench_render import RenderBenchCase, RenderBenchConfig, run_render_bench

    config = RenderBenchConfig(repeats=args.repeats)
    if args.quick:
        config = RenderBenchConfig(
            cases=[RenderBenchCase("a", 2_000, 128), RenderBenchCase("b", 5_000, 128)], repeats=2, reference_repeats=1, feature_channels=(0, 8)
        )
    run_render_bench(config, Path(args.out) if args.out else None)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pidg", description="Physics-Informed Deformable Gaussian Splatting")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="render the embedded demo scene (no download needed)")
    demo.add_argument("--out", default="outputs/demo", help="output folder")
    demo.add_argument("--size", type=int, default=256, help="image side in pixels")
    demo.add_argument("--views", type=int, default=8, help="number of orbit views")
    demo.set_defaults(func=_cmd_demo)

    bench = sub.add_parser("bench", help="benchmarks (not tests)")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    render = bench_sub.add_parser("render", help="rasterizer speed and memory: CPU kernel vs torch reference")
    render.add_argument("--repeats", type=int, default=7)
    render.add_argument("--out", default="outputs/bench/render.json", help="JSON with all figures ('' for none)")
    render.add_argument("--quick", action="store_true", help="tiny cases, for a smoke test")
    render.set_defaults(func=_cmd_bench_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
