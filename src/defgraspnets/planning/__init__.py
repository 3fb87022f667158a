"""Grasp planning with DefGraspNets (thesis §7.5, §7.7): differentiable objectives, batched scoring of
sampled grasps, gradient-based pose refinement, and verification in the FEM simulator."""

from .objectives import OBJECTIVE_TERMS, PRESETS, GraspObjective, smooth_max
from .planner import GraspEvaluation, GraspPlanner, RefinementResult, gripper_finger_geometry
from .pose import perturb_pose, rotation_exp
from .verify import GraspPoses, SimulatedGrasps, simulate_grasps, threshold_hits

__all__ = [
    "OBJECTIVE_TERMS",
    "PRESETS",
    "GraspEvaluation",
    "GraspObjective",
    "GraspPlanner",
    "GraspPoses",
    "RefinementResult",
    "SimulatedGrasps",
    "gripper_finger_geometry",
    "perturb_pose",
    "rotation_exp",
    "simulate_grasps",
    "smooth_max",
    "threshold_hits",
]
