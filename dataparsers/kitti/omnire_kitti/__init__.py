"""KITTI tracking dataparser for omnire (image_02/03, velodyne, calib, oxts, label_02)."""
from omnire_kitti.dataparser import (
    ATTRIBUTION, CAMERAS, KittiConfig, KittiDataError, KittiDataparser, KittiFileMissing, category_of, label_box,
    oxts_poses, read_calib, read_labels, read_oxts,
)

__all__ = [
    "ATTRIBUTION", "CAMERAS", "KittiConfig", "KittiDataError", "KittiDataparser", "KittiFileMissing", "category_of",
    "label_box", "oxts_poses", "read_calib", "read_labels", "read_oxts",
]
