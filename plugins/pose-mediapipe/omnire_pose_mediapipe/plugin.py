from omnire.api import PoseEstimatorSpec, hookimpl


def _available():
    from omnire_pose_mediapipe.estimator import available

    return available()


def _factory(**kw):
    from omnire_pose_mediapipe.estimator import MediapipeEstimator

    return MediapipeEstimator(**kw)


@hookimpl
def omnire_register_pose_estimators(registry) -> None:
    registry.register(PoseEstimatorSpec(
        "mediapipe", "MediaPipe Pose landmarks on crops of the projected pedestrian boxes + IK to SMPL rotations "
        "(offline; needs mediapipe 0.10.x)", _factory, _available, priority=10))
