"""PandaSet dataparser plugin for omnire."""
from omnire_pandaset.dataparser import (
    ATTRIBUTION,
    CAMERAS,
    LIDAR_SENSORS,
    PandasetConfig,
    PandasetDataparser,
    category_of,
    deduplicate_cuboids,
)

__all__ = [
    "ATTRIBUTION",
    "CAMERAS",
    "LIDAR_SENSORS",
    "PandasetConfig",
    "PandasetDataparser",
    "category_of",
    "deduplicate_cuboids",
]
