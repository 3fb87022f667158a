"""Parallel-jaw gripper, antipodal grasp sampling, grasp experiments (squeeze ramp, pickup, reorientation, accelerations), performance metrics and grasp features."""
