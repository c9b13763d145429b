"""The whole method on a CUDA device with gsplat, and checkpoints that move between CUDA and CPU. Skips cleanly
without CUDA and gsplat (the device-agnostic path is guarded on CPU by tests/training/test_device_path.py)."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses

import pytest
import torch

from pidg.data import load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.device import cuda_available, gsplat_installed
from pidg.metrics import compute_metrics
from pidg.models.deformation import HashGridConfig
from pidg.pipeline import evaluate_run, load_run
from pidg.training.config import TrainConfig
from pidg.training.trainer import Trainer

pytestmark = pytest.mark.skipif(
    not (cuda_available() and gsplat_installed()), reason="needs a CUDA device and `pip install gsplat`"
)


def _config(data, out_dir, device: str, iterations: int = 12) -> TrainConfig:
    cfg = TrainConfig(device=device)
    cfg.data = dataclasses.replace(cfg.data, path=data, progress=False)
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=64)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=8)
    # the 6-frame orbit turns ~65 degrees a pair, where training refuses the flow loss; these tests run its machinery
    cfg.flow = dataclasses.replace(cfg.flow, kind="lpfm", max_view_change=180.0)
    cfg.gaussians = dataclasses.replace(cfg.gaussians, init_opacity=0.8)
    cfg.densify = dataclasses.replace(cfg.densify, start=2, stop=8, every=2, opacity_reset_every=1000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=0, progress=False, preview_every=0, log_every=1)
    return cfg


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=2, width=48, height=48, n_gaussians=800, n_init_points=300),
        tmp_path_factory.mktemp("cuda") / "data",
    )


def test_full_method_trains_on_cuda_and_the_checkpoint_moves_to_the_cpu(data, tmp_path):
    cfg = _config(data, tmp_path / "run", "cuda")
    trainer = Trainer(cfg, load_scene(cfg.data))
    summary = trainer.train()
    assert summary["rasterizer"] == "gsplat" and summary["device"].startswith("cuda") and summary["peak_gpu_memory_mb"] > 0
    assert all(p.is_cuda for p in trainer.model.gaussians.params.values())
    assert any(h.get("densified") for h in trainer.history) and "cmr" in trainer.history[-1]
    # the CUDA run evaluates on the CPU, and resumes there
    on_cpu = load_run(tmp_path / "run", ("test",), device="cpu")
    frame = on_cpu.scene.test[0]
    with torch.no_grad():
        cpu_image = on_cpu.model.render(frame.camera, frame.time).rgb
        gpu_image = trainer.model.render(frame.camera.to("cuda"), frame.time).rgb.cpu()
    assert (cpu_image - gpu_image).abs().max() < 2e-3
    assert evaluate_run(tmp_path / "run", "test", lpips_nets=(), device="cpu")["views"] == 2
    resumed = Trainer.from_checkpoint(tmp_path / "run" / "checkpoint.pt", load_scene(cfg.data), dataclasses.replace(cfg, device="cpu"))
    resumed.train(iterations=cfg.optim.iterations + 2)
    assert resumed.step == cfg.optim.iterations + 2


def test_cpu_checkpoint_resumes_on_cuda(data, tmp_path):
    cfg = _config(data, tmp_path / "run", "cpu", iterations=6)
    Trainer(cfg, load_scene(cfg.data)).train()
    resumed = Trainer.from_checkpoint(tmp_path / "run" / "checkpoint.pt", load_scene(cfg.data), dataclasses.replace(cfg, device="cuda"))
    resumed.train(iterations=9)
    assert resumed.step == 9 and resumed.model.device.type == "cuda"


def test_metrics_run_on_the_gpu():
    pred, gt = torch.rand(64, 64, 3, device="cuda"), torch.rand(64, 64, 3, device="cuda")
    metrics = compute_metrics(pred, gt, lpips_nets=())
    assert 0 < metrics["psnr"] < 20 and -1 <= metrics["ssim"] <= 1
