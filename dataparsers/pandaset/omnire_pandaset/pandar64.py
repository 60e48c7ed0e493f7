"""The Pandar64 of PandaSet's car: its beam model, where it sits, and the beam of each return.

Facts used (docs/lidar.md, "PandaSet"):

- Elevations: the vertical angle of each of the 64 channels from the Pandar64 user manual,
  as published by pandaset-devkit (``tutorials/raw_depth_projection/
  pandar64_channel_distribution.csv``); channel ``c`` (1..64, top to bottom) is beam
  ``c - 1``. Azimuth step 0.2 degrees at 10 Hz, range 0.3-200 m (datasheet).
- Pose: ``lidar/poses.json`` is not the sensor's optical centre (its origin lies near the
  ground). The devkit's static extrinsic calibration (``docs/static_extrinsic_calibration.yaml``,
  entry ``front_camera``) maps the Pandar64's coordinates (x left, y backward, z up on
  PandaSet's car) into the front camera's; composed with the front camera's pose
  (``camera/front_camera/poses.json`` at its own timestamps, the middle of each sweep) it
  gives the sensor's pose, 1.86 m above that origin.
- :data:`CENTRE_OFFSET`: the optical centre relative to that calibrated origin, estimated
  from the complete sweeps of log 002 (``tools/fit_pandar64_centre.py``): a few centimetres.

With these, 99.7% of the returns of log 002's complete sweeps lie within 0.1 degrees of
their beam's elevation in the sensor frame at their own time (``tests/``).
"""
from __future__ import annotations

import numpy as np

from omnire.api import (
    BeamModel,
    assign_beams,
    extend_poses,
    interpolate_poses,
    points_in_sensor_frame,
    quat_to_rotmat,
    rigid,
    spherical,
)

ELEVATIONS_DEG = np.array([
    14.87, 11.02, 8.047, 5.045, 3.028, 2.016, 1.848, 1.676, 1.51, 1.339, 1.172, 1.001, 0.834, 0.663, 0.496,
    0.325, 0.157, -0.012, -0.181, -0.349, -0.52, -0.687, -0.857, -1.025, -1.196, -1.363, -1.534, -1.7, -1.872,
    -2.04, -2.21, -2.377, -2.548, -2.712, -2.885, -3.052, -3.222, -3.387, -3.56, -3.724, -3.896, -4.062, -4.233,
    -4.397, -4.57, -4.732, -4.904, -5.069, -5.241, -5.403, -5.577, -5.738, -5.91, -6.073, -7.075, -8.071, -9.072,
    -9.897, -11.044, -12.018, -12.986, -13.942, -18.901, -24.909,
])
"""(64,) vertical angle of channels 1..64 in degrees (Pandar64 user manual via pandaset-devkit)."""

BEAM_MODEL = BeamModel(ELEVATIONS_DEG, azimuth_resolution_deg=0.2, max_range=200.0, min_range=0.3,
                       name="Pandar64")
"""The Pandar64 at 10 Hz: 64 beams x 1800 azimuths (datasheet)."""

LIDAR_TO_FRONT_CAMERA = rigid(
    quat_to_rotmat(np.array([0.016213200031258722, 0.0030578899383849464, 0.7114721800418571, -0.7025205466606356])),
    (0.0002585796504896516, -0.03907777167811011, -0.0440125762408362))
"""(4, 4) Pandar64 coordinates -> front-camera (OpenCV) coordinates: the ``front_camera``
entry of pandaset-devkit's ``docs/static_extrinsic_calibration.yaml`` (quaternion wxyz,
translation in metres)."""

FORWARD_AXES = np.array([[0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""(4, 4) x-forward sensor axes -> the calibration's Pandar64 axes (x left, y backward, z
up): its columns are forward, left and up written in the calibration's axes."""

CENTRE_OFFSET = np.array([-0.0273, -0.0023, 0.0107])
"""(3,) metres, forward/left/up: the optical centre relative to the calibrated sensor
origin, fitted on the complete sweeps of log 002 (``tools/fit_pandar64_centre.py``)."""

POSE_MARGIN_S = 0.2
"""Seconds the sensor track is extrapolated past the first and last camera pose (a sweep
runs 0.05 s past the middle-of-sweep pose of its frame)."""


def sensor_track(front_camera_to_world: np.ndarray, offset: np.ndarray = CENTRE_OFFSET) -> np.ndarray:
    """Front-camera poses (K, 4, 4) (OpenCV camera-to-world) -> Pandar64 poses (K, 4, 4) in
    x-forward, y-left, z-up axes, at the optical centre (``offset`` (3,) forward/left/up
    metres from the calibrated origin)."""
    return np.asarray(front_camera_to_world, dtype=np.float64) @ LIDAR_TO_FRONT_CAMERA @ FORWARD_AXES @ rigid(t=offset)


def sensor_poses_at(track_times: np.ndarray, track: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The sensor track (K, 4, 4) at increasing ``track_times`` (K,) -> poses (Q, 4, 4) at
    ``times`` (Q,), extrapolated at constant velocity up to :data:`POSE_MARGIN_S` past its
    ends."""
    known, poses = extend_poses(track_times, track, POSE_MARGIN_S)
    return interpolate_poses(known, poses, times)


def returns_in_sensor_frame(points: np.ndarray, times: np.ndarray, track_times: np.ndarray,
                            track: np.ndarray) -> np.ndarray:
    """World returns (N, 3) at their ``times`` (N,) -> (N, 3) in the sensor frame at each
    return's own time, on the sensor track (K, 4, 4) at ``track_times`` (K,)."""
    known, poses = extend_poses(track_times, track, POSE_MARGIN_S)
    return points_in_sensor_frame(points, times, known, poses)


def beams_of(points: np.ndarray, times: np.ndarray, track_times: np.ndarray, track: np.ndarray) -> np.ndarray:
    """(N,) int16 beam of each Pandar64 return (world (N, 3) at ``times`` (N,)): the beam
    of nearest elevation in the sensor frame at the return's own time."""
    _, _, elevation = spherical(returns_in_sensor_frame(points, times, track_times, track))
    return assign_beams(elevation, BEAM_MODEL)
