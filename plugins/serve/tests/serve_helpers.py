"""Shared by the closed-loop tests and their fixtures: the omnire command, the test token, a
clean environment for server processes, a hostile request and its record."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import httpx

from hostile import record

OMNIRE = Path(sys.executable).parent / "omnire"
TOKEN = "test-token-5f2a"


def clean_env(**extra) -> dict:
    """This process's environment without a server token, single-threaded, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k != "OMNIRE_SERVE_TOKEN"}
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra)
    return env


def hostile_request(client: httpx.Client, name: str, method: str, path: str, field: str, status: int, **kw) -> None:
    """Send a bad request: it must be answered with ``status`` and a JSON error naming
    ``field`` (recorded for the hostile-input count)."""
    r = client.request(method, path, **kw)
    try:
        body = r.json()
        err = body["error"]
        ok = r.status_code == status and err["field"] == field and err["message"]
    except (ValueError, KeyError, TypeError):
        ok, body = False, r.text
    record("serve", name, exit=r.status_code, traceback=None if r.status_code < 500 else r.text, wrong=not ok)
    assert ok, f"{name}: {r.status_code} {str(body)[:500]}"
