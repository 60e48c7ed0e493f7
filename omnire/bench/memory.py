"""Memory of this process as Linux reports it, for benchmarks that measure peak growth."""
from __future__ import annotations

from pathlib import Path


def process_status_kib(field: str) -> int:
    """A memory field of ``/proc/self/status`` in KiB: ``VmRSS`` (resident now), ``VmHWM``
    (resident peak since start or since ``5`` was written to ``/proc/self/clear_refs``)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")
