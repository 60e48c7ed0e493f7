"""What a dataparser returns: :class:`SceneData`.

Conventions (docs/conventions.md): world frame right-handed, z up, metres; cameras in
OpenCV axes (x right, y down, z forward) stored as camera-to-world 4x4; intrinsics K in
pixels at the *loaded* resolution, pixel centres at +0.5; quaternions wxyz; box pose =
box-to-world SE(3) with origin at the box centre and x along the heading, size =
(length, width, height). Frames are indexed 0..F-1 over the loaded frame range; every
per-frame array has F rows. All arrays are numpy float64/float32 (converted to torch by
the consumers), so a SceneData can be built and checked without torch.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

from omnire.errors import UserError

CATEGORIES = ("vehicle", "human", "cyclist", "other")
"""Actor categories dataparsers map their class names to. Node types declare which they take."""


class SceneDataError(UserError):
    """A dataparser produced, or was given, inconsistent data. The message names the field."""


@dataclasses.dataclass
class CameraSequence:
    """One physical camera over the frame range.

    Attributes:
        name: camera name as the dataset calls it (e.g. ``front_camera``).
        width, height: loaded image size in pixels.
        intrinsics: (3, 3) pinhole K at the loaded resolution.
        cam_to_world: (F, 4, 4) OpenCV camera-to-world per frame.
        image_paths: F image files (any resolution; loaders resize to width x height).
        timestamps: (F,) seconds.
        sky_mask_paths: optional F mask files (non-zero = sky).
        dynamic_mask_paths: optional ``{"human"|"vehicle"|"all": F files}`` (non-zero = actor).
        distortion: optional (5,) OpenCV lens distortion ``k1 k2 p1 p2 k3`` of the images on
            disk (coefficients of normalised coordinates, so independent of the resolution).
            Images and masks are undistorted to the pinhole ``intrinsics`` when loaded.
        ego_mask_path: optional image (any resolution) whose non-zero pixels show the
            recording vehicle itself in this camera; they are left out of every loss,
            densification statistic and metric.
        extras: dataset-specific per-camera fields kept with the scene (e.g. rolling-shutter
            parameters), name -> array with F rows; the core does not use them.
    """

    name: str
    width: int
    height: int
    intrinsics: np.ndarray
    cam_to_world: np.ndarray
    image_paths: list[Path]
    timestamps: np.ndarray
    sky_mask_paths: Optional[list[Path]] = None
    dynamic_mask_paths: Optional[dict[str, list[Path]]] = None
    distortion: Optional[np.ndarray] = None
    ego_mask_path: Optional[Path] = None
    extras: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.image_paths)

    def camera(self, frame: int, device="cpu"):
        """The :class:`omnire.camera.Camera` of this sequence at ``frame``."""
        from omnire.camera import Camera

        return Camera.from_numpy(self.intrinsics, self.cam_to_world[frame], self.width, self.height, self.name,
                                 device)


@dataclasses.dataclass(frozen=True)
class BeamModel:
    """The ray layout of a spinning LiDAR (docs/lidar.md).

    Angles are in the sensor frame (:attr:`LidarSweeps.sensor_to_world`: x forward, y left,
    z up): elevation above the x-y plane, azimuth counter-clockwise from +x.

    Attributes:
        elevations_deg: (B,) elevation of each beam in degrees; the beam index of a return
            (:attr:`LidarSweeps.beams`) indexes this array. Any order (datasets number
            their lasers differently); :meth:`order` sorts them.
        azimuth_resolution_deg: azimuth step between two firings of one beam, degrees.
        max_range: metres; a ray with nothing nearer returns nothing.
        min_range: metres; nearer surfaces return nothing either.
        name: the sensor, for reports.
    """

    elevations_deg: np.ndarray
    azimuth_resolution_deg: float
    max_range: float
    min_range: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        el = np.asarray(self.elevations_deg, dtype=np.float64)
        if el.ndim != 1 or len(el) == 0:
            raise SceneDataError(f"beam model {self.name!r}.elevations_deg: shape {el.shape}, expected (B,) with B >= 1")
        if not np.isfinite(el).all() or np.abs(el).max() >= 90.0:
            raise SceneDataError(f"beam model {self.name!r}.elevations_deg: expected finite degrees in (-90, 90)")
        if len(np.unique(el)) != len(el):
            raise SceneDataError(f"beam model {self.name!r}.elevations_deg: two beams share an elevation")
        res = self.azimuth_resolution_deg
        if not (np.isfinite(res) and 0.0 < res <= 360.0):
            raise SceneDataError(f"beam model {self.name!r}.azimuth_resolution_deg: {res}, expected in (0, 360]")
        if not (np.isfinite(self.max_range) and 0.0 <= self.min_range < self.max_range):
            raise SceneDataError(f"beam model {self.name!r}: min_range {self.min_range}, max_range "
                                 f"{self.max_range}; expected finite metres with 0 <= min_range < max_range")
        object.__setattr__(self, "elevations_deg", el)

    @property
    def num_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def num_azimuths(self) -> int:
        """Azimuth bins of one revolution (the width of a range image)."""
        return int(round(360.0 / self.azimuth_resolution_deg))

    def order(self) -> np.ndarray:
        """(B,) beam indices from the top beam to the bottom one (range-image rows)."""
        return np.argsort(-self.elevations_deg, kind="stable")

    def directions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every ray of one revolution: unit directions (B * A, 3) in the sensor frame,
        beam index (B * A,) and azimuth bin (B * A,), beam-major; bin k is at azimuth
        ``k * azimuth_resolution_deg``."""
        az = np.deg2rad(np.arange(self.num_azimuths) * (360.0 / self.num_azimuths))
        el = np.deg2rad(self.elevations_deg)
        E, A = np.meshgrid(el, az, indexing="ij")  # (B, A)
        d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
        beam, col = np.meshgrid(np.arange(self.num_beams), np.arange(self.num_azimuths), indexing="ij")
        return d, beam.reshape(-1), col.reshape(-1)


