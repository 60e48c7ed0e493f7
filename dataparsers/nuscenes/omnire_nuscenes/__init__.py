"""nuScenes dataparser for omnire: the release layout read in place (standard library + numpy)."""
from omnire_nuscenes.dataparser import (
    ATTRIBUTION,
    CAMERAS,
    LIDAR,
    NuScenesConfig,
    NuScenesDataparser,
    category_of,
    frame_targets,
)
from omnire_nuscenes.tables import NuScenesDataError, NuScenesFileMissing, iter_json_array, load_table

__all__ = [
    "ATTRIBUTION", "CAMERAS", "LIDAR", "NuScenesConfig", "NuScenesDataError", "NuScenesDataparser",
    "NuScenesFileMissing", "category_of", "frame_targets", "iter_json_array", "load_table",
]
