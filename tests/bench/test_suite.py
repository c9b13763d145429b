"""The paper's tables by one command: scenes found in a folder, jobs that run anywhere and fail alone, tables shaped
like the paper's (per scene, average, best in bold), the future-prediction protocol end to end on tiny scenes."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import json
import os
from pathlib import Path

import pytest

from pidg.bench.executors import make_executor, run_local, run_process_pool
from pidg.bench.suite import Job, build_tables, crashed_job, discover_scenes, make_jobs, run_job, run_suite, tables_markdown
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.deformation import HashGridConfig
from pidg.pipeline import evaluate_run
from pidg.training.config import TrainConfig

TINY = ProceduralSceneConfig(n_train=9, n_test=3, width=32, height=32, n_gaussians=600, n_init_points=150)


@pytest.fixture(scope="module")
def scenes_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    write_procedural_dataset(TINY, root / "alpha")
    write_procedural_dataset(dataclasses.replace(TINY, seed=1), root / "beta")
    (root / "notes").mkdir()  # not a dataset: ignored
    return root


def tiny_train_config(iterations: int = 4) -> TrainConfig:
    cfg = TrainConfig(preset="none")
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.deformation.mlp = dataclasses.replace(cfg.deformation.mlp, width=16, depth=3, skips=(1,))
    cfg.physics = dataclasses.replace(cfg.physics, samples=32, block_size=32)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=4)
    cfg.densify = dataclasses.replace(cfg.densify, start=1000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=iterations)
    cfg.output = dataclasses.replace(cfg.output, checkpoint_every=0, progress=False, preview_every=0)
    return cfg


def test_scenes_come_from_the_folder(scenes_root):
    assert [p.name for p in discover_scenes(scenes_root, "pidg")] == ["alpha", "beta"]
    assert [p.name for p in discover_scenes(scenes_root / "beta", "pidg")] == ["beta"]  # one scene folder
    with pytest.raises(FileNotFoundError, match="no dnerf scene"):
        discover_scenes(scenes_root, "dnerf")
    with pytest.raises(FileNotFoundError, match="no such folder"):
        discover_scenes(scenes_root / "missing", "pidg")


def _row(scene, variant, psnr, ssim, lpips, **extra):
    return {"scene": scene, "variant": variant, "psnr": psnr, "ssim": ssim - 0.01, "ssim_zeros": ssim, "lpips_vgg": lpips,
            "train_minutes": 1.0, "iterations_per_second": 2.0, "gaussians": 1000, "peak_rss_mb": 500.0, "render_fps": 9.0, **extra}


def test_tables_have_per_scene_cells_averages_and_the_best_in_bold():
    rows = [
        _row("a", "base", 30.0, 0.95, 0.05), _row("b", "base", 20.0, 0.90, 0.10),
        _row("a", "cmr", 31.0, 0.94, 0.04), _row("b", "cmr", 21.0, 0.91, 0.12),
        _row("a", "full", 29.0, 0.93, 0.06), {"scene": "b", "variant": "full", "error": "RuntimeError: boom"},
    ]
    tables = build_tables(rows, ("psnr", "ssim", "lpips_vgg"), ssim="zeros")
    assert tables["metrics"] == ["psnr", "ssim_zeros", "lpips_vgg"]
    assert tables["average"]["PIDG w/o LPFM"]["psnr"] == pytest.approx(26.0)
    assert tables["average"]["PIDG (full)"]["psnr"] is None  # a failed scene: no average
    assert tables["best"]["a"] == {"psnr": 31.0, "ssim_zeros": 0.95, "lpips_vgg": 0.04}  # LPIPS: lower is better
    assert tables["best"]["average"]["lpips_vgg"] == pytest.approx(0.075)
    assert tables["failures"] == [{"scene": "b", "method": "PIDG (full)", "error": "RuntimeError: boom"}]
    text = tables_markdown(tables, "t")
    assert "zero-padded" in text and "a SSIM↑" in text and "average LPIPS-V↓" in text
    quality = text.split("Efficiency")[0]
    lines = {line.split(" | ")[0][2:]: line for line in quality.splitlines() if line.startswith("| PIDG")}
    assert "**31.00**" in lines["PIDG w/o LPFM"] and "**0.950**" in lines["PIDG w/o (CMR + LPFM)"]
    assert "**26.00**" in lines["PIDG w/o LPFM"] and "**0.075**" in lines["PIDG w/o (CMR + LPFM)"]
    assert "b / PIDG (full): RuntimeError: boom" in text
    valid = build_tables(rows, ("psnr", "ssim"), ssim="valid")
    assert valid["metrics"] == ["psnr", "ssim"] and valid["best"]["a"]["ssim"] == pytest.approx(0.94)


def test_a_suite_runs_every_job_records_provenance_and_reports_a_failure(scenes_root, tmp_path):
    out = tmp_path / "suite"
    result = run_suite("pidg", scenes_root, out, tiny_train_config(), minutes=None, variants=["base", "nostress", "mlp_cmr"],
                       scenes=["alpha"], log=lambda s: None)
    rows = result["rows"]
    assert [(r["scene"], r["variant"]) for r in rows] == [("alpha", "base"), ("alpha", "nostress"), ("alpha", "mlp_cmr")]
    # the plug-in row: an MLP deformation trained with the material field and L_CMR
    assert rows[2]["config"]["deformation"]["kind"] == "mlp" and rows[2]["cmr_final"] >= 0
    assert all(not r.get("error") and r["iterations"] == 4 and r["psnr"] > 5 for r in rows)
    assert rows[1]["config"]["material"]["stress"] is False and rows[0]["config"]["physics"]["kind"] == "none"
    assert all(r["machine"]["cpus"] == os.cpu_count() and "git_commit" in r for r in rows)
    assert rows[0]["config"]["optim"]["seed"] == rows[1]["config"]["optim"]["seed"]
    assert (out / "alpha" / "base" / "eval_test" / "metrics.json").is_file()
    assert "PIDG w/o LPFM, no stress" in (out / "suite.md").read_text()
    # a job that cannot run is a row with its error, and the job after it still runs
    jobs = make_jobs([scenes_root / "alpha"], ["base"], tiny_train_config(), tmp_path / "more", None)
    broken = Job(str(tmp_path / "no_such_scene"), "base", {**jobs[0].config, "data": {**jobs[0].config["data"],
                 "path": str(tmp_path / "no_such_scene")}, "output": {**jobs[0].config["output"], "dir": str(tmp_path / "x")}})
    got = []
    run_local([broken, jobs[0]], run_job, crashed_job, got.extend)
    assert "no_such_scene" in got[0]["error"] and not got[1].get("error")
    assert (tmp_path / "x" / "error.txt").is_file()
    with pytest.raises(FileNotFoundError, match="no pidg scene named gamma"):
        run_suite("pidg", scenes_root, out, tiny_train_config(), minutes=None, scenes=["gamma"], log=lambda s: None)


def test_future_prediction_scores_the_deformation_and_the_advection(scenes_root, tmp_path):
    base = tiny_train_config()
    base.data = dataclasses.replace(base.data, train_until=0.7)
    jobs = make_jobs([scenes_root / "beta"], ["base", "cmr"], base, tmp_path, None, protocol="future", integrator="midpoint")
    rows = [r for job in jobs for r in run_job(job)]
    assert [(r["variant"], r["predictor"]) for r in rows] == [
        ("base", "deformation"), ("base", "hold"), ("cmr", "deformation"), ("cmr", "advection"), ("cmr", "hold")
    ]
    assert all(r["t_last"] <= 0.7 and r["psnr"] > 5 for r in rows)
    saved = json.loads((tmp_path / "beta" / "cmr" / "eval_future" / "advection" / "metrics.json").read_text())
    assert saved["integrator"] == "midpoint" and all(v["time"] > 0.7 for v in saved["per_view"])
    tables = build_tables(rows, ("psnr", "ssim"))
    assert tables["methods"][:4] == ["PIDG w/o (CMR + LPFM) [deformation]", "PIDG w/o (CMR + LPFM) [hold]",
                                     "PIDG w/o LPFM [deformation]", "PIDG w/o LPFM [advection]"]
    # holding the last trained state still is the zero-motion baseline: it differs from the deformation's extrapolation
    assert rows[0]["psnr"] != rows[1]["psnr"]
    with pytest.raises(ValueError, match="train_until"):
        make_jobs([scenes_root / "beta"], ["base"], tiny_train_config(), tmp_path, None, protocol="future")
    # pidg eval on such a run scores the future frames too, with the same figures
    result = evaluate_run(tmp_path / "beta" / "cmr", lpips_nets=(), device="cpu")
    assert set(result["future"]) == {"deformation", "advection", "hold"}
    assert result["future"]["deformation"]["mean"]["psnr"] == pytest.approx(rows[2]["psnr"], abs=1e-6)


# ---- executors (job functions at module level: they are pickled to workers) -------------------------------------
def _square(job):
    if job == "die":
        os._exit(3)  # a worker that dies without a word
    if job == "raise":
        raise RuntimeError("should have been caught by the job function")
    return [{"job": job, "value": job * job}]


def _crashed(job, message):
    return [{"job": job, "error": message}]


def test_the_process_pool_runs_jobs_in_other_processes_and_reports_a_dead_worker():
    got = []
    run_process_pool([2, 3], _square, _crashed, got.extend, workers=2)
    assert sorted(r["value"] for r in got) == [4, 9]
    got = []
    run_process_pool(["die"], _square, _crashed, got.extend, workers=1)
    assert got[0]["job"] == "die" and "worker process died" in got[0]["error"]


def test_the_ray_executor_runs_jobs_as_tasks_and_keeps_the_others_when_one_fails(scenes_root, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is an optional extra (pip install ray)")
    # workers import this test module by name, as pytest did (rootdir-relative, no package)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": str(Path(__file__).parent)}})
    try:
        got = []
        make_executor("ray")([2, "die", "raise", 5], _square, _crashed, got.extend)
        by_job = {r["job"]: r for r in got}
        assert by_job[2]["value"] == 4 and by_job[5]["value"] == 25
        assert "ray task failed" in by_job["die"]["error"] and "RuntimeError" in by_job["raise"]["error"]
        # a real suite job, trained and evaluated inside a Ray worker, gathered into the same table
        result = run_suite("pidg", scenes_root, tmp_path / "suite", tiny_train_config(), minutes=None, variants=["base"],
                           scenes=["alpha"], executor=make_executor("ray"), log=lambda s: None)
        (row,) = result["rows"]
        assert not row.get("error") and row["psnr"] > 5 and row["machine"]["host"]
        assert result["tables"]["cells"]["PIDG w/o (CMR + LPFM)"]["alpha"]["psnr"] == row["psnr"]
    finally:
        ray.shutdown()


def test_rows_without_lpfm_leave_out_what_is_made_from_the_flow(scenes_root, tmp_path):
    """The rigid-body setting tracks bodies through the optical flow: its w/o-LPFM rows (and every row without the
    flow) start from rest without the tracks term, so they neither read the flow nor stop at the missing cache; the
    full row keeps the base config's start and term."""
    base = tiny_train_config()
    base = dataclasses.replace(base, optim=dataclasses.replace(base.optim, motion_start="rigid_tracks", lambda_tracks=0.3))
    jobs = {j.variant: j.config for j in make_jobs([scenes_root / "alpha"], ["base", "cmr", "full", "nostress", "mlp_cmr"],
                                                   base, tmp_path / "jobs", None)}
    for variant in ("base", "cmr", "nostress", "mlp_cmr"):
        config = jobs[variant]
        assert (config["flow"]["kind"], config["optim"]["motion_start"], config["optim"]["lambda_tracks"]) == ("none", "rest", 0.0)
    full = jobs["full"]
    assert (full["flow"]["kind"], full["optim"]["motion_start"], full["optim"]["lambda_tracks"]) == ("lpfm", "rigid_tracks", 0.3)


