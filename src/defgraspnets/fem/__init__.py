"""Quasi-static finite elements in NVIDIA Warp: the one physics engine of defgraspnets."""

from .mesh import MeshError, TetMesh

__all__ = ["MeshError", "TetMesh"]
