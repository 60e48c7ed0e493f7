"""Everything a plugin author imports: the public module of the core for plugins.

Third-party plugins (node types, dataparsers, rasterizers, losses, methods, commands, pose
estimators, scene writers, training observers) import from here, and command and benchmark
authors also from :mod:`omnire.command_api`; no other core module is public (an
import-linter contract in pyproject.toml keeps plugin packages to these two).
docs/plugins.md shows each in use.
"""
from omnire.camera import CULL_SIGMAS, Camera, gaussian_reach, in_frustum, may_be_drawn
from omnire.config import InstantiateConfig
from omnire.data.dataparser import Dataparser, DataparserConfig, LogDataparserConfig, first_pose_world, frame_range
from omnire.data.images import ImageCache, ImageReadError, image_size, read_image
from omnire.data.scene import (
    CATEGORIES,
    ActorTrack,
    CameraSequence,
    HumanPoseSequence,
    LidarSweeps,
    SceneData,
    SceneDataError,
    SceneTime,
    View,
    holdout_split,
)
from omnire.errors import ConfigError, MissingFileError, UserError
from omnire.gaussians import GAUSSIAN_KEYS, Gaussians, rgb_to_sh0
from omnire.geometry import (
    axis_angle_to_rotmat,
    axis_rotation,
    invert_se3,
    quat_multiply,
    quat_to_rotmat,
    quat_to_se3,
    rigid,
    rot_z,
    rotmat_to_axis_angle,
    rotmat_to_quat,
    slerp_rotmats,
)
from omnire.hookspecs import hookimpl
from omnire.interpolation import bracket, interpolate_poses, interpolate_rotations, interpolate_track
from omnire.io import safe_pickle
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.io.cache import user_cache_dir
from omnire.io.images import write_png
from omnire.losses import LossContext, ssim_map
from omnire.method import MethodConfig
from omnire.native import NativeExtension, build_error_line
from omnire.nn import DeformationMLP, positional_encoding
from omnire.nodes.actors import (
    ActorNode,
    ActorState,
    ActorPoses,
    BoxActorConfig,
    BoxActorNode,
    frame_blend,
    placed_output,
    segment_max,
    track_displacement,
    train_frame_bracket,
    transform_instances,
    usable_track,
    visible_in_cameras,
)
from omnire.nodes.background import BackgroundConfig, init_background_params, lidar_points_for_init
from omnire.nodes.base import (
    EnvironmentNode,
    GaussianNode,
    GaussianNodeConfig,
    Node,
    NodeConfig,
    NodeContext,
    NodeOutput,
    ParamGroup,
    init_gaussian_params,
)
from omnire.placement import Placement
from omnire.plugins import PluginLoadError, Plugins, PluginSelection
from omnire.pointcloud import colour_from_images, far_shell, knn_scales, points_in_box, to_tensor, voxel_downsample
from omnire.rasterization import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    RasterInputError,
    RasterSettings,
    RenderOutput,
    Splats,
    check_raster_inputs,
)
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
    TrainObserverSpec,
)
from omnire.rowsparse import row_sparse
from omnire.rundir import CheckpointError, RunDirectory, RunDirectoryError
from omnire.runconfig import TrainConfig, TrainerConfig, parse_device
from omnire.runtime import Reconstruction
from omnire.trainer import Trainer

# Shared by dataset readers (dataparsers): option checks, camera sizes, tracks, LiDAR thinning.
from omnire.data.dataparser import (
    STATIONARY_THRESHOLD,
    MaxTrackGap,
    hold_absent_poses,
    is_stationary,
    loaded_camera,
    loaded_intrinsics,
    majority_label,
    nearest_index,
    require_files,
    resample_track,
)
from omnire.pointcloud import thin_points
# LiDAR beams (docs/lidar.md)
from omnire.beams import (
    RangeImage,
    assign_beams,
    estimate_azimuth_resolution,
    estimate_elevations,
    points_in_sensor_frame,
    range_image,
    spherical,
)
from omnire.data.scene import BeamModel

__all__ = [
    "CATEGORIES", "CULL_SIGMAS", "GAUSSIAN_KEYS", "MissingFileError", "ActorNode", "ActorState", "ActorPoses", "ActorTrack", "BackgroundConfig", "BoxActorConfig",
    "BoxActorNode", "Camera", "CameraSequence", "CommandSpec", "ConfigError", "Dataparser", "DataparserConfig",
    "DataparserSpec", "DeformationMLP", "EnvironmentNode", "GaussianNode", "GaussianNodeConfig", "Gaussians",
    "HumanPoseSequence", "ImageCache", "ImageReadError", "InstantiateConfig", "LidarSweeps", "LogDataparserConfig",
    "LossContext", "LossSpec", "MethodConfig", "MethodSpec", "Node", "NodeConfig", "NodeContext", "NodeOutput",
    "NodeTypeSpec", "ParamGroup", "PoseEstimatorSpec", "RasterInputError", "RasterSettings", "RasterizerSpec",
    "CheckpointError", "Reconstruction", "Registry", "RunDirectory", "RunDirectoryError", "RenderOutput", "SceneData", "SceneDataError", "SceneTime", "SceneWriterSpec",
    "Splats", "TrainConfig", "TrainObserverSpec", "Trainer", "TrainerConfig", "parse_device", "UserError", "View", "atomic_write_bytes",
    "atomic_write_text", "axis_angle_to_rotmat", "axis_rotation", "bracket", "check_raster_inputs", "colour_from_images",
    "far_shell", "first_pose_world", "gaussian_reach", "image_size", "frame_blend", "frame_range", "holdout_split", "hookimpl", "in_frustum", "may_be_drawn", "segment_max",
    "init_background_params", "init_gaussian_params", "interpolate_poses", "interpolate_track", "invert_se3",
    "knn_scales", "lidar_points_for_init", "points_in_box", "positional_encoding", "quat_multiply",
    "quat_to_rotmat", "quat_to_se3", "rgb_to_sh0", "rot_z", "rotmat_to_axis_angle", "rotmat_to_quat", "slerp_rotmats",
    "to_tensor", "track_displacement", "train_frame_bracket", "transform_instances", "usable_track", "user_cache_dir",
    "placed_output", "Placement",
    "visible_in_cameras", "voxel_downsample", "write_png",
    # Shared by dataset readers (dataparsers).
    "STATIONARY_THRESHOLD", "MaxTrackGap", "hold_absent_poses", "is_stationary", "loaded_camera",
    "loaded_intrinsics", "majority_label", "nearest_index", "read_image", "require_files", "resample_track", "thin_points",
    # LiDAR beams (docs/lidar.md)
    "BeamModel", "RangeImage", "assign_beams", "estimate_azimuth_resolution", "estimate_elevations",
    "points_in_sensor_frame", "range_image", "spherical",
    "ALPHA_THRESHOLD", "MAX_ALPHA", "TILE_SIZE", "TRANSMITTANCE_MIN", "NativeExtension", "PluginLoadError", "Plugins",
    "PluginSelection", "build_error_line", "interpolate_rotations", "rigid", "row_sparse", "safe_pickle",
    "ssim_map",
]
