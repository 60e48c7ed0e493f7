from omnire_pose_mediapipe.ik import landmarks_to_smpl

__all__ = ["landmarks_to_smpl"]
