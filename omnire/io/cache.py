"""Where omnire keeps what it can rebuild (compiled extensions, extracted images)."""
from __future__ import annotations

import os
from pathlib import Path


def user_cache_dir(name: str, env: str) -> Path:
    """``$<env>`` when set, else ``$XDG_CACHE_HOME/omnire/<name>`` (``~/.cache/omnire/<name>``
    without ``XDG_CACHE_HOME``)."""
    root = os.environ.get(env)
    if root:
        return Path(root)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "omnire" / name
