"""Shared by the closed-loop tests and their fixtures: the omnire command, the test token, a
clean environment for server processes."""
from __future__ import annotations

import os
import sys
from pathlib import Path

OMNIRE = Path(sys.executable).parent / "omnire"
TOKEN = "test-token-5f2a"


def clean_env(**extra) -> dict:
    """This process's environment without a server token, single-threaded, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k != "OMNIRE_SERVE_TOKEN"}
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra)
    return env