def test_seeds_give_one_job_each_and_a_spread_per_scene_and_variant(scenes_root, tmp_path):
    """``pidg bench quality --seeds``: one run per seed in its own folder, trained with that seed (different
    Gaussians from the first step: a different run); the spread line is the mean, sample sd and range of the rows."""
    import statistics

    from pidg.bench.quality import format_table, run_quality_bench, seed_spread

    jobs = make_jobs([scenes_root / "alpha"], ["base", "cmr"], tiny_train_config(), tmp_path / "jobs", None, seeds=[3, 11])
    assert [(j.variant, j.config["optim"]["seed"], j.run_dir.name) for j in jobs] == [
        ("base", 3, "seed3"), ("base", 11, "seed11"), ("cmr", 3, "seed3"), ("cmr", 11, "seed11")]
    logged: list[str] = []
    rows = run_quality_bench([scenes_root / "alpha"], tmp_path / "q", tiny_train_config(), variants=["base"], minutes=None,
                             log=logged.append, seeds=[3, 11])
    assert [r["seed"] for r in rows] == [3, 11] and not any(r.get("error") for r in rows)
    assert rows[0]["psnr"] != rows[1]["psnr"]  # another seed is another run
    (entry,) = seed_spread(rows)
    psnrs = [r["psnr"] for r in rows]
    assert entry["seeds"] == [3, 11] and entry["failed"] == 0
    assert entry["psnr"] == pytest.approx({"mean": statistics.fmean(psnrs), "sd": statistics.stdev(psnrs),
                                           "min": min(psnrs), "max": max(psnrs)})
    saved = json.loads((tmp_path / "q" / "quality_seeds.json").read_text())
    assert saved[0]["psnr"]["mean"] == pytest.approx(entry["psnr"]["mean"])
    table = format_table(rows)
    assert "base/s3" in table and "base/s11" in table and "alpha base, 2 seeds: psnr" in table
    assert seed_spread(rows[:1]) == [] and seed_spread([rows[0], {**rows[1], "error": "boom"}]) == []
    with pytest.raises(ValueError, match="--seeds: distinct"):
        run_quality_bench([scenes_root / "alpha"], tmp_path / "bad", tiny_train_config(), seeds=[1, 1])
