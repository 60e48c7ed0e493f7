"""``omnire bench train`` end to end (real subprocesses, tiny budget)."""
import json
import os
import subprocess
import sys

import pytest

from scene_helpers import DEMO_SCENE


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_bench_train_compares_methods(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "bench", "train", "--methods", "3dgs", "street-fixed-boxes=streetgs --method.nodes.rigid.no-refine-boxes", "--dataparser", "pandaset", "--data", str(DEMO_SCENE),
         "--dataparser-args=--end-frame 12 --scale 0.25",
         "--method-args=--method.nodes.background.max-lidar-points 3000 --method.nodes.background.num-far-points 300",
         "--steps", "4", "--checkpoints", "2", "--output", str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stdout + out.stderr
    results = json.loads((tmp_path / "results.json").read_text())["results"]
    assert [r["method"] for r in results] == ["3dgs", "street-fixed-boxes"]
    assert "--method.nodes.rigid.no-refine-boxes" in results[1]["command"]
    run = json.loads((tmp_path / "runs" / "street-fixed-boxes" / "run.json").read_text())
    assert "no-refine-boxes" in json.dumps(run)
    for r in results:
        assert r["steps_done"] == 4 and len(r["curve"]) == 2  # one mid-way evaluation + the final one
        assert r["final"]["novel_view.views"] == 3 and r["final"]["peak_rss_mb"] > 0
    md = (tmp_path / "results.md").read_text()
    assert results[0]["rasterizer"] == results[1]["rasterizer"] == run["rasterizer"]
    assert f"Rasterizer: {run['rasterizer']} (every run)." in md
    assert "| street-fixed-boxes |" in md and "street-fixed-boxes = `streetgs --method.nodes.rigid.no-refine-boxes`" in md and "copy nearest training frame" in md and "4 steps" in md
    assert (tmp_path / "psnr_vs_time.png").stat().st_size > 1000
    # --report-only rebuilds the table and plot from results.json without training.
    (tmp_path / "results.md").unlink()
    (tmp_path / "psnr_vs_time.png").unlink()
    again = subprocess.run([sys.executable, "-m", "omnire.cli", "bench", "train", "--report-only", "--output", str(tmp_path)],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stdout + again.stderr
    assert (tmp_path / "results.md").read_text() == md and (tmp_path / "psnr_vs_time.png").stat().st_size > 1000
    # --reuse keeps results whose exact command ran before and trains only the new entry;
    # results.json holds both, also when the reused entry comes last.
    more = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "bench", "train", "--methods", "3dgs-dim=3dgs --method.nodes.background.init-opacity 0.05", "3dgs",
         "--dataparser", "pandaset", "--data", str(DEMO_SCENE), "--dataparser-args=--end-frame 12 --scale 0.25",
         "--method-args=--method.nodes.background.max-lidar-points 3000 --method.nodes.background.num-far-points 300",
         "--steps", "4", "--checkpoints", "2", "--output", str(tmp_path), "--reuse"],
        capture_output=True, text=True, timeout=900, env=dict(os.environ, COLUMNS="200"))
    assert more.returncode == 0, more.stdout + more.stderr
    assert "3dgs: reusing the earlier result" in more.stdout and "3dgs-dim=3dgs --method.nodes.background.init-opacity 0.05: training" in more.stdout
    merged = json.loads((tmp_path / "results.json").read_text())["results"]
    assert [r["method"] for r in merged] == ["3dgs-dim", "3dgs"] and merged[1] == results[0]


def test_same_step_table_when_a_time_budget_stops_methods_early():
    from omnire.bench.train import _same_step_table, common_step

    def result(name, steps):
        curve = [{"step": s, "train_seconds": s / 2, "novel_view.full_psnr": 20 + s / 1000, "num_gaussians": 5}
                 for s in steps]
        return {"method": name, "final": {}, "steps_done": steps[-1], "curve": curve}

    results = [result("fast", [500, 1000, 1500, 2000]), result("slow", [500, 1000, 1500, 1730]),
               {"method": "broken", "exit_code": 1}]
    assert common_step(results) == 1500
    lines = _same_step_table(results)
    assert "every method at step 1500" in lines[1]
    assert lines[-1] == "| slow | - | - | - | 21.50 | - | - | - | - | 5 | 750 |"
    # Everyone finished the same steps: no second table.
    assert _same_step_table([result("a", [500, 1000]), result("b", [500, 1000])]) == []


def test_runs_on_different_rasterizers_are_flagged():
    from omnire.bench.train import rasterizer_line

    ok = [{"method": "a", "final": {}, "rasterizer": "cpu"}, {"method": "b", "final": {}, "rasterizer": "cpu"},
          {"method": "broken", "exit_code": 1}]
    assert rasterizer_line(ok) == "Rasterizer: cpu (every run)."
    # e.g. the native build failed between two runs and ``auto`` fell back to torch
    mixed = ok[:1] + [{"method": "b", "final": {}, "rasterizer": "torch"}, {"method": "old", "final": {}}]
    line = rasterizer_line(mixed)
    assert line.startswith("**Warning: the runs used different rasterizers")
    assert "a: cpu, b: torch, old: unrecorded." in line
