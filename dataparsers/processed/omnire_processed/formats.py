"""Facts about the reference implementation's processed-scene format (docs/conventions.md):
per-dataset camera ids, LiDAR column layouts, camera-axis, pixel-centre and box-axis
conventions, and class names.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from omnire.api import BYTE_INTENSITY, UNBOUNDED_INTENSITY, UNIT_INTENSITY, IntensityScale

SOURCES = ("waymo", "nuscenes", "nuplan", "argoverse", "pandaset", "kitti")

# Waymo camera axes (x forward, y left, z up) -> OpenCV: cam_to_ego_opencv = cam_to_ego @ M.
WAYMO_TO_OPENCV = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)

CAMERA_NAMES: dict[str, tuple[str, ...]] = {
    "waymo": ("front_camera", "front_left_camera", "front_right_camera", "left_camera", "right_camera"),
    "pandaset": ("front_camera", "front_left_camera", "front_right_camera", "left_camera", "right_camera",
                 "back_camera"),
    "nuscenes": ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_BACK"),
    "argoverse": ("ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left", "ring_side_right",
                  "ring_rear_left", "ring_rear_right"),
    "kitti": ("CAM_LEFT", "CAM_RIGHT"),
    "nuplan": ("CAM_F0", "CAM_L0", "CAM_R0", "CAM_L1", "CAM_R1", "CAM_L2", "CAM_R2", "CAM_B0"),
}


# Pixel-centre convention of the intrinsics each source's preprocessing copies unchanged into
# intrinsics/{cam}.txt (the reference's savers write the dataset's own fx fy cx cy). "half":
# pixel (i, j) is centred at (i + 0.5, j + 0.5), i.e. the image spans [0, W] x [0, H], which is
# omnire's convention (used as is); "integer": centred at (i, j) as in OpenCV (+0.5 added).
# Evidence, from each dataset's own tools:
# - waymo: camera_model.cc (waymo-open-dataset) accepts 0 <= u < width as in the image and
#   times the rolling-shutter readout from image coordinate 0 to width/height.
# - pandaset: pandaset-devkit geometry.projection keeps points with 0 < u < width, 0 < v < height.
# - nuscenes: nuscenes-devkit box_in_image keeps corners with 0 < u < width, and its 2D-box
#   export clips projected boxes to the canvas box(0, 0, 1600, 900).
# - argoverse: av2-api PinholeCamera.cull_to_view_frustum documents image coordinates in
#   [0, W-1] x [0, H-1] (first and last pixel centres at 0 and W-1).
# - kitti: the devkit's label format gives 2D boxes as "0-based index" pixel coordinates.
# - nuplan: no statement in nuplan-devkit; its cameras ship OpenCV's distortion model
#   (k1 k2 p1 p2 k3) for distorted images, so OpenCV's convention is assumed.
PIXEL_CENTRES: dict[str, str] = {
    "waymo": "half", "pandaset": "half", "nuscenes": "half",
    "argoverse": "integer", "kitti": "integer", "nuplan": "integer",
}

# Which local axis of the reference's obj_to_world boxes points along the object's heading,
# per source (box_size always lists the extents along local x, y, z). From
# ziyc/drivestudio datasets/*/*_preprocess.py save_objects:
# - waymo: vehicle_to_world @ Rz(box.heading) at the box centre; heading rotates +x to the
#   front face normal; box_size = (length, width, height).
# - nuscenes: the annotation quaternion (nuScenes Box: x along the length) at its
#   translation; box_size = (l, w, h) converted from nuScenes' (w, l, h).
# - argoverse: city_SE3_ego @ ego_SE3_object (AV2 cuboids: length along object x);
#   box_size = (length_m, width_m, height_m).
# - kitti: velo_to_world @ Rz(tracklet rz) with the tracklet's bottom centre raised by h/2;
#   box_size = (l, w, h) from the tracklet's (h, w, l).
# - nuplan: the SE2 pose (x, y, yaw) of the lidar_box with its z; box_size = (l, w, h).
# - pandaset: Rz(cuboid yaw) at the cuboid position; box_size = (dimensions.x, .y, .z).
#   PandaSet's dimensions.x is the width and yaw rotates that width axis: the object moves
#   along local +y, so box_size = (width, length, height).
BOX_HEADING_AXIS: dict[str, str] = {
    "waymo": "+x", "nuscenes": "+x", "argoverse": "+x", "kitti": "+x", "nuplan": "+x", "pandaset": "+y",
}


@dataclasses.dataclass(frozen=True)
class LidarLayout:
    """float32 columns of one LiDAR row. ``origin`` is the column of the sensor origin x
    (None: the sensor sits at the pose origin); ``xyz`` the column of point x;
    ``intensity`` its column (None if absent), on ``intensity_scale``: the source dataset's
    own, which the reference's preprocessing copies unchanged."""

    columns: int
    xyz: int
    origin: int | None
    intensity: int | None
    description: str
    intensity_scale: IntensityScale


