"""Everything a plugin author imports: the public module of the core for plugins.

Third-party plugins (node types, dataparsers, rasterizers, losses, methods, commands, pose
estimators, scene writers, training observers) import from here, and command and benchmark
authors also from :mod:`omnire.command_api`; no other core module is public (an
import-linter contract in pyproject.toml keeps plugin packages to these two).
docs/plugins.md shows each in use.
"""
from omnire.beams import (
    RangeImage,
    assign_beams,
    estimate_azimuth_resolution,
    estimate_elevations,
    points_in_sensor_frame,
    range_image,
    spherical,
)
from omnire.camera import CULL_SIGMAS, Camera, gaussian_reach, in_frustum, may_be_drawn
from omnire.config import InstantiateConfig
from omnire.data.dataparser import (
    STATIONARY_THRESHOLD,
    Dataparser,
    DataparserConfig,
    LogDataparserConfig,
    MaxTrackGap,
    first_pose_world,
    frame_range,
    hold_absent_poses,
    is_stationary,
    loaded_camera,
    loaded_intrinsics,
    majority_label,
    nearest_index,
    require_files,
    resample_track,
)
from omnire.data.images import ImageCache, ImageReadError, image_size, read_image
from omnire.data.scene import (
    CATEGORIES,
    ActorTrack,
    BeamModel,
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
from omnire.io.documents import TomlDocument, load_json, load_toml, parse_json, parse_toml, read_text
from omnire.io.images import write_png
from omnire.io.outputs import OutputError, check_location, check_output_dir, staged_directory, staged_files, writing
from omnire.limits import (
    DEFAULT_FRAME_CAP,
    MAX_FPS,
    MAX_IMAGE_SIDE,
    MAX_MOTION_FRAMES,
    POSITION_MARGIN_M,
    check_fps,
    check_frame_count,
    check_image_size,
    check_npz_rows,
    check_offset,
    check_positions,
)
from omnire.losses import LossContext, ssim_map
from omnire.method import MethodConfig
from omnire.native import NativeExtension, build_error_line
from omnire.nn import DeformationMLP, positional_encoding
from omnire.nodes.actors import (
    ActorNode,
    ActorPoses,
    ActorState,
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
from omnire.pointcloud import (
    colour_from_images,
    far_shell,
    knn_scales,
    points_in_box,
    thin_points,
    to_tensor,
    voxel_downsample,
)
from omnire.rasterization import (
    ALPHA_THRESHOLD,
    CAPABILITIES,
    MAX_ALPHA,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    FusedTrainingRasterizer,
    InferenceRasterizer,
    RasterInputError,
    Rasterizer,
    RasterSettings,
    RenderOutput,
    Splats,
    SsimRasterizer,
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
from omnire.runconfig import TrainConfig, TrainerConfig, parse_device
from omnire.rundir import CheckpointError, RunDirectory, RunDirectoryError, flatten_eval
from omnire.runtime import ActorEdits, Drawn, EditedActor, Reconstruction
from omnire.trainer import Trainer

__all__ = [
    "ALPHA_THRESHOLD", "CAPABILITIES", "CATEGORIES", "CULL_SIGMAS", "DEFAULT_FRAME_CAP", "GAUSSIAN_KEYS",
    "MAX_ALPHA", "MAX_FPS", "MAX_IMAGE_SIDE", "MAX_MOTION_FRAMES", "POSITION_MARGIN_M", "STATIONARY_THRESHOLD",
    "TILE_SIZE", "TRANSMITTANCE_MIN", "ActorEdits", "ActorNode", "ActorPoses", "ActorState", "ActorTrack",
    "BackgroundConfig", "BeamModel", "BoxActorConfig", "BoxActorNode", "Camera", "CameraSequence",
    "CheckpointError", "CommandSpec", "ConfigError", "Dataparser", "DataparserConfig", "DataparserSpec",
    "DeformationMLP", "Drawn", "EditedActor", "EnvironmentNode", "FusedTrainingRasterizer", "GaussianNode",
    "GaussianNodeConfig", "Gaussians", "HumanPoseSequence", "ImageCache", "ImageReadError", "InferenceRasterizer",
    "InstantiateConfig", "LidarSweeps", "LogDataparserConfig", "LossContext", "LossSpec", "MaxTrackGap",
    "MethodConfig", "MethodSpec", "MissingFileError", "NativeExtension", "Node", "NodeConfig", "NodeContext",
    "NodeOutput", "NodeTypeSpec", "OutputError", "ParamGroup", "Placement", "PluginLoadError", "Plugins",
    "PluginSelection", "PoseEstimatorSpec", "RangeImage", "RasterInputError", "Rasterizer", "RasterizerSpec",
    "RasterSettings", "Reconstruction", "Registry", "RenderOutput", "RunDirectory", "RunDirectoryError",
    "SceneData", "SceneDataError", "SceneTime", "SceneWriterSpec", "Splats", "SsimRasterizer", "TomlDocument",
    "TrainConfig", "Trainer", "TrainerConfig", "TrainObserverSpec", "UserError", "View", "assign_beams",
    "atomic_write_bytes", "atomic_write_text", "axis_angle_to_rotmat", "axis_rotation", "bracket",
    "build_error_line", "check_fps", "check_frame_count", "check_image_size", "check_location", "check_npz_rows",
    "check_offset", "check_output_dir", "check_positions", "check_raster_inputs", "colour_from_images",
    "estimate_azimuth_resolution", "estimate_elevations", "far_shell", "first_pose_world", "flatten_eval",
    "frame_blend", "frame_range", "gaussian_reach", "hold_absent_poses", "holdout_split", "hookimpl", "image_size",
    "in_frustum", "init_background_params", "init_gaussian_params", "interpolate_poses", "interpolate_rotations",
    "interpolate_track", "invert_se3", "is_stationary", "knn_scales", "lidar_points_for_init", "load_json",
    "load_toml", "loaded_camera", "loaded_intrinsics", "majority_label", "may_be_drawn", "nearest_index",
    "parse_device", "parse_json", "parse_toml", "placed_output", "points_in_box", "points_in_sensor_frame",
    "positional_encoding", "quat_multiply", "quat_to_rotmat", "quat_to_se3", "range_image", "read_image",
    "read_text", "require_files", "resample_track", "rgb_to_sh0", "rigid", "rot_z", "rotmat_to_axis_angle",
    "rotmat_to_quat", "row_sparse", "safe_pickle", "segment_max", "slerp_rotmats", "spherical", "ssim_map",
    "staged_directory", "staged_files", "thin_points", "to_tensor", "track_displacement", "train_frame_bracket",
    "transform_instances", "usable_track", "user_cache_dir", "visible_in_cameras", "voxel_downsample", "write_png",
    "writing",
]
