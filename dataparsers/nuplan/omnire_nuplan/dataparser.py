"""nuPlan reader: one log as distributed (SQLite database + sensor blobs) -> :class:`SceneData`.

Layout read (the release's; ``--data`` is the database or a folder holding one)::

    nuplan-v1.1/splits/<split>/<log>.db                        the log's tables (database.py)
    nuplan-v1.1/sensor_blobs/<log>/CAM_F0/<token>.jpg          8 cameras, image.filename_jpg
    nuplan-v1.1/sensor_blobs/<log>/MergedPointCloud/<token>.pcd  lidar_pc.filename (pointcloud.py)

Conventions, each from nuplan-devkit (paths under ``nuplan/database/``; schema in
``docs/nuplan_schema.md``):

- Timestamps are integer microseconds (``nuplan_db/nuplan_scenario_queries.py``
  ``get_images_from_lidar_tokens``: ``lookahead_window_us=50000`` is "0.05s"). lidar_pc rows
  come at 20 Hz, images at 10 Hz per camera (same docstring).
- Quaternions are w, x, y, z: ``ego_pose.qw qx qy qz`` (``nuplan_db_orm/ego_pose.py``
  ``Quaternion(self.qw, self.qx, self.qy, self.qz)``); camera and lidar ``rotation`` is
  ``Quaternion(self.rotation)`` of a [w, x, y, z] list (schema: "quaternion: w, x, y, z").
- ``ego_pose`` is ego-to-global; ``camera`` / ``lidar`` rows are sensor-to-ego; merged point
  clouds are in their ``lidar`` row's frame. The devkit maps LiDAR points into an image with
  ``camera.trans_matrix_inv @ ego_pose(image).trans_matrix_inv @ ego_pose(lidar_pc).trans_matrix
  @ lidar.trans_matrix`` (``nuplan_db_orm/rendering_utils.py`` ``map_pointcloud_to_image``),
  and takes boxes global -> camera the same way (``nuplan_db_orm/image.py`` ``Image.boxes``,
  ``utils.py`` ``get_boxes``). Each image and each lidar_pc has its own ego_pose row.
- The camera frame is OpenCV's (x right, y down, z forward): the devkit projects
  camera-frame points with ``view_points(points, camera.intrinsic, normalize=True)``
  (``utils/geometry.py``), dividing by z, and keeps those with depth > 0
  (``map_pointcloud_to_image``). ``camera.intrinsic`` is a 3x3 K of the distorted
  image; ``camera.distortion`` is (k1, k2, p1, p2, k3) "according to the Caltech model"
  (schema), the OpenCV / Bouguet model: images are undistorted at load to K.
- Pixel centres: the devkit draws projected points over ``ax.imshow(image)``
  (``nuplan_db_orm/rendering_utils.py`` ``render_pointcloud_in_image``, ``image.py``
  ``Image.render``), and imshow centres pixel (i, j) at integer coordinates; K is read in
  that (OpenCV) convention and shifted by +0.5 px to omnire's.
- ``lidar_box`` rows are in the global frame ("center_x in global coordinates", schema; the
  devkit's ``LidarPc.boxes`` returns them as ``Frame.GLOBAL`` by default), rotated by ``yaw``
  about the global z axis only (``nuplan_db_orm/lidar_box.py`` ``LidarBox.rotation``: roll and
  pitch 0). Size is (width, length, height) (``LidarBox.size``) and the box's x axis runs
  along the length (``utils/boxes/box3d.py`` ``Box3D._calc_corners``: x * length / 2,
  y * width / 2). omnire boxes keep that rotation with size = (length, width, height).

Frames: every ``--frame-step``-th lidar_pc of the log (default 2: the paper's code takes
every second lidar_pc, 10 Hz, ziyc/drivestudio ``datasets/nuplan/nuplan_preprocess.py``,
starting at the one of the two interleaved phases whose sweeps lie nearest the images, as it
does). Each camera takes, per frame, its image nearest in time (at most
``--max-camera-offset`` away) with that image's own timestamp and ego pose. Boxes come from
the lidar_pc of each frame (nuPlan boxes every lidar_pc, so every frame has its own; by
default, ``--max-track-gap 0``, a frame without a box of a track leaves the actor absent
there, as in the reference's preprocessing; a positive gap interpolates across such frames).
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Optional, Type

import numpy as np

from omnire.api import (
    BYTE_INTENSITY,
    ActorTrack,
    CameraSequence,
    ConfigError,
    Dataparser,
    LidarSweeps,
    LogDataparserConfig,
    SceneData,
    first_pose_world,
    frame_range,
    image_size,
    is_stationary,
    loaded_camera,
    nearest_index,
    require_files,
    resample_track,
    rot_z,
    thin_points,
)
from omnire_nuplan.database import (
    LogDatabase,
    NuPlanDataError,
    NuPlanFileMissing,
    Row,
    index,
    lookup,
    pose,
    raw_tokens,
)
from omnire_nuplan.lidars import (
    ESTIMATE_SWEEPS,
    beams_of,
    ring_and_lidar,
    top_beam_model,
    top_ring_count,
)
from omnire_nuplan.pointcloud import read_points

CAMERAS = ("CAM_F0", "CAM_L0", "CAM_R0", "CAM_L1", "CAM_R1", "CAM_L2", "CAM_R2", "CAM_B0")
"""The eight nuPlan cameras (the reference's camera ids 0..7 in this order)."""
ATTRIBUTION = (
    '"nuPlan: A closed-loop ML-based planning benchmark for autonomous vehicles", Caesar et al., 2021; nuPlan by '
    "Motional, CC BY-NC-SA 4.0 (non-commercial use; nuPlan Terms of Use)."
)


def category_of(name: str) -> str:
    """nuPlan category name (vehicle, bicycle, pedestrian, traffic_cone, barrier, czone_sign,
    generic_object) -> omnire actor category."""
    return {"vehicle": "vehicle", "pedestrian": "human", "bicycle": "cyclist"}.get(name, "other")


def box_to_global(row: Row) -> np.ndarray:
    """(4, 4) box-to-global of a lidar_box row: centre (x, y, z), rotation yaw about z."""
    T = np.eye(4)
    T[:3, :3] = rot_z(np.array(row.number("yaw")))
    T[:3, 3] = [row.number("x"), row.number("y"), row.number("z")]
    return T


class NuPlanDataparser(Dataparser):
    """Reads one nuPlan log (see the module docstring for the layout and conventions)."""

    config: "NuPlanConfig"

    def parse(self) -> SceneData:
        cfg = self.config
        self._check_options()
        db_path = self._database()
        blobs = self._sensor_blobs(db_path)
        with LogDatabase(db_path) as db:
            pcs = db.rows("lidar_pc", order="timestamp, token")
            if not pcs:
                raise NuPlanDataError(f"{db_path}: table lidar_pc has no rows: the log has no LiDAR sample "
                                      "(the frame clock of this reader)")
            t_pc = np.array([r.integer("timestamp") for r in pcs], dtype=np.int64)
            if np.any(np.diff(t_pc) <= 0):
                i = int(np.flatnonzero(np.diff(t_pc) <= 0)[0])
                raise NuPlanDataError(f"{db_path}: table lidar_pc rows {pcs[i].token} and {pcs[i + 1].token} share "
                                      f"timestamp {t_pc[i]}")
            images = self._images(db, db_path)
            names = list(images)
            phase = self._phase(t_pc, np.array([r.integer("timestamp") for r in images[names[0]]], dtype=np.int64))
            chosen = pcs[phase::cfg.frame_step]
            rng = frame_range(cfg.start_frame, cfg.end_frame, len(chosen),
                              f"nuPlan log {db_path.stem} ({len(chosen)} frames at --frame-step {cfg.frame_step})")
            frame_pcs = chosen[rng.start:rng.stop]
            frame_us = np.array([r.integer("timestamp") for r in frame_pcs], dtype=np.int64)

            cam_imgs = {}
            for name in names:
                recs = images[name]
                t = np.array([r.integer("timestamp") for r in recs], dtype=np.int64)
                pick = nearest_index(t, frame_us)
                far = np.abs(t[pick] - frame_us) > cfg.max_camera_offset * 1e6
                if far.any():
                    j = int(np.flatnonzero(far)[0])
                    raise NuPlanDataError(
                        f"{db_path}: table image has no {name} image within {cfg.max_camera_offset} s of lidar_pc "
                        f"{frame_pcs[j].token} (timestamp {frame_us[j]}; nearest {t[pick[j]]}); "
                        "--max-camera-offset sets the tolerance")
                cam_imgs[name] = [recs[i] for i in pick]
            ego = index(db.rows_with("ego_pose", "token", raw_tokens(frame_pcs, "ego_pose_token") + [
                v for recs in cam_imgs.values() for v in raw_tokens(recs, "ego_pose_token")]))

            def ego_of(row: Row) -> np.ndarray:
                e = lookup(ego, row, "ego_pose_token", "ego_pose")
                t = np.array([e.number("x"), e.number("y"), e.number("z")])
                q = np.array([e.number("qw"), e.number("qx"), e.number("qy"), e.number("qz")])
                return pose(t, q, e, "qw qx qy qz")

            ego_frames = np.stack([ego_of(r) for r in frame_pcs])  # (F, 4, 4) ego -> global
            world = first_pose_world(ego_frames[0])  # (4, 4) global -> omnire world
            cameras = index(db.rows("camera"))
            cams = [self._camera(name, cam_imgs[name], cameras, ego_of, world, blobs, db_path) for name in names]
            lidar = self._lidar(db, frame_pcs, ego_frames, world, blobs) if cfg.load_lidar else None
            tracks = self._tracks(db, frame_pcs, frame_us, world)
        source_frames = np.array([phase + cfg.frame_step * i for i in rng], dtype=np.int64)
        return self.build_scene(f"nuplan_{db_path.stem}", cams, frame_us * 1e-6, source_frames, lidar=lidar,
                                tracks=tracks, ego_poses=world[None] @ ego_frames, attribution=ATTRIBUTION)

    # -- options and files ------------------------------------------------------------------
    def _check_options(self) -> None:
        cfg = self.config
        cfg.check()
        if cfg.frame_step < 1:
            raise ConfigError(f"frame_step: {cfg.frame_step}, expected >= 1 (1 = every 20 Hz lidar_pc, 2 = 10 Hz)")
        if not cfg.max_camera_offset >= 0:
            raise ConfigError(f"max_camera_offset: {cfg.max_camera_offset}, expected seconds >= 0")
        bad = [c for c in cfg.cameras if c not in CAMERAS]
        if bad:
            raise ConfigError(f"cameras: {bad} are not nuPlan cameras; choose from {list(CAMERAS)}")

    def _database(self) -> Path:
        data = Path(self.config.data)
        if data.is_file():
            return data
        if not data.is_dir():
            raise NuPlanFileMissing(f"{data}: no such nuPlan log database or folder (expected <log>.db, e.g. "
                                    "nuplan-v1.1/splits/mini/<log>.db, or a folder holding one)")
        found = sorted(data.rglob("*.db"))
        if len(found) != 1:
            listed = ", ".join(str(p.relative_to(data)) for p in found[:8]) + (" ..." if len(found) > 8 else "")
            raise ConfigError(f"data: {data} holds {len(found)} .db files ({listed or 'none'}); pass one log's "
                              "database with --data")
        return found[0]

    def _sensor_blobs(self, db_path: Path) -> Path:
        if self.config.sensor_blobs is not None:
            blobs = Path(self.config.sensor_blobs)
            if not blobs.is_dir():
                raise NuPlanFileMissing(f"{blobs}: --sensor-blobs folder does not exist (expected the folder holding "
                                        "<log>/CAM_F0/..., <log>/MergedPointCloud/...)")
            return blobs
        # The release keeps nuplan-v1.1/splits/<split>/<log>.db beside nuplan-v1.1/sensor_blobs/.
        candidates = [p / "sensor_blobs" for p in (db_path.parent.parent.parent, db_path.parent.parent, db_path.parent)]
        for blobs in candidates:
            if blobs.is_dir():
                return blobs
        raise NuPlanFileMissing(f"{candidates[0]}: no sensor_blobs folder beside the log database {db_path} (looked "
                                f"in {', '.join(str(c) for c in candidates)}); pass it with --sensor-blobs")

    def _images(self, db: LogDatabase, db_path: Path) -> dict[str, list[Row]]:
        """Image rows per loaded camera channel, in time order."""
        by_channel: dict[str, list[Row]] = {}
        for cam in db.rows("camera"):
            by_channel.setdefault(cam.text("channel"), []).append(cam)
        present = [c for c in CAMERAS if c in by_channel]
        if not present:
            raise NuPlanDataError(f"{db_path}: table camera has no row of a nuPlan camera ({', '.join(CAMERAS)}): "
                                  f"the log has no camera (channels: {sorted(by_channel) or 'none'})")
        missing = [c for c in self.config.cameras if c not in by_channel]
        if missing:
            raise NuPlanDataError(f"{db_path}: table camera has no row for {missing}; cameras of this log: {present}")
        out = {}
        for name in self.config.cameras or present:
            recs = db.rows_with("image", "camera_token", raw_tokens(by_channel[name]))
            if recs:
                recs.sort(key=lambda r: (r.integer("timestamp"), r.token))
                out[name] = recs
            elif self.config.cameras:
                raise NuPlanDataError(f"{db_path}: table image has no row of camera {name}")
        if not out:
            raise NuPlanDataError(f"{db_path}: table image has no rows for the cameras {present}: the log has no image")
        return out

    def _phase(self, t_pc: np.ndarray, t_img: np.ndarray) -> int:
        """Which of the ``frame_step`` interleaved lidar_pc sequences lies nearest the images
        (median time to the nearest image; the earliest phase on ties)."""
        step = self.config.frame_step
        costs = [float(np.median(np.abs(t_img[nearest_index(t_img, t_pc[p::step])] - t_pc[p::step])))
                 if len(t_pc[p::step]) else np.inf for p in range(step)]
        return int(np.argmin(costs))

    # -- sensors -------------------------------------------------------------------------------
    def _camera(self, name: str, imgs: list[Row], cameras: dict[str, Row], ego_of, world: np.ndarray, blobs: Path,
                db_path: Path) -> CameraSequence:
        cal = [lookup(cameras, r, "camera_token", "camera") for r in imgs]
        first = cal[0]
        K0 = first.pickled("intrinsic", (3, 3))
        dist = first.pickled("distortion", (5,))
        if K0[2, 2] != 1 or K0[1, 0] != 0 or K0[2, 0] != 0 or K0[2, 1] != 0 or K0[0, 0] <= 0 or K0[1, 1] <= 0:
            raise first.error("intrinsic", "a pinhole K [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
        for c in {r.token: r for r in cal}.values():
            if not (np.array_equal(c.pickled("intrinsic", (3, 3)), K0) and np.array_equal(c.pickled("distortion", (5,)), dist)):
                raise NuPlanDataError(f"{db_path}: table camera rows {first.token} and {c.token} of {name} differ in "
                                      "intrinsic/distortion within the loaded frames; one calibration per camera is "
                                      "supported (choose frames with --start-frame/--end-frame)")
        size = []
        for col in ("width", "height"):
            v = first.number(col)
            if v <= 0 or v != int(v):
                raise first.error(col, "a positive whole number of pixels")
            size.append(int(v))
        width, height = size
        paths = [blobs / r.text("filename_jpg") for r in imgs]
        require_files(paths, f"image blob of {name} (table image, column filename_jpg; is --sensor-blobs the nuPlan "
                      "sensor_blobs folder?)", NuPlanFileMissing)
        w_disk, h_disk = image_size(paths[0])
        if (w_disk, h_disk) != (width, height):
            raise NuPlanDataError(f"{paths[0]}: image is {w_disk}x{h_disk}, but table camera row {first.token} says "
                                  f"width x height = {width}x{height}")
        c2e = {c.token: pose(c.pickled("translation", (3,)), c.pickled("rotation", (4,)), c, "rotation") for c in cal}
        c2w = np.stack([world @ ego_of(r) @ c2e[c.token] for r, c in zip(imgs, cal)])  # (F, 4, 4) OpenCV cam -> world
        # K centres pixels at integer coordinates (module docstring): +0.5 px, then the scale.
        return loaded_camera(name, paths, K0, (width, height), self.config.scale, "integer", cam_to_world=c2w,
                             timestamps=np.array([r.integer("timestamp") for r in imgs], dtype=np.int64) * 1e-6,
                             distortion=dist if np.any(dist != 0) else None,
                             extras={"image_token": np.array([r.token for r in imgs])})

    def _lidar(self, db: LogDatabase, frame_pcs: list[Row], ego_frames: np.ndarray, world: np.ndarray,
               blobs: Path) -> LidarSweeps:
        """The merged sweeps in the world; the top LiDAR's rings as beams with its measured
        beam model (omnire_nuplan/lidars.py), or no beams and one warning saying why."""
        cfg = self.config
        lidars = index(db.rows("lidar"))
        to_ego: dict[str, np.ndarray] = {}
        points: list[Optional[np.ndarray]] = []
        intensity: list[Optional[np.ndarray]] = []
        ids: list[Optional[tuple[np.ndarray, np.ndarray]]] = []  # thinned (ring, lidar_info) per sweep
        ring_count = 0  # of the top LiDAR: its largest ring over every loaded blob + 1
        estimate: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # sweeps spread over the log, not thinned
        measured = set(np.linspace(0, len(frame_pcs) - 1, ESTIMATE_SWEEPS).round().astype(int).tolist())
        sensor_to_world = np.full((len(frame_pcs), 4, 4), np.nan)
        missing = []
        lacking_ids: Optional[Path] = None
        model_name = "nuPlan top LiDAR"
        for j, pc in enumerate(frame_pcs):
            path = blobs / pc.text("filename")
            if not path.is_file():  # a sweep not downloaded: a gap
                points.append(None)
                intensity.append(None)
                ids.append(None)
                missing.append(path)
                continue
            rec = read_points(path)
            xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)  # (N, 3) LiDAR frame
            if not np.isfinite(xyz).all():
                raise NuPlanDataError(f"{path}: non-finite x, y, z values (table lidar_pc row {pc.token})")
            has_value = rec.dtype.names is not None and "intensity" in rec.dtype.names
            keep = thin_points(np.arange(len(xyz)), cfg.max_lidar_points_per_frame, pc.integer("timestamp"))  # keyed by the sweep
            ring_lidar = ring_and_lidar(rec, path)
            if ring_lidar is None:
                lacking_ids = lacking_ids or path
                ids.append(None)
            else:
                ring_count = max(ring_count, top_ring_count(*ring_lidar))
                if j in measured:
                    estimate.append((xyz, *ring_lidar))
                ids.append((ring_lidar[0][keep], ring_lidar[1][keep]))
            intensity.append(BYTE_INTENSITY.to_unit(rec["intensity"], f"{path}: field intensity", NuPlanDataError)[keep]
                             if has_value else None)
            lidar = lookup(lidars, pc, "lidar_token", "lidar")
            if lidar.token not in to_ego:
                to_ego[lidar.token] = pose(lidar.pickled("translation", (3,)), lidar.pickled("rotation", (4,)),
                                           lidar, "rotation")
                listed = lidar.values["model"] if "model" in lidar.values.keys() else None  # "the lidar model" (schema)
                if isinstance(listed, str) and listed:
                    model_name = f"nuPlan top LiDAR ({listed})"
            M = world @ ego_frames[j] @ to_ego[lidar.token]  # (4, 4) LiDAR -> world
            points.append((xyz[keep] @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
            sensor_to_world[j] = M
        if len(missing) == len(frame_pcs):
            raise NuPlanFileMissing(f"{missing[0]}: none of the {len(frame_pcs)} LiDAR blobs of the loaded frames exists "
                                    "(table lidar_pc column filename; is --sensor-blobs right?); --no-load-lidar "
                                    "skips LiDAR")
        # Intensity 0-255 / 255; all sweeps or none carry it.
        carried = all(v is not None for v, p in zip(intensity, points) if p is not None)
        if lacking_ids is not None:
            model, why = None, f"{lacking_ids} has no ring and lidar_info fields"
        else:
            model, why = top_beam_model(estimate, ring_count, model_name)
        beams = None
        if model is None:
            warnings.warn(f"{db.path}: the nuPlan sweeps carry no beams (no ray-drop targets): {why}", stacklevel=2)
        else:
            beams = [None if i is None else beams_of(*i) for i in ids]
        return LidarSweeps(points=points, origins=sensor_to_world[:, :3, 3].copy(),
                           intensity=intensity if carried else None,
                           sensor_to_world=sensor_to_world, beams=beams, beam_model=model)

    def _tracks(self, db: LogDatabase, frame_pcs: list[Row], frame_us: np.ndarray,
                world: np.ndarray) -> list[ActorTrack]:
        """One track per track token with a box on a loaded frame's lidar_pc; frames between
        its boxes at most ``max_track_gap`` apart are interpolated, other frames absent."""
        cfg = self.config
        frame_of = {pc.token: j for j, pc in enumerate(frame_pcs)}
        boxes = db.rows_with("lidar_box", "lidar_pc_token", raw_tokens(frame_pcs))
        tracks = index(db.rows_with("track", "token", raw_tokens(boxes, "track_token")))
        categories = index(db.rows("category"))
        groups: dict[str, list[Row]] = {}
        for b in boxes:
            groups.setdefault(b.ref("track_token"), []).append(b)
        out = []
        for track_token, rows in sorted(groups.items()):
            track = lookup(tracks, rows[0], "track_token", "track")
            name = lookup(categories, track, "category_token", "category").text("name")
            rows.sort(key=lambda b: frame_of[b.ref("lidar_pc_token")])
            frames = np.array([frame_of[b.ref("lidar_pc_token")] for b in rows])
            if np.any(np.diff(frames) == 0):
                k = int(np.flatnonzero(np.diff(frames) == 0)[0])
                raise NuPlanDataError(f"{db.path}: table lidar_box has two boxes of track {track_token} on "
                                      f"lidar_pc {frame_pcs[frames[k]].token} (rows {rows[k].token} and "
                                      f"{rows[k + 1].token})")
            sizes = []
            for b in rows:
                wlh = [b.number("width"), b.number("length"), b.number("height")]
                if min(wlh) <= 0:
                    raise b.error("width" if wlh[0] <= 0 else "length" if wlh[1] <= 0 else "height",
                                  "a positive size in metres")
                sizes.append(wlh)
            boxes = world[None] @ np.stack([box_to_global(b) for b in rows])  # (K, 4, 4) box -> world
            poses, present = resample_track(frame_us[frames].astype(np.float64), boxes, frame_us.astype(np.float64),
                                            cfg.max_track_gap * 1e6)
            out.append(ActorTrack(
                track_id=track_token,
                class_name=name,
                category=category_of(name),
                poses=poses,
                size=np.asarray(sizes)[:, [1, 0, 2]].max(axis=0),  # (width, length, height) -> (length, width, height)
                present=present,
                stationary=is_stationary(poses[present, :3, 3], cfg.stationary_threshold),
                extras={"box_tokens": [b.token for b in rows]},
            ))
        return out


@dataclasses.dataclass
class NuPlanConfig(LogDataparserConfig):
    """One nuPlan log: its SQLite database and sensor blobs, read without the devkit."""

    _target: Type = dataclasses.field(default_factory=lambda: NuPlanDataparser)
    data: Path = Path("data/nuplan")
    """The log's database (nuplan-v1.1/splits/<split>/<log>.db), or a folder holding exactly one .db."""
    sensor_blobs: Optional[Path] = None
    """Folder of the sensor blobs (<log>/CAM_F0/*.jpg, <log>/MergedPointCloud/*.pcd); default: nuplan-v1.1/sensor_blobs beside splits/ (or a sensor_blobs folder beside the database)."""
    cameras: tuple[str, ...] = ()
    """Cameras to load: any of CAM_F0, CAM_L0, CAM_R0, CAM_L1, CAM_R1, CAM_L2, CAM_R2, CAM_B0; empty loads all eight (those present)."""
    frame_step: int = 2
    """Take every N-th lidar_pc (20 Hz) as a frame: 2 gives the paper's 10 Hz (the camera rate), 1 every sweep."""
    max_camera_offset: float = 0.05
    """A camera's image must lie within this many seconds of its frame's lidar_pc (the devkit's matching window)."""
    max_track_gap: float = 0.0
    """Interpolate a track across frames without its box when the boxes around them are at most this many seconds apart; 0 (nuPlan boxes every lidar_pc, so every frame has its own) leaves the actor absent there, as the reference's preprocessing does."""