@dataclasses.dataclass
class LidarSweeps:
    """LiDAR points per frame, in the world frame, with what the dataset records per point.

    Every per-point field is a list of F entries aligned with ``points`` (None exactly where
    ``points[t]`` is None), or None as a whole when the dataset does not record it.
    Checked on construction (:class:`SceneDataError` naming the field).

    Attributes:
        points: F entries, each (N_t, 3) float32 world xyz, or None where the frame has no
            LiDAR (a real gap: consumers must skip it).
        origins: (F, 3) sensor origin in the world per frame (NaN where missing).
        intensity: optional F entries of (N_t,) float32 return strength in [0, 1]: the
            file's value mapped from its dataset's scale (:mod:`omnire.data.intensity`;
            PandaSet 0-255 -> / 255). LiDAR learning refuses values outside [0, 1].
        times: optional F entries of (N_t,) float64 seconds on the log's clock
            (:attr:`SceneData.frame_timestamps`) at which each return was measured.
        beams: optional F entries of (N_t,) int16 beam index into
            ``beam_model.elevations_deg``; -1 for a return of another sensor (PandaSet's
            forward PandarGT). Requires ``beam_model``.
        sensor_to_world: optional (F, 4, 4) pose of the sensor at the frame's timestamp,
            axes x forward, y left, z up (NaN where the frame has no LiDAR); its
            translation equals ``origins``.
        beam_model: optional :class:`BeamModel` of the sensor the beams refer to.
    """

    points: list[Optional[np.ndarray]]
    origins: np.ndarray
    intensity: Optional[list[Optional[np.ndarray]]] = None
    times: Optional[list[Optional[np.ndarray]]] = None
    beams: Optional[list[Optional[np.ndarray]]] = None
    sensor_to_world: Optional[np.ndarray] = None
    beam_model: Optional[BeamModel] = None

    def __post_init__(self) -> None:
        F = len(self.points)
        for name in ("intensity", "times", "beams"):
            self._check_per_point(name, F)
        if self.beams is not None:
            if self.beam_model is None:
                raise SceneDataError("lidar.beams: given without lidar.beam_model (the elevations they index)")
            B = self.beam_model.num_beams
            for t, b in enumerate(self.beams):
                if b is not None and len(b) and (b.min() < -1 or b.max() >= B):
                    raise SceneDataError(f"lidar.beams[{t}]: values {b.min()}..{b.max()}, expected -1..{B - 1}")
        if self.intensity is not None:
            for t, v in enumerate(self.intensity):
                if v is not None and len(v) and not v.min() >= 0:
                    raise SceneDataError(f"lidar.intensity[{t}]: negative values, expected >= 0")
        if self.sensor_to_world is not None:
            _check_shape(self.sensor_to_world, (F, 4, 4), "lidar.sensor_to_world", finite=False)
            have = np.array([p is not None for p in self.points], dtype=bool)
            poses = self.sensor_to_world[have]
            if not np.isfinite(poses).all():
                raise SceneDataError("lidar.sensor_to_world: NaN or inf in a frame that has LiDAR")
            if len(poses) and np.abs(poses[:, :3, 3] - np.asarray(self.origins)[have]).max() > 1e-6:
                raise SceneDataError("lidar.sensor_to_world: translations differ from lidar.origins")

    def _check_per_point(self, name: str, F: int) -> None:
        values = getattr(self, name)
        if values is None:
            return
        if len(values) != F:
            raise SceneDataError(f"lidar.{name}: {len(values)} frames, expected {F} (one per lidar.points entry)")
        for t, (v, p) in enumerate(zip(values, self.points)):
            if (v is None) != (p is None):
                raise SceneDataError(f"lidar.{name}[{t}]: {'None' if v is None else 'given'} where lidar.points[{t}] "
                                     f"is {'None' if p is None else 'given'}")
            if v is None:
                continue
            if not isinstance(v, np.ndarray) or v.shape != (len(p),):
                raise SceneDataError(f"lidar.{name}[{t}]: shape {getattr(v, 'shape', type(v).__name__)}, "
                                     f"expected ({len(p)},) (one value per point)")
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                raise SceneDataError(f"lidar.{name}[{t}]: contains NaN or inf")

    def available_frames(self) -> list[int]:
        return [i for i, p in enumerate(self.points) if p is not None]


