"""``omnire serve`` as a child process (for ``omnire bench serve`` and the tests): started
on a free port, its URL read from the line it prints once bound, stopped with SIGTERM."""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import httpx

from omnire.api import UserError


class ServerProcess:
    """``omnire serve RUN --port 0 EXTRA...``; ``log``: the file its stderr goes to."""

    def __init__(self, run: Path, extra: list[str], env: Optional[dict] = None, log: Optional[Path] = None) -> None:
        omnire = Path(sys.executable).parent / "omnire"
        self.log_path = log
        self.log = open(log, "w+") if log is not None else subprocess.DEVNULL
        self.proc = subprocess.Popen([str(omnire), "serve", str(run), "--port", "0", *extra], stdout=subprocess.PIPE,
                                     stderr=self.log, text=True, env=env)
        self.url: Optional[str] = None

    def wait_ready(self, token: Optional[str] = None, timeout: float = 1800.0) -> "ServerProcess":
        """Wait until the server answers /alive; its URL is then ``self.url``."""
        line = self.proc.stdout.readline()  # printed once the run is loaded and the port bound
        m = re.search(r"listening on (http://\S+)", line)
        if not m:
            self.stop()
            tail = self.log_path.read_text()[-2000:] if self.log_path else ""
            raise UserError(f"omnire serve did not start (exit {self.proc.returncode}): {tail.strip()}")
        self.url = m.group(1)
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                if httpx.get(self.url + "/alive", headers=headers, timeout=10).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise UserError(f"omnire serve at {self.url}: no answer within {timeout:.0f} s")

    def stop(self, timeout: float = 60.0) -> tuple[int, str]:
        """SIGTERM, then wait: (exit code, the rest of its stdout)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        if self.log is not subprocess.DEVNULL:
            self.log.close()
        return self.proc.returncode, out or ""
