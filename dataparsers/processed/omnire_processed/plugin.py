"""omnire plugin: registers the ``processed`` dataparser."""
from __future__ import annotations

from omnire.api import DataparserSpec, hookimpl


def _config():
    from omnire_processed.reader import ProcessedDataparserConfig

    return ProcessedDataparserConfig()


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(
        DataparserSpec(
            "processed",
            "Scenes in the reference implementation's processed format (Waymo, nuScenes, NuPlan, "
            "Argoverse2, PandaSet, KITTI), converted to omnire conventions",
            _config,
        )
    )
