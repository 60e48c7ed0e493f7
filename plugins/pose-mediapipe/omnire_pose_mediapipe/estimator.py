"""MediaPipe Pose (legacy ``solutions.pose``, full model shipped inside the 0.10.x wheel) on
crops around the projected pedestrian boxes, lifted to SMPL rotations by :mod:`.ik`.

MediaPipe Pose finds one person per image, so each region hint (a projected 3D box,
enlarged) is cropped from the full-resolution image and processed alone; the detections
of one region over the frames form one tracklet, whose 2D boxes are the extent of the
visible landmarks (the pipeline's IoU matching then rejects crops that caught someone
else). World landmarks are camera-aligned (x right, y down, z away from the camera), so
the solved global orientation is taken as camera-frame; the small rotation between an
off-centre crop's viewing ray and the optical axis is ignored.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Optional

import numpy as np

from omnire.data.images import image_size, read_image
from omnire_body.humanpose import HumanTracklet
from omnire_pose_mediapipe.ik import landmarks_to_smpl

TORSO = (11, 12, 23, 24)


def available() -> tuple[bool, str]:
    try:
        from mediapipe.python.solutions import pose  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means unavailable; say why
        return False, (f"mediapipe legacy solutions not importable ({type(exc).__name__}: {exc}); install "
                       "mediapipe 0.10.x (its wheels ship the pose-landmark model), see the plugin README")
    return True, ""


@dataclasses.dataclass
class MediapipeEstimator:
    """Options: crop margin (fraction of the box size added on each side), minimum crop
    height in source pixels, minimum landmark visibility of the torso."""

    name: str = "mediapipe"
    margin: float = 0.3
    min_crop_height: int = 48
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
            from mediapipe.python.solutions import pose as mp_pose

            # model_complexity=1: the "full" model, the one shipped in the wheel (0 and 2 download).
            self._pose = mp_pose.Pose(static_image_mode=True, model_complexity=1, min_detection_confidence=0.5)
        return self._pose

    def estimate(self, scene, camera: int, rois: dict[int, list[tuple[Any, np.ndarray]]]) -> list[HumanTracklet]:
        cam = scene.cameras[camera]
        per_key: dict[Any, list] = {}
        for f in sorted(rois):
            path = cam.image_paths[f]
            W, H = image_size(path)
            sx, sy = W / cam.width, H / cam.height
            image = None
            for key, box in rois[f]:
                x0, y0, x1, y1 = box * [sx, sy, sx, sy]
                if y1 - y0 < self.min_crop_height:
                    continue
                mw, mh = self.margin * (x1 - x0) + 0.2 * (y1 - y0), self.margin * (y1 - y0)
                c0, r0 = int(max(0, x0 - mw)), int(max(0, y0 - mh))
                c1, r1 = int(min(W, x1 + mw)), int(min(H, y1 + mh))
                if image is None:
                    image = read_image(path, W, H)
                det = self._detect(image[r0:r1, c0:c1])
                if det is None:
                    continue
                uv, world = det
                bx = np.array([uv[:, 0].min() + c0, uv[:, 1].min() + r0, uv[:, 0].max() + c0, uv[:, 1].max() + r0])
                go, bp = landmarks_to_smpl(world, self.joints, self.parents)
                per_key.setdefault(key, []).append((f, bx / [sx, sy, sx, sy], go, bp))
        out = []
        for key, obs in per_key.items():
            out.append(HumanTracklet(camera, np.array([o[0] for o in obs]), np.stack([o[1] for o in obs]),
                                     np.stack([o[2] for o in obs]), np.stack([o[3] for o in obs]),
                                     np.zeros((len(obs), 0)), self.name, key))
        return out

    def _detect(self, crop: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(visible landmark pixels (K, 2) in the crop, world landmarks (33, 3)) or None."""
        if crop.size == 0:
            return None
        res = self._model().process(np.ascontiguousarray(crop))
        if res.pose_landmarks is None or res.pose_world_landmarks is None:
            return None
        lm = res.pose_landmarks.landmark
        vis = np.array([p.visibility for p in lm])
        if vis[list(TORSO)].min() < self.min_visibility:
            return None
        h, w = crop.shape[:2]
        uv = np.array([[p.x * w, p.y * h] for p, v in zip(lm, vis) if v >= self.min_visibility])
        world = np.array([[p.x, p.y, p.z] for p in res.pose_world_landmarks.landmark])
        return uv, world
