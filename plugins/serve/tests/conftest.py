"""Fixtures of the closed-loop tests: one tiny trained run of the whole demo log (streetgs,
quarter size, two steps: the route, the actors and the LiDAR of the real log, Gaussians
barely trained) and real ``omnire serve`` processes on free ports, one without and one with
a token; the same run with LiDAR features learned, and a server of it."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # serve_helpers (tests are imported by path)

from serve_helpers import TOKEN, clean_env  # noqa: E402

REPO = Path(__file__).resolve().parents[3]
DEMO_SCENE = REPO / "data" / "demo" / "pandaset_002"


@pytest.fixture(scope="session")
def plugins():
    from omnire.plugins import load_plugins

    return load_plugins()


@pytest.fixture(scope="session")
def serve_run(tmp_path_factory, plugins):
    """A run directory: streetgs on the 40 frames of the demo scene at quarter size, 2 steps."""
    if not DEMO_SCENE.is_dir():
        pytest.skip("demo scene (data/demo/pandaset_002) not in this checkout")
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    root = tmp_path_factory.mktemp("serve-runs")
    argv = ["streetgs", "pandaset", "--data", str(DEMO_SCENE), "--holdout-every", "0", "--scale", "0.25",
            "--method.nodes.background.max-lidar-points", "3000", "--method.nodes.background.num-far-points", "300",
            "--trainer.max-steps", "2", "--trainer.no-progress", "--trainer.eval-train-views", "1",
            "--trainer.threads", "1", "--trainer.output-dir", str(root), "--trainer.run-name", "demo"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return root / "demo"


@pytest.fixture(scope="session")
def lidar_run(tmp_path_factory, plugins):
    """The run of :func:`serve_run` with LiDAR features learned (--method.lidar.enabled)."""
    if not DEMO_SCENE.is_dir():
        pytest.skip("demo scene (data/demo/pandaset_002) not in this checkout")
    from omnire.runconfig import parse_train_args
    from omnire.trainer import Trainer

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("serve-lidar-runs")
    argv = ["streetgs", "pandaset", "--data", str(DEMO_SCENE), "--holdout-every", "0", "--scale", "0.25",
            "--method.nodes.background.max-lidar-points", "3000", "--method.nodes.background.num-far-points", "300",
            "--trainer.max-steps", "2", "--trainer.no-progress", "--trainer.eval-train-views", "1",
            "--trainer.threads", "1", "--trainer.output-dir", str(root), "--trainer.run-name", "demo",
            "--method.lidar.enabled", "--method.lidar.rays-per-step", "4000"]
    Trainer(parse_train_args(argv, plugins), plugins, argv=argv).train()
    return root / "demo"


@pytest.fixture(scope="session")
def lidar_server(lidar_run):
    """A server of :func:`lidar_run`."""
    from omnire_serve.process import ServerProcess

    server = ServerProcess(lidar_run, ["--threads", "1"], clean_env(), lidar_run.parent / "serve.log")
    try:
        yield server.wait_ready()
    finally:
        code, _ = server.stop()
        assert code == 0, f"omnire serve exited {code} on SIGTERM"


@pytest.fixture(scope="session")
def lidar_served(lidar_run, plugins):
    """:func:`lidar_run` served in this process."""
    from omnire.api import Reconstruction
    from omnire_serve.served import ServedScene

    torch.set_num_threads(1)
    return ServedScene(Reconstruction.from_run(lidar_run, plugins), plugins)


@pytest.fixture(scope="session")
def servers(serve_run):
    """(open server, server requiring TOKEN), started together; stopped with SIGTERM at the
    end, which must exit 0."""
    from omnire_serve.process import ServerProcess

    plain = ServerProcess(serve_run, ["--threads", "1"], clean_env(), serve_run.parent / "serve.log")
    guarded = ServerProcess(serve_run, ["--threads", "1"], clean_env(OMNIRE_SERVE_TOKEN=TOKEN),
                            serve_run.parent / "serve-token.log")
    try:
        yield plain.wait_ready(), guarded.wait_ready(TOKEN)
    finally:
        for s in (plain, guarded):
            code, out = s.stop()
            assert code == 0, f"omnire serve exited {code} on SIGTERM"
            assert "stopped" in out


@pytest.fixture(scope="session")
def server(servers):
    return servers[0]


@pytest.fixture(scope="session")
def served(serve_run, plugins):
    """The same run served in this process (for the environment's local transport)."""
    from omnire.api import Reconstruction
    from omnire_serve.served import ServedScene

    torch.set_num_threads(1)
    return ServedScene(Reconstruction.from_run(serve_run, plugins), plugins)
