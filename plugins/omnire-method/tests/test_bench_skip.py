"""``omnire bench skip`` end to end (real subprocess, a few steps, a few thousand background
Gaussians and a 2000-ray LiDAR batch through ``--method-args``): without humans omnire
builds exactly streetgs's nodes; absent actors add instances and Gaussians that the timed
frames never render; LiDAR rendering on a scene without LiDAR adds no parameter."""
import json
import os
import subprocess
import sys

import pytest

from scene_helpers import DEMO_SCENE


@pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
def test_bench_skip_builds_no_human_machinery_and_adds_absent_actors(tmp_path):
    out_json = tmp_path / "skip.json"
    out = subprocess.run(
        [sys.executable, "-m", "omnire.cli", "bench", "skip", "--data", str(DEMO_SCENE), "--scale", "0.25",
         "--steps", "2", "--warmup", "1", "--extra-actors", "0", "20", "--output", str(out_json),
         "--method-args=--method.nodes.background.max-lidar-points 3000 --method.nodes.background.num-far-points 300 "
         "--method.lidar.rays-per-step 2000"],
        capture_output=True, text=True, timeout=900, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stdout + out.stderr
    result = json.loads(out_json.read_text())
    streetgs, omnire = result["no_humans"]
    assert (streetgs["method"], omnire["method"]) == ("streetgs", "omnire")
    assert omnire["nodes"] == streetgs["nodes"] and "smpl" not in omnire["nodes"]
    assert omnire["gaussians"] == streetgs["gaussians"]
    none, some = result["absent_actors"]
    assert some["rigid_instances"] == none["rigid_instances"] + 20 and some["gaussians"] > none["gaussians"]
    assert all(r["ms_per_step"] > 0 for r in result["no_humans"] + result["absent_actors"])
    assert "omnire overhead" in out.stdout
    off, on = result["lidar"][:2]  # LiDAR on for a scene without LiDAR: not one more parameter
    assert (off["lidar"], on["lidar"]) == (False, True) and off["scene"] == on["scene"] == "scene without LiDAR"
    assert on["parameters"] == off["parameters"] and on["gaussians"] == off["gaussians"]
    assert on["actors"] == off["actors"]
    if len(result["lidar"]) == 4:  # the rasterizer renders LiDAR: two features per Gaussian, and a node
        off, on = result["lidar"][2:]  # for each actor only the LiDAR sees (the demo cut has some)
        assert on["actors"] > off["actors"] and on["gaussians"] > off["gaussians"]
        assert on["parameters"] > off["parameters"] + 2 * on["gaussians"]
