"""Grasp planning with DefGraspNets: differentiable objectives, batched scoring, gradient refinement."""
