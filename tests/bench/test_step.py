"""``pidg bench step`` times the steps of a run past its first epoch: the flow term finds the depths of frame t+1
kept from training renders, so a timed step renders once, as in a real run."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import json

import torch

from pidg.bench.step import _load_trained_model, format_step_table, run_step_bench
from pidg.checkpoint import CHECKPOINT_FILE
from pidg.data import load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.deformation import HashGridConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.training.config import TrainConfig
from pidg.training.trainer import Trainer


def test_step_bench_times_steady_state_steps(tmp_path, monkeypatch):
    n_train = 6
    root = write_procedural_dataset(
        ProceduralSceneConfig(n_train=n_train, n_test=1, width=32, height=32, n_gaussians=600, n_init_points=200), tmp_path / "scene"
    )
    cfg = TrainConfig()
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=8)
    cfg.physics = dataclasses.replace(cfg.physics, samples=64, block_size=32)
    cfg.gaussians = dataclasses.replace(cfg.gaussians, init_opacity=0.8)
    cfg.output = dataclasses.replace(cfg.output, dir=tmp_path / "runs")
    renders = []
    original = DynamicGaussians.prepare_render  # every render starts here
    monkeypatch.setattr(DynamicGaussians, "prepare_render", lambda self, *a, **k: renders.append(1) or original(self, *a, **k))
    warmup, iterations = 3, 4
    results = run_step_bench(
        root, cfg, ["base", "full"], downscale=None, gaussians=200, iterations=iterations, warmup=warmup, chunk=2,
        out=tmp_path / "step.json", log=lambda _: None
    )
    written = json.loads((tmp_path / "step.json").read_text())
    assert set(written["variants"]) == {"base", "full"} and written["machine"]["cpu_target"] and "git_commit" in written
    assert {"flow", "flow_target", "physics"} <= set(results["full"]["step_breakdown_ms"])
    assert "flow" not in results["base"]["step_breakdown_ms"]
    # one ratio per interleaved round, to the first variant's round (itself: 1)
    assert results["base"]["round_ratios"] == [1.0, 1.0]
    assert len(results["full"]["round_ratios"]) == iterations // 2 and all(r > 0 for r in results["full"]["round_ratios"])
    assert written["variants"]["full"]["round_ratios"] == results["full"]["round_ratios"]
    # base: one render per step; full: one per training frame to start from (its kept depths), then one per step
    assert len(renders) == 2 * (warmup + iterations) + n_train


def test_step_bench_from_a_run_starts_from_its_optimiser_moments(tmp_path):
    """``--from-run`` takes the run's Adam moments with its Gaussians and deformation (a long run's moments cost what
    fresh ones do not: its denormal ones), and leaves a field the run did not have (the material field) fresh."""
    root = write_procedural_dataset(
        ProceduralSceneConfig(n_train=4, n_test=1, width=24, height=24, n_gaussians=500, n_init_points=100), tmp_path / "scene"
    )
    cfg = TrainConfig(device="cpu")
    cfg.data = dataclasses.replace(cfg.data, path=root, progress=False)
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.optim = dataclasses.replace(cfg.optim, iterations=3)
    cfg.output = dataclasses.replace(cfg.output, dir=tmp_path / "run", progress=False, preview_every=0)
    scene = load_scene(cfg.data)
    run = Trainer(cfg, scene)
    run.train()
    full = dataclasses.replace(cfg, physics=dataclasses.replace(cfg.physics, kind="cmr"), output=dataclasses.replace(cfg.output, dir=tmp_path / "bench"))
    trainer = Trainer(full, scene)
    _load_trained_model(trainer, tmp_path / "run" / CHECKPOINT_FILE, log=lambda _: None)
    for name in ("means", "sh_dc", "deformation"):
        saved, loaded = run.optimizers[name].optimizer.state_dict()["state"], trainer.optimizers[name].optimizer.state_dict()["state"]
        assert saved.keys() == loaded.keys() and len(saved) > 0
        assert all(torch.equal(saved[k]["exp_avg"], loaded[k]["exp_avg"]) for k in saved)
    assert "material" in trainer.optimizers and not trainer.optimizers["material"].optimizer.state


def test_the_step_table_gives_the_ratio_with_its_rounds_spread():
    def variant(rate, rounds):
        return {"iterations_per_second": rate, "gaussians": 10, "step_breakdown_ms": {"render": 1.0}, "projected_minutes": 1.0,
                "projected_iterations": 100, "round_ratios": rounds}

    text = format_step_table({"base": variant(10.0, [1.0, 1.0, 1.0]), "full": variant(6.0, [1.6, 1.7, 1.65])}, "scene")
    assert "full: step time x1.67 of base (its 3 rounds: x1.60 to x1.70, median x1.65)" in text
