"""Grasping: parallel-jaw gripper, antipodal grasp sampling, grasp experiments (squeeze ramp, pickup,
reorientation, accelerations), performance metrics and grasp features."""

from .gripper import FRANKA_HAND, Box, ContactFace, ParallelJawGripper, finger_closing_distances
from .sampler import GraspSet, grasp_frames, sample_antipodal_grasps

__all__ = [
    "FRANKA_HAND",
    "Box",
    "ContactFace",
    "GraspSet",
    "ParallelJawGripper",
    "finger_closing_distances",
    "grasp_frames",
    "sample_antipodal_grasps",
]
