"""Entry point of the ``omnire-dataparser-argoverse2`` distribution."""
from __future__ import annotations

from omnire.api import DataparserSpec, SceneWriterSpec, hookimpl


def _config():
    from omnire_argoverse2.dataparser import Argoverse2Config

    return Argoverse2Config()


def _write(source, output) -> None:
    from omnire_argoverse2.writer import write_scene

    write_scene(source, output)


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(DataparserSpec(
        "argoverse2",
        "Argoverse 2 sensor log in AV2's own layout (feather files through pyarrow: ring cameras, LiDAR, cuboids)",
        _config,
    ))


@hookimpl
def omnire_register_scene_writers(registry) -> None:
    registry.register(SceneWriterSpec(
        "argoverse2",
        "a synthetic scene as an AV2 sensor log (feather files in AV2's schema, ring-camera jpgs)",
        _write,
    ))
