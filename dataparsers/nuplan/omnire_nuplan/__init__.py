"""nuPlan dataparser for omnire: a log's SQLite database and sensor blobs, read without the devkit."""
from omnire_nuplan.database import ListUnpickler, LogDatabase, NuPlanDataError, NuPlanFileMissing
from omnire_nuplan.dataparser import ATTRIBUTION, CAMERAS, NuPlanConfig, NuPlanDataparser, category_of
from omnire_nuplan.pointcloud import parse_pcd, read_points, write_pcd

__all__ = [
    "ATTRIBUTION", "CAMERAS", "ListUnpickler", "LogDatabase", "NuPlanConfig", "NuPlanDataError", "NuPlanDataparser",
    "NuPlanFileMissing", "category_of", "parse_pcd", "read_points", "write_pcd",
]
