"""Shared fixtures of the waymo reader tests: paths and one tiny synthetic scene."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
REAL_FRAME = REPO.parent / "shared" / "data" / "waymo" / "pvps_data_one_frame.tfrecord"
OMNIRE = Path(sys.executable).parent / "omnire"


def run_omnire(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run([str(OMNIRE), *args], capture_output=True, text=True, env=env, timeout=timeout)
    assert res.returncode == 0, f"omnire {' '.join(args)} failed ({res.returncode}):\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}"
    return res


@pytest.fixture(scope="session")
def real_frame() -> Path:
    """The one real Waymo frame of the shared data (the test is skipped without it)."""
    if not REAL_FRAME.is_file():
        pytest.skip(f"real Waymo frame not present at {REAL_FRAME}")
    return REAL_FRAME


@pytest.fixture(scope="session")
def omnire_cli():
    """Runs ``omnire <args>`` in a subprocess and asserts exit code 0."""
    return run_omnire


@pytest.fixture(scope="session")
def synthetic(tmp_path_factory):
    """(processed scene, the same scene as a Waymo segment folder): 8 frames, 3 cameras."""
    from omnire_waymo.writer import write_scene

    root = tmp_path_factory.mktemp("waymo_synth")
    processed = root / "processed"
    run_omnire("synth", "urban", str(processed), "--tiny")
    segment_dir = root / "waymo"
    segment_dir.mkdir()
    write_scene(processed, segment_dir)
    return processed, segment_dir
