"""Entry point of the ``omnire-dataparser-nuscenes`` distribution."""
from __future__ import annotations

from pathlib import Path

from omnire.api import DataparserSpec, SceneWriterSpec, hookimpl


def _config():
    from omnire_nuscenes.dataparser import NuScenesConfig

    return NuScenesConfig()


def _write(source: Path, output: Path) -> None:
    from omnire_nuscenes.writer import write_scene

    write_scene(source, output)


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(DataparserSpec(
        "nuscenes",
        "nuScenes scene in the release layout (v1.0-* JSON tables, samples/, sweeps/), 10 Hz frames on the LiDAR clock",
        _config,
    ))


@hookimpl
def omnire_register_scene_writers(registry) -> None:
    registry.register(SceneWriterSpec(
        "nuscenes", "nuScenes release layout (v1.0-mini tables, samples/, sweeps/; 2 Hz keyframes)", _write))
