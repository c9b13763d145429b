"""Benchmarks score the motion against ground truth where a scene carries it: the quality table and the suite's
Markdown gain the motion columns, and keep them out otherwise."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses
import shutil

import pytest

from pidg.bench.quality import format_table
from pidg.bench.suite import build_tables, make_jobs, run_job, tables_markdown
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.deformation import HashGridConfig
from pidg.training.config import TrainConfig

GT_KEYS = {"gt_motion_flow_epe", "gt_velocity_flow_epe", "gt_zero_motion_epe", "gt_velocity_rel_deformation",
           "gt_velocity_rel_field", "gt_coverage", "gt_target_flow_epe", "gt_track_rel", "gt_track_rel_seen", "gt_spin_rel"}


def _row(scene, variant, **extra):
    return {"scene": scene, "variant": variant, "psnr": 20.0, "ssim": 0.8, "ssim_zeros": 0.81, "lpips_alex": None,
            "lpips_vgg": 0.2, "train_minutes": 1.0, "iterations": 10, "iterations_per_second": 2.0, "gaussians": 1000,
            "peak_rss_mb": 500.0, "render_fps": 9.0, **extra}


def test_tables_show_motion_columns_only_with_ground_truth():
    plain = [_row("a", "base"), _row("a", "cmr")]
    assert "gtEPE-m" not in format_table(plain)
    assert build_tables(plain, ("psnr",))["motion"] == {}
    assert "Motion against ground-truth motion" not in tables_markdown(build_tables(plain, ("psnr",)), "t")
    gt = {"gt_motion_flow_epe": 0.95, "gt_velocity_flow_epe": None, "gt_zero_motion_epe": 1.62,
          "gt_velocity_rel_deformation": 0.659, "gt_velocity_rel_field": None, "gt_coverage": 0.729,
          "gt_target_flow_epe": 0.74, "gt_track_rel": 0.413, "gt_track_rel_seen": 0.208, "gt_spin_rel": 0.871}
    rows = [_row("a", "base", **gt), _row("a", "cmr", **{**gt, "gt_velocity_flow_epe": 1.5, "gt_velocity_rel_field": 0.9})]
    table = format_table(rows).splitlines()
    assert "gtEPE-m" in table[0] and "relV-v" in table[0] and "cover" in table[0] and "gtEPE-tgt" in table[0] and "track" in table[0]
    assert table[1].split()[-10:] == ["0.95", "-", "1.62", "0.659", "-", "0.729", "0.74", "0.413", "0.208", "0.871"]
    assert table[0].split()[-4:] == ["gtEPE-tgt", "track", "track-seen", "spin"]  # names wider than a column stay apart
    assert len(table[0]) == len(table[1])  # and the figures stay under them
    tables = build_tables(rows, ("psnr",))
    assert tables["motion"]["PIDG w/o LPFM"]["gt_velocity_rel_field"] == pytest.approx(0.9)
    text = tables_markdown(tables, "t")
    assert "Motion against ground-truth motion" in text and "| PIDG w/o (CMR + LPFM) | 0.95 | - | 1.62 | 0.659 | - | 0.729 | 0.74 | 0.413 | 0.208 | 0.871 |" in text


@pytest.mark.filterwarnings("ignore:ms_ssim reported as None")  # 32 px images are below MS-SSIM's minimum
def test_a_bench_job_on_a_scene_with_ground_truth_scores_its_motion(tmp_path):
    with_gt = write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=2, width=32, height=32, n_gaussians=600, n_init_points=150), tmp_path / "ring"
    )
    without = tmp_path / "plain"
    shutil.copytree(with_gt, without, ignore=shutil.ignore_patterns("motion_gt"))
    cfg = TrainConfig(preset="none")
    cfg.deformation.grid4d = dataclasses.replace(
        cfg.deformation.grid4d, spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16
    )
    cfg.physics = dataclasses.replace(cfg.physics, samples=32, block_size=32)
    cfg.material = dataclasses.replace(cfg.material, width=16, embedding_dim=4)
    cfg.densify = dataclasses.replace(cfg.densify, start=1000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=3)
    cfg.output = dataclasses.replace(cfg.output, checkpoint_every=0, progress=False, preview_every=0)
    jobs = make_jobs([with_gt, without], ["cmr"], cfg, tmp_path / "out", None)
    jobs = [dataclasses.replace(j, lpips_nets=()) for j in jobs]
    (scored,), (plain,) = (run_job(j) for j in jobs)
    assert not scored.get("error") and not plain.get("error")
    assert GT_KEYS <= set(scored) and scored["gt_velocity_flow_epe"] is not None and 0 <= scored["gt_coverage"] <= 1
    assert scored["gt_target_flow_epe"] is not None and scored["gt_target_flow_epe"] >= 0
    assert scored["gt_track_rel"] is not None and scored["gt_track_rel"] >= 0
    assert scored["gt_track_rel_seen"] is not None and scored["gt_track_rel_seen"] >= 0
    assert (jobs[0].run_dir / "eval_test" / "motion_gt.json").is_file()
    assert not GT_KEYS & set(plain) and not (jobs[1].run_dir / "eval_test" / "motion_gt.json").exists()
    assert "gtEPE-v" in format_table([scored, plain]) and "gtEPE-v" not in format_table([plain])
