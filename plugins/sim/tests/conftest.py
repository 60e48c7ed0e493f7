"""Fixtures of the simulation tests: the in-memory street (sim_scene.py) and one tiny trained
run on disk (the demo scene's first frames, streetgs, two steps) for the command-line tests."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # sim_scene (tests are imported by path)

REPO = Path(__file__).resolve().parents[3]
DEMO_SCENE = REPO / "data" / "demo" / "pandaset_002"


@pytest.fixture(scope="session")
def plugins():
    from omnire.plugins import load_plugins

    return load_plugins()


@pytest.fixture(scope="session")
def street(tmp_path_factory, plugins):
    from sim_scene import build, street_scene

    torch.set_num_threads(1)
    return build(street_scene(tmp_path_factory.mktemp("street")), plugins=plugins)


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory, plugins):
    """A run directory: streetgs on 4 frames of the demo scene at quarter size, 2 steps."""
    if not DEMO_SCENE.is_dir():
        pytest.skip("demo scene (data/demo/pandaset_002) not in this checkout")
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    root = tmp_path_factory.mktemp("runs")
    argv = ["streetgs", "pandaset", "--data", str(DEMO_SCENE), "--end-frame", "4", "--holdout-every", "2",
            "--scale", "0.25", "--method.nodes.background.max-lidar-points", "3000",
            "--method.nodes.background.num-far-points", "300", "--trainer.max-steps", "2", "--trainer.no-progress",
            "--trainer.eval-train-views", "1", "--trainer.threads", "1", "--trainer.output-dir", str(root),
            "--trainer.run-name", "demo"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return root / "demo"
