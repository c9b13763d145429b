"""The path a CUDA run takes, guarded on the CPU: the pure-torch compositor, hash grid and SSIM train the full method
(densification, physics, flow, checkpoint and resume) without a numba kernel; presets per dataset; device errors
are one line naming the fix."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import fcntl
import json
import sys
import types

import pytest
import torch

import pidg.device
import pidg.models.deformation.hash_grid as hash_grid_module
import pidg.models.deformation.warp as warp_module
import pidg.render.api as render_api
import pidg.render.rasterize_gsplat as rasterize_gsplat
import pidg.training.losses as losses_module
from pidg.cli import main
from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene, write_procedural_dataset
from pidg.device import DeviceUnavailable, rasterizer_for, resolve_device
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.trainer import Trainer


def device_agnostic_config(out_dir, iterations: int) -> TrainConfig:
    """The full method (CMR + LPFM, densification, decoupling) on the pure-torch implementations CUDA uses."""
    cfg = TrainConfig(backend="torch", device="cpu")
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16),
        width=16, backend="torch",
    )
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=64, block_size=32)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=8)
    cfg.flow = dataclasses.replace(cfg.flow, kind="lpfm", max_view_change=180.0)  # a 6-frame orbit: the machinery only
    cfg.gaussians = dataclasses.replace(cfg.gaussians, init_opacity=0.8)
    cfg.densify = dataclasses.replace(cfg.densify, start=2, stop=6, every=2, opacity_reset_every=1000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations)
    cfg.output = dataclasses.replace(cfg.output, dir=out_dir, checkpoint_every=0, progress=False, preview_every=0, log_every=1)
    return cfg


def test_the_cuda_path_trains_and_resumes_without_any_cpu_kernel(tmp_path, monkeypatch):
    scene = make_procedural_scene(ProceduralSceneConfig(n_train=6, n_test=2, width=24, height=24, n_gaussians=600, n_init_points=150))

    def cpu_kernel(*args, **kwargs):
        raise AssertionError("the device-agnostic path called a numba kernel")

    monkeypatch.setattr(render_api, "composite_cpu", cpu_kernel)
    monkeypatch.setattr(render_api, "project_and_shade_cpu", cpu_kernel)
    monkeypatch.setattr(hash_grid_module, "hash_encode_cpu", cpu_kernel)
    monkeypatch.setattr(warp_module, "apply_warp_cpu", cpu_kernel)
    monkeypatch.setattr(losses_module, "fused_ssim", cpu_kernel)
    full = Trainer(device_agnostic_config(tmp_path / "full", 8), scene)
    summary = full.train()
    assert (summary["rasterizer"], summary["hash_grids"], summary["ssim"]) == ("torch", "torch", "torch")
    assert summary["device"].startswith("cpu") and summary["peak_rss_mb"] > 0
    assert {"physics", "flow", "flow_target"} <= set(summary["step_breakdown_ms"])  # the target, timed apart
    assert any(h.get("densified") for h in full.history) and full.model.dynamic_mask is not None
    half = Trainer(device_agnostic_config(tmp_path / "half", 8), scene)
    half.train(iterations=5)
    resumed = Trainer.from_checkpoint(tmp_path / "half" / "checkpoint.pt", scene)
    resumed.train()
    for name, p in full.model.gaussians.params.items():
        assert torch.allclose(p, resumed.model.gaussians.params[name], atol=1e-5, rtol=1e-4), name


def test_device_resolution_and_clear_errors(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert rasterizer_for("auto", torch.device("cpu")) == "cpu" and rasterizer_for("torch", torch.device("cpu")) == "torch"
    monkeypatch.setattr(pidg.device, "cuda_available", lambda: False)
    with pytest.raises(DeviceUnavailable, match="--device cuda: no CUDA device is available.*--device cpu"):
        resolve_device("cuda")
    monkeypatch.setattr(pidg.device, "gsplat_installed", lambda: False)
    with pytest.raises(DeviceUnavailable, match="not installed: pip install gsplat"):
        rasterizer_for("auto", torch.device("cuda"))
    with pytest.raises(DeviceUnavailable, match="numba CPU kernel"):
        rasterizer_for("cpu", torch.device("cuda"))
    with pytest.raises(DeviceUnavailable, match="CUDA only"):
        rasterizer_for("gsplat", torch.device("cpu"))


def test_a_gsplat_that_cannot_render_stops_before_training_with_its_reason(monkeypatch):
    """gsplat compiles its CUDA code on first use; a failed build is reported when the run starts, not at step 0,
    and the first use holds a lock so that parallel processes do not delete each other's build."""
    def broken(**kwargs):
        raise ImportError("/root/.cache/torch_extensions/gsplat_cuda/gsplat_cuda.so: cannot open shared object file")

    def working(**kwargs):
        assert kwargs["means"].shape == (1, 3) and kwargs["Ks"].shape == (1, 3, 3)
        with open(rasterize_gsplat.GSPLAT_BUILD_LOCK, "a") as other:  # another process's try: the probe holds the lock
            with pytest.raises(BlockingIOError):
                fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return None

    for rasterization, expected in ((broken, "ImportError: /root/.cache/torch_extensions/gsplat_cuda/gsplat_cuda.so: cannot open"), (working, None)):
        monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=rasterization))
        rasterize_gsplat.gsplat_load_error.cache_clear()
        found = rasterize_gsplat.gsplat_load_error(torch.device("cpu"))  # the probe runs on any device; CUDA in use
        assert found == expected if expected is None else found.startswith(expected)
    rasterize_gsplat.gsplat_load_error.cache_clear()
    monkeypatch.setattr(pidg.device, "gsplat_installed", lambda: True)
    monkeypatch.setattr(rasterize_gsplat, "gsplat_load_error", lambda device: "ImportError: no .so")
    with pytest.raises(DeviceUnavailable, match=r"gsplat is installed but cannot render on cuda \(ImportError: no .so\).*--backend torch"):
        rasterizer_for("auto", torch.device("cuda"))


