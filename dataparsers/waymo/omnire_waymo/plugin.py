"""Entry point of the ``omnire-dataparser-waymo`` distribution."""
from __future__ import annotations

from omnire.api import CommandSpec, DataparserSpec, SceneWriterSpec, hookimpl


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    from omnire_waymo.dataparser import WaymoConfig

    registry.register(
        DataparserSpec(
            "waymo",
            "Waymo Open Dataset v1 segment (.tfrecord of Frame protos; read without TensorFlow)",
            WaymoConfig,
        )
    )


@hookimpl
def omnire_register_scene_writers(registry) -> None:
    from omnire_waymo.writer import write_scene

    registry.register(
        SceneWriterSpec(
            "waymo",
            "Waymo Open Dataset v1 segment: one .tfrecord of Frame protos (JPEGs, range images, 3D labels)",
            write_scene,
        )
    )


@hookimpl
def omnire_register_commands(registry) -> None:
    from omnire_waymo.bench import main

    registry.register(
        CommandSpec(
            "bench waymo-read",
            "Peak memory of reading a large generated Waymo segment (streaming check; default 1 GB)",
            main,
        )
    )
