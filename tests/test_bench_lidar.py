"""``omnire bench lidar`` and the LiDAR figures of ``omnire eval`` end to end: real
subprocesses on the demo scene cut to 12 frames at a tiny budget, the figures checked
against the evaluation and the baselines run directly in this process."""
import json
import math
import os
import subprocess
import sys

import pytest

from scene_helpers import DEMO_SCENE

LIDAR_KEYS = ("median_abs_range_error", "mean_abs_range_error", "mean_relative_range_error", "range_coverage",
              "intensity_rmse", "drop_accuracy", "drop_f1", "chamfer", "vehicle_median_abs_range_error",
              "vehicle_returns", "human_returns", "rays", "returns")


def _same(a, b, rel=0.0):
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return a == pytest.approx(b, rel=rel, abs=0.0)


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_bench_lidar_rows_equal_the_evaluation_and_the_baselines_run_directly(tmp_path):
    import torch

    from omnire.api import baseline_metrics
    from omnire.bench.train import TrainBenchArgs, markdown_table
    from omnire.lidar_evaluation import evaluate_lidar, format_value
    from omnire.plugins import load_plugins
    from omnire.runtime import Reconstruction

    method_args = ("--method.nodes.background.max-lidar-points 3000 --method.nodes.background.num-far-points 300 "
                   "--method.lidar.every 1 --method.lidar.rays-per-step 2000")
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "bench", "lidar", "--methods", "3dgs", "--dataparser", "pandaset",
         "--data", str(DEMO_SCENE), "--dataparser-args=--end-frame 12 --scale 0.25", f"--method-args={method_args}",
         "--steps", "4", "--checkpoints", "2", "--threads", "1", "--output", str(tmp_path)],
        capture_output=True, text=True, timeout=600, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stdout + out.stderr
    saved = json.loads((tmp_path / "results.json").read_text())
    [result] = saved["results"]
    assert "--method.lidar.enabled" in result["command"]
    final = result["final"]
    # the trainer's periodic evaluation carries the LiDAR figures: one mid-way, one final
    assert [c["step"] for c in result["curve"]] == [2, 4]
    assert all(c["lidar.sweeps"] == 1 and c["lidar.rays"] == 64 * 1800 for c in result["curve"])
    assert result["curve"][0]["lidar.median_abs_range_error"] != final["lidar.median_abs_range_error"]

    # The rendered row is the evaluation of the final checkpoint, redone here.
    run_dir = tmp_path / "runs" / "3dgs"
    torch.set_num_threads(1)
    recon = Reconstruction.from_run(run_dir, load_plugins())
    assert recon.step == 4
    scene = recon.scene
    again = evaluate_lidar(recon)
    for key in LIDAR_KEYS:
        assert _same(final[f"lidar.{key}"], again[key], rel=1e-5), key
    # The baseline rows are omnire.lidar_baselines run directly on the same scene and split.
    direct = baseline_metrics(scene, scene.test_frames, scene.train_frames)
    assert set(direct) == {"nearest_sweep", "mesh"}
    for name, figures in direct.items():
        for key in LIDAR_KEYS:
            assert _same(final[f"lidar_baselines.{name}.{key}"], figures[key]), (name, key)

    md = (tmp_path / "results.md").read_text()
    nearest = direct["nearest_sweep"]
    assert (f"| nearest training sweep, moved | {format_value(nearest['median_abs_range_error'], 4)} | "
            f"{format_value(nearest['mean_abs_range_error'], 3)} |") in md
    assert f"| 3dgs | {format_value(final['lidar.median_abs_range_error'], 4)} |" in md
    assert "4 steps" in md and "## Cameras of the same runs" in md
    assert (tmp_path / "lidar_error_vs_time.png").stat().st_size > 1000
    # bench train's table carries the same LiDAR rows for runs that learned LiDAR
    train_md = markdown_table(saved["results"], TrainBenchArgs(dataparser="pandaset", data=DEMO_SCENE, steps=4))
    assert "LiDAR on the held-out sweeps" in train_md and "| mesh of the 4 nearest training sweeps |" in train_md

    # omnire eval prints the same table: the rendered sweeps and both baselines
    ev = subprocess.run([sys.executable, "-m", "omnire.cli", "eval", str(run_dir), "--train-views", "1"],
                        capture_output=True, text=True, timeout=600, env=dict(os.environ, COLUMNS="250"))
    assert ev.returncode == 0, ev.stdout + ev.stderr
    assert "LiDAR on held-out sweeps (sweeps: 1)" in ev.stdout
    rows = {line.split("│")[1].strip(): line for line in ev.stdout.splitlines() if line.count("│") > 5}
    assert format_value(nearest["median_abs_range_error"], 4) in rows["nearest training sweep, moved"]
    assert format_value(again["median_abs_range_error"], 4) in rows["rendered"]


@pytest.mark.parametrize("case", ["no budget", "no scene", "report without results", "bad methods entry"])
def test_bad_bench_lidar_arguments_are_one_line(case, tmp_path, capsys):
    from hostile import run_case

    scene = ["--dataparser", "pandaset", "--data", str(DEMO_SCENE)]
    argv, needle = {
        "no budget": (["--steps", "0", *scene], "expected a step budget, a time budget or both"),
        "no scene": (["--steps", "4"], "--dataparser and --data are required"),
        "report without results": (["--report-only"], "no results.json to report from"),
        "bad methods entry": (["--methods", "=3dgs", "--steps", "4", *scene], "expected METHOD or LABEL=METHOD"),
    }[case]
    run_case(f"bench lidar: {case}", ["bench", "lidar", *argv, "--output", str(tmp_path / "out")], capsys,
             [tmp_path], needles=(needle,), surface="sim")
    assert not (tmp_path / "out" / "results.json").exists()
