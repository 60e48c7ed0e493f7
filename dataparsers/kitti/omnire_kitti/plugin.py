"""Entry point of the ``omnire-dataparser-kitti`` distribution."""
from __future__ import annotations

from pathlib import Path

from omnire.api import DataparserSpec, SceneWriterSpec, hookimpl


def _config():
    from omnire_kitti.dataparser import KittiConfig

    return KittiConfig()


def _write(source: Path, output: Path) -> None:
    from omnire_kitti.writer import write_scene

    write_scene(source, output)


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(DataparserSpec(
        "kitti",
        "KITTI tracking sequence in the release layout (image_02/03, velodyne, calib, oxts, label_02)",
        _config,
    ))


@hookimpl
def omnire_register_scene_writers(registry) -> None:
    registry.register(SceneWriterSpec(
        "kitti", "KITTI tracking layout (training/, sequence 0000; rectified image_02, velodyne, oxts, label_02)",
        _write))