@dataclasses.dataclass
class ActorTrack:
    """One tracked actor.

    Attributes:
        track_id: stable id from the dataset (string).
        class_name: the dataset's class label (e.g. ``Car``).
        category: one of :data:`CATEGORIES`.
        poses: (F, 4, 4) box-to-world; rows where ``present`` is False are unspecified.
        size: (3,) length, width, height in metres (max over frames when the dataset varies).
        present: (F,) bool, True where the actor is annotated in that frame.
        stationary: True when the dataset says (or motion shows) the actor never moves.
        extras: dataset-specific per-track fields kept with the scene (e.g. camera-synced
            boxes), name -> array or value; the core does not use them.
    """

    track_id: str
    class_name: str
    category: str
    poses: np.ndarray
    size: np.ndarray
    present: np.ndarray
    stationary: bool = False
    extras: dict = dataclasses.field(default_factory=dict)

    def frames(self) -> np.ndarray:
        return np.flatnonzero(self.present)


@dataclasses.dataclass
class HumanPoseSequence:
    """SMPL pose sequence of one pedestrian track (world frame, SMPL joint order).

    Attributes:
        track_id: the :class:`ActorTrack` this belongs to.
        global_orient: (F, 3, 3) body-to-world rotation of the pelvis.
        body_pose: (F, 23, 3, 3) local joint rotations.
        betas: (B,) shape coefficients (B may be 0).
        valid: (F,) bool, frames with an observed (not interpolated) estimate.
        source: how the poses were obtained (estimator name, ``smpl.pkl``, ``neutral``).
    """

    track_id: str
    global_orient: np.ndarray
    body_pose: np.ndarray
    betas: np.ndarray
    valid: np.ndarray
    source: str = "unknown"


@dataclasses.dataclass(frozen=True)
class View:
    """One image of the scene: camera index and frame index."""

    camera: int
    frame: int


@dataclasses.dataclass(frozen=True)
class SceneTime:
    """A moment of the log, as nodes see it.

    Attributes:
        frame: position in frame indices; fractional between recorded frames (a rendered
            moment between two frames interpolates what was recorded at both).
        seconds: the same moment in seconds (the log's clock).
    """

    frame: float
    seconds: float

    @property
    def index(self) -> int | None:
        """The frame index when the moment is a recorded frame, else None."""
        return int(self.frame) if float(self.frame).is_integer() else None


BOX_TIMINGS = ("frame", "sweep")
"""The moments a dataset's boxes can hold their actors at (:attr:`SceneData.box_timing`)."""


def holdout_split(num_frames: int, every: int) -> tuple[np.ndarray, np.ndarray]:
    """Train/test frame split: frames ``every, 2*every, ...`` are held out (all cameras).

    With ``every <= 0`` nothing is held out. Returns (train_frames, test_frames) int arrays.
    Matches the paper's protocol for N=10 (test frames 10, 20, ...).
    """
    frames = np.arange(num_frames)
    if every <= 0:
        return frames, frames[:0]
    test = (frames % every == 0) & (frames > 0)
    return frames[~test], frames[test]


