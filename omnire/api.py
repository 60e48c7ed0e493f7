"""Everything a plugin author imports: the one public module of the core for plugins.

Third-party plugins (node types, dataparsers, rasterizers, losses, methods, commands, pose
estimators, scene writers) import from here only; docs/plugins.md shows each in use.
"""
from omnire.camera import CULL_SIGMAS, Camera, gaussian_reach, in_frustum, may_be_drawn
from omnire.config import InstantiateConfig
from omnire.data.dataparser import Dataparser, DataparserConfig, LogDataparserConfig, first_pose_world, frame_range
from omnire.data.images import ImageCache, ImageReadError, image_size
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
    rot_z,
    rotmat_to_axis_angle,
    rotmat_to_quat,
    slerp_rotmats,
)
from omnire.hookspecs import hookimpl
from omnire.interpolation import bracket, interpolate_poses, interpolate_track
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.io.cache import user_cache_dir
from omnire.io.images import write_png
from omnire.losses import LossContext
from omnire.method import MethodConfig
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
from omnire.pointcloud import colour_from_images, far_shell, knn_scales, points_in_box, to_tensor, voxel_downsample
from omnire.rasterization import RasterInputError, RasterSettings, RenderOutput, Splats, check_raster_inputs
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
from omnire.rundir import CheckpointError, RunDirectory, RunDirectoryError
from omnire.runconfig import TrainConfig, TrainerConfig
from omnire.runtime import Reconstruction
from omnire.trainer import Trainer

# Trusted input and output (issue 41): documents read with bounded nesting and line positions,
# output directories that --overwrite may replace, writes that leave nothing half-written.
from omnire.io.documents import TomlDocument, load_json, load_toml, parse_json, parse_toml, read_text
from omnire.io.outputs import (
    OutputError,
    check_location,
    check_output_dir,
    staged_directory,
    staged_files,
    writing,
)
from omnire.limits import (
    DEFAULT_FRAME_CAP,
    MAX_FPS,
    MAX_IMAGE_SIDE,
    MAX_MOTION_FRAMES,
    POSITION_MARGIN_M,
    check_fps,
    check_frame_count,
    check_npz_rows,
    check_image_size,
    check_offset,
    check_positions,
)
from omnire.rundir import flatten_eval

__all__ = [
    "CATEGORIES", "GAUSSIAN_KEYS", "MissingFileError", "ActorNode", "ActorState", "ActorPoses", "ActorTrack", "BackgroundConfig", "BoxActorConfig",
    "BoxActorNode", "Camera", "CameraSequence", "CommandSpec", "ConfigError", "Dataparser", "DataparserConfig",
    "DataparserSpec", "DeformationMLP", "EnvironmentNode", "GaussianNode", "GaussianNodeConfig", "Gaussians",
    "HumanPoseSequence", "ImageCache", "ImageReadError", "InstantiateConfig", "LidarSweeps", "LogDataparserConfig",
    "LossContext", "LossSpec", "MethodConfig", "MethodSpec", "Node", "NodeConfig", "NodeContext", "NodeOutput",
    "NodeTypeSpec", "ParamGroup", "PoseEstimatorSpec", "RasterInputError", "RasterSettings", "RasterizerSpec",
    "CheckpointError", "Reconstruction", "Registry", "RunDirectory", "RunDirectoryError", "RenderOutput", "SceneData", "SceneDataError", "SceneTime", "SceneWriterSpec",
    "Splats", "TrainConfig", "TrainObserverSpec", "Trainer", "TrainerConfig", "UserError", "View", "atomic_write_bytes",
    "atomic_write_text", "axis_angle_to_rotmat", "axis_rotation", "bracket", "check_raster_inputs", "colour_from_images",
    "far_shell", "first_pose_world", "gaussian_reach", "image_size", "frame_blend", "frame_range", "holdout_split", "hookimpl", "in_frustum",
    "init_background_params", "init_gaussian_params", "interpolate_poses", "interpolate_track", "invert_se3",
    "knn_scales", "lidar_points_for_init", "points_in_box", "positional_encoding", "quat_multiply",
    "quat_to_rotmat", "rgb_to_sh0", "rot_z", "rotmat_to_axis_angle", "rotmat_to_quat", "slerp_rotmats",
    "to_tensor", "track_displacement", "train_frame_bracket", "transform_instances", "usable_track", "user_cache_dir",
    "placed_output", "Placement",
    "visible_in_cameras", "voxel_downsample", "write_png",
    # trusted input and output (issue 41)
    "TomlDocument", "load_json", "load_toml", "parse_json", "parse_toml", "read_text",
    "OutputError", "check_location", "check_output_dir", "staged_directory", "staged_files", "writing",
    "flatten_eval", "DEFAULT_FRAME_CAP", "MAX_FPS", "MAX_IMAGE_SIDE", "MAX_MOTION_FRAMES", "POSITION_MARGIN_M",
    "check_fps", "check_frame_count", "check_npz_rows", "check_image_size", "check_offset", "check_positions",
]