LIDAR_LAYOUTS: dict[str, LidarLayout] = {
    "waymo": LidarLayout(14, 3, 0, 11, "origin xyz, point xyz, flow xyz, flow class, ground, intensity, "
                                        "elongation, laser id (ego frame)", UNBOUNDED_INTENSITY),
    "nuscenes": LidarLayout(4, 0, None, 3, "xyz, intensity (lidar frame, posed by lidar_pose/)", BYTE_INTENSITY),
    "argoverse": LidarLayout(4, 0, None, 3, "xyz, intensity (ego frame)", BYTE_INTENSITY),
    "kitti": LidarLayout(4, 0, None, 3, "xyz, intensity (ego frame)", UNIT_INTENSITY),
    "pandaset": LidarLayout(5, 0, None, 3, "xyz, intensity, sensor id (ego frame)", BYTE_INTENSITY),
    "nuplan": LidarLayout(6, 0, None, 3, "xyz, intensity, ring, lidar id (ego frame)", BYTE_INTENSITY),
}

# Dataset class name -> actor category (omnire.data.scene.CATEGORIES). "vehicle" is the rigid
# category: like the reference implementation, rigid street furniture tracked as boxes
# (cones, barrels, signs, trailers) goes there too. Cyclists and riders -> "cyclist";
# other non-rigid actors (animals, strollers, wheelchairs) -> "other".
_CLASSES_BY_CATEGORY: dict[str, dict[str, tuple[str, ...]]] = {
    "waymo": {
        "vehicle": ("Vehicle",),
        "human": ("Pedestrian",),
        "cyclist": ("Cyclist",),
        "other": ("Sign",),
    },
    "nuscenes": {
        "vehicle": (
            "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction",
            "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.motorcycle",
            "vehicle.trailer", "vehicle.truck",
        ),
        "human": (
            "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.construction_worker",
            "human.pedestrian.police_officer",
        ),
        "cyclist": ("vehicle.bicycle",),
        "other": (
            "human.pedestrian.personal_mobility", "human.pedestrian.stroller",
            "human.pedestrian.wheelchair", "animal", "movable_object.barrier", "movable_object.debris",
            "movable_object.pushable_pullable", "movable_object.trafficcone", "static_object.bicycle_rack",
        ),
    },
    "pandaset": {
        "vehicle": (
            "Bus", "Car", "Emergency Vehicle", "Medium-sized Truck", "Motorcycle", "Motorized Scooter",
            "Other Vehicle - Construction Vehicle", "Other Vehicle - Pedicab", "Other Vehicle - Uncommon",
            "Pickup Truck", "Semi-truck", "Train", "Tram / Subway", "Towed Object",
        ),
        "human": ("Pedestrian", "Pedestrian with Object"),
        "cyclist": ("Bicycle",),
        "other": (
            "Animals - Bird", "Animals - Other", "Personal Mobility Device", "Construction Signs", "Cones",
            "Pylons", "Road Barriers", "Rolling Containers", "Signs", "Temporary Construction Barriers",
        ),
    },
    "argoverse": {
        "vehicle": (
            "ARTICULATED_BUS", "BOLLARD", "BOX_TRUCK", "BUS", "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE",
            "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER", "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOTORCYCLE",
            "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS", "SIGN", "STOP_SIGN", "TRAFFIC_LIGHT_TRAILER",
            "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER",
        ),
        "human": ("PEDESTRIAN", "OFFICIAL_SIGNALER"),
        "cyclist": ("BICYCLE", "BICYCLIST", "MOTORCYCLIST", "WHEELED_RIDER"),
        "other": ("ANIMAL", "DOG", "STROLLER", "WHEELCHAIR", "WHEELED_DEVICE"),
    },
    "kitti": {
        "vehicle": ("Car", "Van", "Truck", "Tram"),
        "human": ("Pedestrian", "Person_sitting"),
        "cyclist": ("Cyclist",),
        "other": ("Misc",),
    },
    "nuplan": {
        "vehicle": ("vehicle",),
        "human": ("pedestrian",),
        "cyclist": ("bicycle",),
        "other": ("traffic_cone", "barrier", "czone_sign", "generic_object"),
    },
}
CLASS_CATEGORIES: dict[str, dict[str, str]] = {
    src: {name: cat for cat, names in table.items() for name in names}
    for src, table in _CLASSES_BY_CATEGORY.items()
}
"""Source -> class name -> category, from the table above."""


def category_of(class_name: str, source: str) -> str | None:
    """Category of a class name: the source's table first, then any table (processed scenes
    sometimes mix conventions), then case-insensitively. None when unknown."""
    table = CLASS_CATEGORIES.get(source, {})
    if class_name in table:
        return table[class_name]
    for other in CLASS_CATEGORIES.values():
        if class_name in other:
            return other[class_name]
    low = class_name.lower()
    for other in CLASS_CATEGORIES.values():
        for name, cat in other.items():
            if name.lower() == low:
                return cat
    return None


def detect_source_from_classes(class_names: set[str]) -> str | None:
    """The dataset whose class table covers the most of these names (ties: None)."""
    if not class_names:
        return None
    scores = {s: len(class_names & set(t)) for s, t in CLASS_CATEGORIES.items()}
    best = max(scores.values())
    winners = [s for s, v in scores.items() if v == best]
    return winners[0] if best > 0 and len(winners) == 1 else None
