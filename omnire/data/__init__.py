"""Scene data model shared by every dataparser and every node type."""
from omnire.data.scene import (
    ActorTrack,
    CameraSequence,
    HumanPoseSequence,
    LidarSweeps,
    SceneData,
    SceneDataError,
    View,
    holdout_split,
)

__all__ = [
    "ActorTrack",
    "CameraSequence",
    "HumanPoseSequence",
    "LidarSweeps",
    "SceneData",
    "SceneDataError",
    "View",
    "holdout_split",
]