@dataclasses.dataclass
class SceneData:
    """Everything a scene holds, as returned by a dataparser.

    Attributes:
        name: human-readable scene name.
        cameras: the cameras (each with F frames).
        frame_timestamps: (F,) seconds of each frame.
        source_frames: (F,) frame numbers in the source log (for file names and reports).
        train_frames, test_frames: frame indices (into 0..F-1).
        lidar: optional LiDAR sweeps.
        tracks: actor tracks.
        human_poses: optional pose sequences keyed by track id.
        ego_poses: optional (F, 4, 4) ego-to-world.
        attribution: licence text to show with renders of this data.
        estimate_ego_masks: estimate masks of the recording vehicle from the images for the
            cameras without an ``ego_mask_path`` (:mod:`omnire.egomask`).
        box_timing: when a frame's boxes hold their actors (one of :data:`BOX_TIMINGS`):
            ``"frame"`` at the frame's timestamp; ``"sweep"`` where the frame's LiDAR sweep
            saw them (annotators draw boxes on the sweep's points, which a rotating sensor
            records over its revolution), so a rendered sweep places the actors of every time
            sector at the sweep's end, as annotated (``Reconstruction.sweep_actor_moment``).
    """

    name: str
    cameras: list[CameraSequence]
    frame_timestamps: np.ndarray
    source_frames: np.ndarray
    train_frames: np.ndarray
    test_frames: np.ndarray
    lidar: Optional[LidarSweeps] = None
    tracks: list[ActorTrack] = dataclasses.field(default_factory=list)
    human_poses: dict[str, HumanPoseSequence] = dataclasses.field(default_factory=dict)
    ego_poses: Optional[np.ndarray] = None
    attribution: str = ""
    estimate_ego_masks: bool = False
    box_timing: str = "frame"

    @property
    def num_frames(self) -> int:
        return len(self.frame_timestamps)

    def time_of_frame(self, frame: float) -> SceneTime:
        """The moment at (possibly fractional) ``frame``; seconds interpolated linearly."""
        if not 0 <= frame <= self.num_frames - 1:
            raise SceneDataError(f"scene {self.name!r}: frame {frame} outside 0..{self.num_frames - 1}")
        if float(frame).is_integer():
            return SceneTime(frame, float(self.frame_timestamps[int(frame)]))
        seconds = float(np.interp(frame, np.arange(self.num_frames), self.frame_timestamps))
        return SceneTime(float(frame), seconds)

    def time_since_start(self, seconds: float) -> SceneTime:
        """The moment ``seconds`` after the first frame (clamped to the log): the fractional
        frame between the enclosing recorded frames, its seconds as :meth:`time_of_frame`
        gives them (a recorded frame's time gives that frame exactly)."""
        from omnire.interpolation import bracket

        since = np.asarray(self.frame_timestamps, dtype=np.float64)
        since = since - since[0]
        i0, i1, w = bracket(since, min(max(seconds, 0.0), float(since[-1])))
        return self.time_of_frame(float(i0[0] + w[0] * (i1[0] - i0[0])))

    def camera(self, view: View, device="cpu"):
        """The :class:`omnire.camera.Camera` of ``view``."""
        return self.cameras[view.camera].camera(view.frame, device)

    def views(self, frames: np.ndarray) -> list[View]:
        """All (camera, frame) views for the given frames, frame-major."""
        return [View(c, int(f)) for f in frames for c in range(len(self.cameras))]

    def camera_index(self, name: str) -> int:
        for i, cam in enumerate(self.cameras):
            if cam.name == name:
                return i
        raise SceneDataError(
            f"scene {self.name!r} has no camera {name!r}; cameras: {[c.name for c in self.cameras]}"
        )

    def validate(self) -> "SceneData":
        """Check shapes and finiteness; raise :class:`SceneDataError` naming the field."""
        F = self.num_frames
        if F == 0:
            raise SceneDataError(f"scene {self.name!r}: no frames")
        if not self.cameras:
            raise SceneDataError(f"scene {self.name!r}: no cameras")
        _check_shape(np.asarray(self.frame_timestamps, dtype=np.float64), (F,), "frame_timestamps")
        if F > 1 and not np.all(np.diff(self.frame_timestamps) > 0):
            raise SceneDataError(f"scene {self.name!r}: frame_timestamps must increase strictly")
        if self.box_timing not in BOX_TIMINGS:
            raise SceneDataError(f"scene {self.name!r}: box_timing {self.box_timing!r}, expected one of {BOX_TIMINGS}")
        for cam in self.cameras:
            where = f"camera {cam.name!r}"
            _check_shape(cam.intrinsics, (3, 3), f"{where}.intrinsics")
            fx, fy, cx, cy = cam.intrinsics[0, 0], cam.intrinsics[1, 1], cam.intrinsics[0, 2], cam.intrinsics[1, 2]
            if not (fx > 0 and fy > 0):
                raise SceneDataError(f"{where}.intrinsics: focal lengths fx={fx}, fy={fy} must be positive")
            if not (-cam.width <= cx <= 2 * cam.width and -cam.height <= cy <= 2 * cam.height):
                raise SceneDataError(f"{where}.intrinsics: principal point ({cx:.1f}, {cy:.1f}) is far outside the "
                                     f"{cam.width}x{cam.height} image (wrong units or a wrong image size?)")
            _check_shape(cam.cam_to_world, (F, 4, 4), f"{where}.cam_to_world")
            _check_shape(np.asarray(cam.timestamps, dtype=np.float64), (F,), f"{where}.timestamps")
            if len(cam.image_paths) != F:
                raise SceneDataError(f"{where}.image_paths: {len(cam.image_paths)} entries, expected {F}")
            if cam.width <= 0 or cam.height <= 0:
                raise SceneDataError(f"{where}: image size {cam.width}x{cam.height} must be positive")
            if cam.distortion is not None:
                _check_shape(np.asarray(cam.distortion), (5,), f"{where}.distortion (k1 k2 p1 p2 k3)")
            for key, value in cam.extras.items():
                if len(value) != F:
                    raise SceneDataError(f"{where}.extras[{key!r}]: {len(value)} rows, expected {F}")
            for mask_list, label in [(cam.sky_mask_paths, "sky_mask_paths")] + [
                (v, f"dynamic_mask_paths[{k!r}]") for k, v in (cam.dynamic_mask_paths or {}).items()
            ]:
                if mask_list is not None and len(mask_list) != F:
                    raise SceneDataError(f"{where}.{label}: {len(mask_list)} entries, expected {F}")
        if self.lidar is not None:
            if len(self.lidar.points) != F:
                raise SceneDataError(f"lidar.points: {len(self.lidar.points)} frames, expected {F}")
            _check_shape(self.lidar.origins, (F, 3), "lidar.origins", finite=False)
            for i, pts in enumerate(self.lidar.points):
                if pts is not None:
                    if pts.ndim != 2 or pts.shape[1] != 3:
                        raise SceneDataError(f"lidar.points[{i}]: shape {pts.shape}, expected (N, 3)")
                    if not np.isfinite(pts).all():
                        raise SceneDataError(f"lidar.points[{i}]: non-finite coordinates")
        for tr in self.tracks:
            where = f"track {tr.track_id!r} ({tr.class_name})"
            if tr.category not in CATEGORIES:
                raise SceneDataError(f"{where}.category {tr.category!r}: expected one of {CATEGORIES}")
            _check_shape(tr.poses, (F, 4, 4), f"{where}.poses", finite=False)
            _check_shape(tr.size, (3,), f"{where}.size")
            if tr.present.shape != (F,) or tr.present.dtype != bool:
                raise SceneDataError(f"{where}.present: expected bool array of shape ({F},)")
            if not np.isfinite(tr.poses[tr.present]).all():
                raise SceneDataError(f"{where}.poses: non-finite pose in a frame where it is present")
        for tid, hp in self.human_poses.items():
            where = f"human_poses[{tid!r}]"
            _check_shape(hp.global_orient, (F, 3, 3), f"{where}.global_orient")
            _check_shape(hp.body_pose, (F, 23, 3, 3), f"{where}.body_pose")
        split = np.concatenate([self.train_frames, self.test_frames])
        if len(split) and (split.min() < 0 or split.max() >= F):
            raise SceneDataError(f"train/test frames must lie in 0..{F - 1}")
        return self


def _check_shape(a: np.ndarray, shape: tuple[int, ...], field: str, finite: bool = True) -> None:
    if not isinstance(a, np.ndarray) or a.shape != shape:
        got = getattr(a, "shape", type(a).__name__)
        raise SceneDataError(f"{field}: shape {got}, expected {shape}")
    if finite and not np.isfinite(a).all():
        raise SceneDataError(f"{field}: contains NaN or inf")