def test_cuda_without_cuda_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(pidg.device, "cuda_available", lambda: False)
    data = write_procedural_dataset(ProceduralSceneConfig(n_train=4, n_test=1, width=16, height=16, n_gaussians=500), tmp_path / "data")
    code = main(["train", "--data.path", str(data), "--device", "cuda", "--output.dir", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no CUDA device is available" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_presets_follow_the_device_and_the_dataset(tmp_path):
    paper = {layout: apply_preset(TrainConfig(), "paper", layout) for layout in ("dnerf", "pidg", "hypernerf")}
    assert [paper[k].optim.iterations for k in ("dnerf", "pidg", "hypernerf")] == [50_000, 50_000, 40_000]
    assert all(c.densify.stop == 30_000 and c.optim.deformation_lr_decay_every == 20_000 for c in paper.values())
    assert [paper[k].deformation.grid4d.decoder_depth for k in ("dnerf", "pidg", "hypernerf")] == [0, 0, 1]
    assert [paper[k].densify.prune_world_scale for k in ("dnerf", "pidg", "hypernerf")] == [0.1, 0.015, 0.1]
    assert paper["dnerf"].deformation.grid4d == dataclasses.replace(TrainConfig().deformation.grid4d, decoder_depth=0)  # paper sizes
    cpu = apply_preset(TrainConfig(device="cpu"), "auto")
    assert cpu.preset == "cpu" and cpu.deformation.grid4d.width == 64 and cpu.optim.iterations == TrainConfig().optim.iterations
    assert cpu.material.width == 64 and paper["dnerf"].material == TrainConfig().material  # the paper's 256 on a GPU
    # the flow loss reads half its tiles a step on a CPU, all of them with the paper's settings
    assert cpu.flow.tile_fraction == 0.5 and all(c.flow.tile_fraction == 1.0 for c in paper.values())
    # on D-NeRF scenes the cpu preset also sets a schedule for a CPU's budget; other kinds keep the defaults
    cpu_dnerf = apply_preset(TrainConfig(device="cpu"), "cpu", "dnerf")
    assert (cpu_dnerf.optim.iterations, cpu_dnerf.densify.start, cpu_dnerf.densify.stop, cpu_dnerf.densify.opacity_reset_every,
            cpu_dnerf.gaussians.random_init_points, cpu_dnerf.densify.max_gaussians) == (12_000, 300, 5000, 2000, 20_000, 30_000)
    # ... and finer temporal grids along t (D-NeRF has up to 200 training times); the other grid settings stay the preset's
    assert cpu_dnerf.deformation.grid4d.temporal_grid.finest_resolution == (32, 32, 64)
    # ... with the warp soft-bounded there (its early excursions); elsewhere unbounded, as Grid4D
    g_dnerf, g_cpu = cpu_dnerf.deformation.grid4d, cpu.deformation.grid4d
    assert (g_dnerf.max_translation, g_dnerf.max_log_scale_change) == (1.0, 2.0)
    g_paper = paper["dnerf"].deformation.grid4d
    assert (g_cpu.max_translation, g_cpu.max_log_scale_change, g_paper.max_translation, g_paper.max_log_scale_change) == (0.0,) * 4
    assert cpu.deformation.grid4d.temporal_grid.finest_resolution == (32, 32, 16)
    assert dataclasses.replace(cpu_dnerf.deformation.grid4d.temporal_grid, finest_resolution=(32, 32, 16)) == cpu.deformation.grid4d.temporal_grid
    assert apply_preset(TrainConfig(device="cpu"), "cpu", "pidg").densify == TrainConfig().densify
    # the command line: the preset before the options, the dataset's layout from --data.path, recorded in config.json
    data = write_procedural_dataset(ProceduralSceneConfig(n_train=4, n_test=1, width=16, height=16, n_gaussians=500), tmp_path / "data")
    from pidg.cli import _train_config, build_parser

    args = build_parser().parse_args(["train", "--data.path", str(data), "--preset", "paper", "--optim.iterations", "7"])
    cfg = _train_config(args)
    assert cfg.preset == "paper" and cfg.densify.prune_world_scale == 0.015 and cfg.optim.iterations == 7  # options win
    cfg.output = dataclasses.replace(cfg.output, dir=tmp_path / "run")
    from pidg.config_tools import save_config

    save_config(cfg, tmp_path / "run" / "config.json")
    assert json.loads((tmp_path / "run" / "config.json").read_text())["preset"] == "paper"
