"""Everything a plugin author imports: the one public module of the core for plugins.

Third-party plugins (node types, dataparsers, rasterizers, losses, methods, commands, pose
estimators, scene writers) import from here only; docs/plugins.md shows each in use.
"""
from omnire.config import InstantiateConfig
from omnire.data.dataparser import Dataparser, DataparserConfig, LogDataparserConfig, first_pose_world, frame_range
from omnire.data.images import ImageCache, ImageReadError
from omnire.data.scene import (
    CATEGORIES,
    ActorTrack,
    CameraSequence,
    HumanPoseSequence,
    LidarSweeps,
    SceneData,
    SceneDataError,
    View,
    holdout_split,
)
from omnire.errors import ConfigError, UserError
from omnire.geometry import (
    axis_angle_to_rotmat,
    invert_se3,
    quat_multiply,
    quat_to_rotmat,
    rot_z,
    rotmat_to_axis_angle,
    rotmat_to_quat,
    slerp_rotmats,
)
from omnire.hookspecs import hookimpl
from omnire.interpolation import bracket, interpolate_poses, interpolate_track
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.registry import (
    CommandSpec,
    DataparserSpec,
    LossSpec,
    MethodSpec,
    NodeTypeSpec,
    PoseEstimatorSpec,
    RasterizerSpec,
    Registry,
    SceneWriterSpec,
)

__all__ = [
    "CATEGORIES", "ActorTrack", "CameraSequence", "CommandSpec", "ConfigError", "Dataparser", "DataparserConfig",
    "DataparserSpec", "HumanPoseSequence", "ImageCache", "ImageReadError", "InstantiateConfig", "LidarSweeps",
    "LogDataparserConfig", "LossSpec", "MethodSpec", "NodeTypeSpec", "PoseEstimatorSpec", "RasterizerSpec",
    "Registry", "SceneData", "SceneDataError", "SceneWriterSpec", "UserError", "View", "atomic_write_bytes",
    "atomic_write_text", "axis_angle_to_rotmat", "bracket", "first_pose_world", "frame_range", "hookimpl",
    "holdout_split", "interpolate_poses", "interpolate_track", "invert_se3", "quat_multiply", "quat_to_rotmat",
    "rot_z", "rotmat_to_axis_angle", "rotmat_to_quat", "slerp_rotmats",
]
