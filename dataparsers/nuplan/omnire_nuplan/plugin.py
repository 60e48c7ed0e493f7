"""Entry point of the ``omnire-dataparser-nuplan`` distribution."""
from __future__ import annotations

from pathlib import Path

from omnire.api import DataparserSpec, SceneWriterSpec, hookimpl


def _config():
    from omnire_nuplan.dataparser import NuPlanConfig

    return NuPlanConfig()


def _write(source: Path, output: Path) -> None:
    from omnire_nuplan.writer import write_scene

    write_scene(source, output)


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(DataparserSpec(
        "nuplan",
        "nuPlan log as distributed (SQLite <log>.db + sensor_blobs: 8 cameras, merged LiDAR), 10 Hz frames on the "
        "LiDAR clock",
        _config,
    ))


@hookimpl
def omnire_register_scene_writers(registry) -> None:
    registry.register(SceneWriterSpec(
        "nuplan", "nuPlan log layout (splits/mini/<log>.db, sensor_blobs/; 20 Hz lidar_pc, 10 Hz images)", _write))
