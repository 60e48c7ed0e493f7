"""``omnire render RUN --lidar``: point clouds (PLY read back by plyfile, npz) of a run trained
with LiDAR on a synthetic scene (``omnire synth urban --tiny``), at the recorded pose and
from a moved sensor; refused, in one line, for a run without LiDAR features."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hostile import run_case
from scene_helpers import TINY_RUN_KEY, make_tiny_run

from omnire.lidarpoints import POINT_FIELDS

plyfile = pytest.importorskip("plyfile")


@pytest.fixture(scope="module")
def lidar_run(tmp_path_factory):
    """omnire synth urban --tiny (one camera), 3dgs with LiDAR rendering, 2 steps."""
    import torch

    from omnire.plugins import load_plugins
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("lidar-run")
    plugins = load_plugins()
    scene = root / "scene"
    assert plugins.commands.get("synth").main(["urban", str(scene), "--tiny", "--num-cameras", "1"], plugins) in (0,
                                                                                                                  None)
    argv = ["3dgs", "processed", "--data", str(scene), "--trainer.max-steps", "2", "--trainer.output-dir",
            str(root / "runs"), "--trainer.run-name", "lidar", "--trainer.no-progress", "--trainer.eval-train-views",
            "1", "--trainer.threads", "1", "--method.rasterizer", "cpu", "--method.lidar.enabled",
            "--method.lidar.every", "1", "--method.lidar.rays-per-step", "2000",
            "--method.nodes.background.max-lidar-points", "3000", "--method.nodes.background.num-far-points", "300"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return root / "runs" / "lidar"


def render(run, out, *extra):
    proc = subprocess.run([sys.executable, "-m", "omnire.cli", "render", str(run), "--lidar", "--frames", "0",
                           "--output", str(out), *extra], capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    stems = sorted(p.with_suffix("") for p in (out / "lidar").glob("*.ply"))
    assert len(stems) == 1
    return stems[0]


def test_render_lidar_writes_the_same_points_as_ply_and_npz(lidar_run, tmp_path):
    stem = render(lidar_run, tmp_path / "a")
    vertex = plyfile.PlyData.read(str(stem) + ".ply")["vertex"]
    npz = np.load(str(stem) + ".npz")
    assert [p.name for p in vertex.properties] == [name for name, _ in POINT_FIELDS] == sorted(npz.files, key=[
        name for name, _ in POINT_FIELDS].index)
    assert len(vertex["x"]) > 100
    for name, kind in POINT_FIELDS:
        np.testing.assert_array_equal(vertex[name], npz[name])
        assert npz[name].dtype == np.dtype(kind)
    xyz = np.stack([npz["x"], npz["y"], npz["z"]], 1)
    assert np.isfinite(xyz).all() and ((npz["intensity"] >= 0) & (npz["intensity"] <= 1)).all()
    # a sensor moved 2 m to its left sees the same scene from elsewhere: other points
    moved = np.load(str(render(lidar_run, tmp_path / "b", "--lidar-shift", "0", "2", "0")) + ".npz")
    assert len(moved["x"]) > 100 and not np.array_equal(moved["x"], npz["x"][:len(moved["x"])])


def test_render_lidar_refuses_a_run_without_lidar(tmp_path_factory, tmp_path, capsys):
    run = make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)
    out = tmp_path / "out"
    run_case("render --lidar of a run without LiDAR features", ["render", str(run), "--lidar", "--output", str(out)],
             capsys, [run], needles=("--lidar", "learned no LiDAR"), surface="render")
    assert not out.exists() or not any(out.iterdir())
