"""Quasi-static finite elements in NVIDIA Warp: the one physics engine of defgraspnets.

A deformable object (linear tetrahedra, fixed co-rotated elasticity) in frictional contact with
rigid bodies (planes, spheres, capsules, triangle meshes) that are fixed, displacement-controlled or
force-controlled along one axis, under body loads (gravity, d'Alembert loads of an accelerating
frame) and gas pressure in a cavity (fixed, or a closed isothermal gas), solved to equilibrium by
Newton's method for many problems at once, on CPU or CUDA.

Example::

    from defgraspnets import fem

    mesh = fem.TetMesh.box(size=(0.02, 0.02, 0.02), divisions=(4, 4, 4))
    bottom = fem.RigidBody("bottom", fem.Plane(point=(0, 0, 0), normal=(0, 0, 1)))
    top = fem.RigidBody("top", fem.Plane(point=(0, 0, 0.02), normal=(0, 0, -1)),
                        control=fem.Control.force(axis=(0, 0, -1)))
    solver = fem.QuasiStaticSolver(mesh, [bottom, top], fem.Material(1e5, 0.3, 1000.0))
    eq = solver.solve(targets={"top": 4.0})          # push the top plane down with 4 N
    eq.require_converged()
    print(eq.travel["top"], eq.von_mises.max())
"""

from .bodies import BodyError, Capsule, Control, Plane, RigidBody, RoundedBox, Sphere, TriangleMesh
from .loads import STANDARD_GRAVITY, BodyLoad
from .material import MATERIAL_MODELS, Material, MaterialError
from .mesh import MeshError, TetMesh
from .pressure import STANDARD_ATMOSPHERE, PressureLoad, PressureSurface
from .results import Equilibrium, SolveStatus
from .solver import QuasiStaticSolver, SolverOptions

__all__ = [
    "BodyError",
    "BodyLoad",
    "Capsule",
    "Control",
    "Equilibrium",
    "MATERIAL_MODELS",
    "Material",
    "MaterialError",
    "MeshError",
    "Plane",
    "PressureLoad",
    "PressureSurface",
    "QuasiStaticSolver",
    "RigidBody",
    "RoundedBox",
    "STANDARD_ATMOSPHERE",
    "STANDARD_GRAVITY",
    "SolveStatus",
    "SolverOptions",
    "Sphere",
    "TetMesh",
    "TriangleMesh",
]
