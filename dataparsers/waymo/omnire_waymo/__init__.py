"""Waymo Open Dataset v1 reader and scene writer for omnire (no TensorFlow, no waymo package)."""
from omnire_waymo.dataparser import (
    ALL_LIDARS,
    ATTRIBUTION,
    CAMERA_NAMES,
    CATEGORY,
    DEFAULT_CAMERAS,
    LASER_NAMES,
    WAYMO_TO_OPENCV,
    WaymoConfig,
    WaymoDataparser,
)
from omnire_waymo.tfrecord import TFRecordError, TFRecordReader, TFRecordWriter

__all__ = [
    "ALL_LIDARS", "ATTRIBUTION", "CAMERA_NAMES", "CATEGORY", "DEFAULT_CAMERAS", "LASER_NAMES", "TFRecordError",
    "TFRecordReader", "TFRecordWriter", "WAYMO_TO_OPENCV", "WaymoConfig", "WaymoDataparser",
]
