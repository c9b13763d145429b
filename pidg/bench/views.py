"""``pidg bench views RUN``: where a run's test error comes from, on the embedded procedural scene.

A test view of a monocular capture is a novel view *and* a novel time. The procedural scene can render its ground
truth from any camera at any time, so the error can be taken apart: the run is scored on four probe sets, each
with the ground truth rendered exactly as the dataset's frames were (PSNR over the image, over the moving ring's
pixels and over the static rest):

* training times seen by the training (orbit) cameras       -> the fit;
* the held-out (midpoint) times seen from the orbit          -> generalisation in time only;
* training times seen by the test rig (off the orbit)        -> generalisation in viewpoint only;
* held-out times seen by the test rig                        -> the test split itself.

This is how the demo's train/test gap was found to be a viewpoint gap, not a time gap (docs/cpu-quality.md, "The
train/test gap").
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from pidg.data.procedural import ProceduralScene, ProceduralSceneConfig, composite_rgba
from pidg.data.scene import DatasetError
from pidg.device import Device, resolve_device
from pidg.metrics import psnr
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render import Camera


@dataclass(frozen=True)
class ProbeScores:
    """Mean PSNR (dB) of one probe set: whole image, moving-ring pixels, static pixels; and its view count."""

    name: str
    views: int
    psnr: float
    psnr_dynamic: float
    psnr_static: float


PROBES = (
    ("training times, orbit cameras", "train", "train"),
    ("held-out times, orbit cameras", "held_out", "train"),
    ("training times, test-rig cameras", "train", "test"),
    ("held-out times, test-rig cameras", "held_out", "test"),
)


def procedural_config_of(run_dir: Path) -> ProceduralSceneConfig:
    """The procedural scene a run was trained on (its dataset's ``procedural.json``); DatasetError otherwise."""
    config = json.loads((run_dir / "config.json").read_text())
    path = Path(config["data"]["path"]) / "procedural.json"
    if not path.is_file():
        raise DatasetError(path, "not a procedural dataset: `pidg bench views` needs the scene's generator settings")
    return ProceduralSceneConfig(**json.loads(path.read_text()))


def probe_times(scene: ProceduralScene, every: int = 1) -> dict[str, list[float]]:
    """Training times and held-out (midpoint) times of the scene's common time grid, every ``every``-th."""
    n = scene.config.n_train
    steps = 2 * (n - 1)
    return {"train": [2 * i / steps for i in range(n)][::every], "held_out": [(2 * j + 1) / steps for j in range(n - 1)][::every]}


def probe_truth(scene: ProceduralScene, t: float, rig: str) -> tuple[Camera, torch.Tensor, torch.Tensor]:
    """Camera of ``rig`` ("train": the orbit; "test": the test rig) at time t, the ground-truth image [H, W, 3] in
    [0, 1] (composited exactly as the dataset's frames) and the ring's mask [H, W]."""
    camera = scene.camera(scene.camera_to_world(rig, t))
    rgba, mask = scene.render(t, camera)
    truth = torch.from_numpy(composite_rgba(rgba, scene.config.background_rgb)).float() / 255.0
    return camera, truth, torch.from_numpy(mask)


@torch.no_grad()
def score_probes(model: DynamicGaussians, scene: ProceduralScene, every: int = 1) -> list[ProbeScores]:
    """PSNR of ``model`` on the four probe sets (every ``every``-th time of each)."""
    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    times = probe_times(scene, every)
    results = []
    for name, which, rig in PROBES:
        whole, dynamic, static = [], [], []
        for t in times[which]:
            camera, truth, moving = probe_truth(scene, t, rig)
            image = model.render(camera.to(model.device), t).rgb.clamp(0, 1).cpu()
            whole.append(float(psnr(image, truth)))
            if moving.any():
                dynamic.append(float(psnr(image, truth, moving)))
            static.append(float(psnr(image, truth, ~moving)))
        results.append(ProbeScores(name, len(whole), _mean(whole), _mean(dynamic), _mean(static)))
    return results


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def run_views_bench(run_dir: Path, every: int = 1, device: Device = "auto", out: Path | None = None) -> list[ProbeScores]:
    """Score a run on the probe sets, print a table, write ``RUN/bench_views.json`` (or ``out``)."""
    scene = ProceduralScene(procedural_config_of(run_dir))
    model = DynamicGaussians.from_run(run_dir, device=resolve_device(device))
    results = score_probes(model, scene, every)
    print(f"{'probe set (PSNR in dB)':<36}{'views':>6}{'PSNR':>8}{'ring':>8}{'static':>8}")
    for r in results:
        print(f"{r.name:<36}{r.views:>6}{r.psnr:>8.2f}{r.psnr_dynamic:>8.2f}{r.psnr_static:>8.2f}")
    path = out or run_dir / "bench_views.json"
    path.write_text(json.dumps([r.__dict__ for r in results], indent=2))
    return results
