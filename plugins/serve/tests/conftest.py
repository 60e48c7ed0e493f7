"""Fixtures of the closed-loop tests: one tiny trained run of the whole demo log (streetgs,
quarter size, two steps: the route, the actors and the LiDAR of the real log, Gaussians
barely trained) and real ``omnire serve`` processes on free ports, one without and one with
a token."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import torch

REPO = Path(__file__).resolve().parents[3]
DEMO_SCENE = REPO / "data" / "demo" / "pandaset_002"
OMNIRE = Path(sys.executable).parent / "omnire"
TOKEN = "test-token-5f2a"


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


class ServerProcess:
    """A running ``omnire serve`` subprocess and its URL."""

    def __init__(self, run: Path, extra: list[str], env: dict) -> None:
        self.log = open(run.parent / f"serve-{os.getpid()}-{len(extra)}-{time.time_ns()}.log", "w+")
        self.proc = subprocess.Popen([str(OMNIRE), "serve", str(run), "--port", "0", "--threads", "1", *extra],
                                     stdout=subprocess.PIPE, stderr=self.log, text=True, env=env)
        self.url = None

    def wait_ready(self, timeout: float = 900.0) -> "ServerProcess":
        deadline = time.time() + timeout
        line = self.proc.stdout.readline()  # blocks until the server has bound its port
        m = re.search(r"listening on (http://\S+)", line)
        if not m:
            self.log.seek(0)
            raise RuntimeError(f"omnire serve did not start: {line!r}\n{self.log.read()[-3000:]}")
        self.url = m.group(1)
        while time.time() < deadline:
            try:
                if httpx.get(self.url + "/alive", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=5).status_code < 500:
                    return self
            except httpx.HTTPError:
                time.sleep(0.2)
        raise RuntimeError("omnire serve: no answer")

    def stop(self) -> tuple[int, str]:
        """SIGTERM; the exit code and the rest of its stdout."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        self.log.close()
        return self.proc.returncode, out


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMNIRE_SERVE_TOKEN"}
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra)
    return env


@pytest.fixture(scope="session")
def servers(serve_run):
    """(open server, server requiring TOKEN), started together; stopped with SIGTERM at the
    end, which must exit 0."""
    plain = ServerProcess(serve_run, [], _env())
    guarded = ServerProcess(serve_run, [], _env(OMNIRE_SERVE_TOKEN=TOKEN))
    try:
        yield plain.wait_ready(), guarded.wait_ready()
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
