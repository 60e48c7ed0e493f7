"""The CLI as a user meets it (real subprocesses): train -> eval -> render on a small
cut of the demo scene, and clear errors for bad input."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from scene_helpers import DEMO_SCENE

pytestmark = pytest.mark.skipif(not DEMO_SCENE.is_dir(), reason="demo scene not in this checkout")
OMNIRE = [sys.executable, "-m", "omnire.cli"]
SMALL = ["--end-frame", "4", "--holdout-every", "2", "--scale", "0.25", "--method.rasterizer", "torch",
         "--method.nodes.background.max-lidar-points", "3000", "--method.nodes.background.num-far-points", "300",
         "--trainer.no-progress", "--trainer.eval-train-views", "2"]


def run(args, timeout=600):
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run(OMNIRE + args, capture_output=True, text=True, env=env, timeout=timeout)


def test_train_eval_render_round_trip(tmp_path):
    out = run(["train", "3dgs", "pandaset", "--data", str(DEMO_SCENE), *SMALL, "--trainer.max-steps", "4",
               "--trainer.output-dir", str(tmp_path), "--trainer.run-name", "r"])
    assert out.returncode == 0, out.stderr
    assert "PSNR" in out.stdout and "novel view" in out.stdout
    run_dir = tmp_path / "r"
    info = json.loads((run_dir / "run.json").read_text())
    assert info["method"] == "3dgs" and "PandaSet" in info["attribution"]
    out = run(["eval", str(run_dir)])
    assert out.returncode == 0, out.stderr
    assert (run_dir / "eval" / "step-000004.json").is_file()
    out = run(["render", str(run_dir), "--frames", "1", "2", "--cameras", "front_camera", "--depth",
               "--shift", "0.5", "0", "0"])
    assert out.returncode == 0, out.stderr
    pngs = sorted(p.name for p in (run_dir / "renders").glob("*.png"))
    assert len(pngs) == 4 and any("depth" in p for p in pngs)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--data", "/nonexistent/scene"], "/nonexistent/scene"),
        (["--data", str(DEMO_SCENE), "--cameras", "roof_camera"], "roof_camera"),
        (["--data", str(DEMO_SCENE), "--start-frame", "30", "--end-frame", "90"], "outside the log"),
        (["--data", str(DEMO_SCENE), "--trainer.max-steps", "many"], "--trainer.max-steps"),
    ],
)
def test_bad_input_gives_clear_error(args, needle, tmp_path):
    out = run(["train", "3dgs", "pandaset", *args, "--trainer.output-dir", str(tmp_path)])
    assert out.returncode == 2
    assert needle in out.stderr + out.stdout
    assert "Traceback" not in out.stderr


def test_unreadable_image_is_named(tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(DEMO_SCENE, scene)
    bad = scene / "camera" / "front_camera" / "01.jpg"
    bad.write_bytes(b"not a jpeg at all")
    out = run(["train", "3dgs", "pandaset", "--data", str(scene), *SMALL, "--trainer.max-steps", "2",
               "--trainer.output-dir", str(tmp_path)])
    assert out.returncode == 2, out.stdout + out.stderr
    assert "01.jpg" in out.stderr and "Traceback" not in out.stderr


def test_unknown_command_and_method():
    out = run(["fly"])
    assert out.returncode == 2 and "unknown command 'fly'" in out.stderr
    out = run(["train", "nosuchmethod", "pandaset"])
    assert out.returncode == 2 and "nosuchmethod" in (out.stderr + out.stdout)
