"""The README's main job: render the embedded demo scene, so a fresh install shows pictures at once."""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from tqdm import tqdm

from pidg.evaluation.images import colorize_scalar, save_png
from pidg.render import rasterize
from pidg.render.scenes import orbit_camera, torus_scene


def run_render_demo(out_dir: Path, size: int = 256, n_views: int = 8) -> dict:
    """Render RGB, depth and alpha of the torus scene from ``n_views`` orbit cameras into ``out_dir``."""
    scene = torus_scene()
    background = torch.tensor([1.0, 1.0, 1.0])
    timings = []
    for i in tqdm(range(n_views), desc="rendering demo views"):
        camera = orbit_camera(size, size, fov_x_deg=50.0, azimuth_deg=360.0 * i / n_views, elevation=2.2)
        t0 = time.perf_counter()
        out = rasterize(scene.means, scene.quats, scene.opacities, scene.colors, camera, scales=scene.scales, background=background)
        timings.append(time.perf_counter() - t0)
        save_png(out.rgb, out_dir / f"rgb_{i:03d}.png")
        save_png(colorize_scalar(out.depth_normalized(), valid=out.alpha > 0.5), out_dir / f"depth_{i:03d}.png")
        save_png(out.alpha, out_dir / f"alpha_{i:03d}.png")
    summary = {
        "gaussians": int(scene.means.shape[0]),
        "views": n_views,
        "size": size,
        "median_render_ms": 1e3 * sorted(timings)[len(timings) // 2],
        "output": str(out_dir),
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote {n_views} views (rgb/depth/alpha PNG) to {out_dir}; median render {summary['median_render_ms']:.1f} ms")
    return summary
