"""Entry point of the ``omnire-dataparser-pandaset`` distribution."""
from __future__ import annotations

from omnire.api import DataparserSpec, hookimpl

from omnire_pandaset.dataparser import PandasetConfig


@hookimpl
def omnire_register_dataparsers(registry) -> None:
    registry.register(
        DataparserSpec(
            "pandaset",
            "PandaSet sequence (camera/, lidar/, annotations/cuboids/ in PandaSet's own layout)",
            PandasetConfig,
        )
    )
