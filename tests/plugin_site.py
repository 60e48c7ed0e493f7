"""Installing a plugin package on ``sys.path`` as pip would, without pip (for tests that run
the real plugin loader, in-process or in an ``omnire`` subprocess with ``PYTHONPATH``)."""
from __future__ import annotations

import shutil
from pathlib import Path


def install_on_path(site: Path, package: Path, dist: str, entry: str) -> None:
    """Copy the package directory ``package`` into ``site`` beside a dist-info holding the
    distribution's metadata and its ``omnire`` entry point ``entry = <package>.plugin``."""
    shutil.copytree(package, site / package.name)
    info = site / f"{dist.replace('-', '_')}-0.1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1.0\n")
    (info / "entry_points.txt").write_text(f"[omnire]\n{entry} = {package.name}.plugin\n")
