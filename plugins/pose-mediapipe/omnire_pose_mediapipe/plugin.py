"""Entry point (``omnire`` group, name ``pose_mediapipe``): the MediaPipe pose estimator, imported on use."""
from omnire.api import PoseEstimatorSpec, lazy

SPECS = (PoseEstimatorSpec(
    "mediapipe", "MediaPipe Pose landmarks on crops of the projected pedestrian boxes + IK to SMPL rotations "
    "(offline; needs mediapipe 0.10.x)", lazy("omnire_pose_mediapipe.estimator:MediapipeEstimator"),
    lazy("omnire_pose_mediapipe.estimator:available"), priority=10),)
