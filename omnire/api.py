"""Everything a plugin author imports: the public module of the core for plugins.

Third-party plugins (node types, dataparsers, rasterizers, losses, methods, commands, pose
estimators, scene writers, training observers) import from here, and command and benchmark
authors also from :mod:`omnire.command_api`; no other core module is public (an
import-linter contract in pyproject.toml keeps plugin packages to these two).
docs/plugins.md shows each in use.
"""
from omnire.beams import (
    BeamFit,
    RangeImage,
    assign_beams,
    estimate_azimuth_resolution,
    estimate_elevations,
    fit_beams,
    median_per_beam,
    points_in_sensor_frame,
    range_image,
    spherical,
    spread_sample,
    whole_revolution_step,
)
from omnire.camera import CULL_SIGMAS, Camera, gaussian_reach, in_frustum, may_be_drawn
from omnire.config import InstantiateConfig
from omnire.contribution import keep_top, node_contributions, prune_nodes, sweep_weights, view_weights
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
from omnire.data.intensity import BYTE_INTENSITY, UNBOUNDED_INTENSITY, UNIT_INTENSITY, IntensityScale
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
    lowpass_conics,
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
from omnire.interpolation import bracket, extend_poses, interpolate_poses, interpolate_rotations, interpolate_track
from omnire.io import safe_pickle
from omnire.io.atomic import atomic_write_bytes, atomic_write_text
from omnire.io.cache import user_cache_dir
from omnire.io.documents import TomlDocument, load_json, load_toml, parse_json, parse_toml, read_text
from omnire.io.images import write_png
from omnire.io.outputs import OutputError, check_location, check_output_dir, staged_directory, staged_files, writing
from omnire.lidar_baselines import (
    LidarMesh,
    baseline_metrics,
    cell_tolerance_deg,
    lidar_mesh,
    mesh_render,
    nearest_sweep_render,
    sensor_returns,
    sweep_triangles,
)
from omnire.lidar_metrics import BOX_CATEGORIES, Box, RenderedSweep, boxes_at, lidar_metrics, mean_metrics
from omnire.lidarmodel import LIDAR_KEY, LidarConfig, LidarRender
from omnire.lidarpoints import POINT_FIELDS, sweep_points, write_point_cloud
from omnire.lidarprojection import (
    SphereTiles,
    SphericalSplats,
    max_response_range,
    project_lidar,
    ray_directions,
    wrap_degrees,
)
from omnire.lidarsweep import (
    SensorPath,
    SweepRays,
    beam_model_sweep,
    fixed_path,
    recorded_sweep,
    sectors_of,
    sensor_path,
    shifted_path,
    sweep_rays,
)
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
    observed_in_training,
    placed_output,
    seen_by_lidar,
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
    LidarRasterizer,
    LidarRays,
    LidarRenderOutput,
    LidarSettings,
    RasterInputError,
    Rasterizer,
    RasterSettings,
    RenderOutput,
    Splats,
    SsimRasterizer,
    check_lidar_inputs,
    check_raster_inputs,
)
from omnire.raycast import RayHits, first_hits
from omnire.registration import Lazy, LazyTargetError, lazy
from omnire.registry import (
    CommandSpec,
    DataparserSpec,
    LossSpec,
    MethodSpec,
    NativeExtensionSpec,
    NodeTypeSpec,
    PoseEstimatorSpec,
    RasterizerSpec,
    Registry,
    SceneWriterSpec,
    TrainObserverSpec,
)
from omnire.rollingshutter import SweepSector, spin_times, sweep_sectors
from omnire.rowsparse import row_sparse
from omnire.runconfig import TrainConfig, TrainerConfig, parse_device
from omnire.rundir import CheckpointError, RunDirectory, RunDirectoryError, flatten_eval
from omnire.runtime import ActorEdits, Drawn, EditedActor, Reconstruction
from omnire.trainer import Trainer

__all__ = [name for name in sorted(dir()) if not name.startswith("_")]
"""Every name imported above (each is listed once, in its import)."""
