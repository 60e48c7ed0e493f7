"""A tiny trained OmniRe run (background, rigid cars, SMPL pedestrians, sky): ``omnire synth
urban --tiny`` with one camera, two training steps. Made once per test session and shared
with the export's tests (same helper, same cache folder)."""
from __future__ import annotations

import os

import pytest
import torch

TINY_RUN_KEY = "omnire-tiny-run-v1"  # bump when the recipe below changes (the export's conftest has the same)


def make_tiny_run(root):
    """Synthesise a tiny scene under ``root`` and train OmniRe on it for two steps; returns
    the run directory (reused when ``root`` already holds it)."""
    from omnire.plugins import load_plugins
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    run = root / "runs" / "omnire"
    if list((run / "checkpoints").glob("step-*.pt")):
        return run
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    plugins = load_plugins()
    scene = root / "scene"
    synth = plugins.commands.get("synth").main
    assert synth(["urban", str(scene), "--tiny", "--num-cameras", "1"], plugins) in (0, None)
    argv = ["omnire", "processed", "--data", str(scene), "--trainer.max-steps", "2",
            "--trainer.output-dir", str(root / "runs"), "--trainer.run-name", "omnire", "--trainer.no-progress",
            "--trainer.eval-train-views", "1", "--trainer.threads", "1", "--method.rasterizer", "torch",
            "--method.nodes.background.max-lidar-points", "3000", "--method.nodes.background.num-far-points", "300",
            "--method.nodes.smpl.gaussians-per-person", "300"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return run


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    return make_tiny_run(tmp_path_factory.getbasetemp() / TINY_RUN_KEY)


@pytest.fixture(scope="session")
def plugins():
    from omnire.plugins import load_plugins

    return load_plugins()
