"""Rigid bodies that touch the deformable object, and how they are driven.

A :class:`RigidBody` couples a *shape* (in its own shape frame) to a *pose* (shape frame -> object
frame, one per batched problem) and a *control* along one axis. The body's actual placement is its
pose translated by ``travel * axis_world`` where ``travel`` [m] is either

- fixed at zero (``Control.fixed()``),
- prescribed (``Control.displacement(axis)``: the solver is given the travel), or
- an unknown of the equilibrium solve (``Control.force(axis)``: the solver is given the total force
  the body pushes with along its axis, i.e. the sum over its contacts of the contact force the body
  exerts on the object projected on ``axis``; this is how the parallel-jaw fingers squeeze).

Bodies that name the same ``dof`` share one travel (a mimic joint, like the coupled fingers of a
parallel-jaw gripper); for a shared force-controlled dof the prescribed force is the total over all
of its bodies.

Shapes and their signed distance g (negative inside) in the shape frame:

- :class:`Plane`     g = z (the half-space z < 0 is solid; the normal +z points toward the object)
- :class:`Sphere`    g = |p| - r
- :class:`Capsule`   g = dist(p, segment [-h e_z, +h e_z]) - r
- :class:`RoundedBox` g = |max(q, 0)| + min(max_i q_i, 0) - r,  q = |p| - b (a box with rounded edges,
  e.g. a gripper finger pad: exact and C1 across the rounded edges)
- :class:`TriangleMesh`  closed, outward-oriented triangle mesh; g = signed distance to the surface
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Plane",
    "Sphere",
    "Capsule",
    "RoundedBox",
    "TriangleMesh",
    "Control",
    "RigidBody",
    "BodyError",
    "SHAPE_KIND",
]


class BodyError(ValueError):
    """Invalid rigid-body description."""


def _vec3(value, name) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise BodyError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


def _unit(value, name) -> np.ndarray:
    v = _vec3(value, name)
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise BodyError(f"{name} must be a non-zero vector")
    return v / n


def frame_from_z(origin, z_axis) -> np.ndarray:
    """A 4x4 rigid transform whose z axis is ``z_axis`` and whose origin is ``origin``."""
    z = _unit(z_axis, "z_axis")
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, _vec3(origin, "origin")
    return T


def check_rigid_transform(T, name="pose", single: bool = False) -> np.ndarray:
    """``T`` as float64 (..., 4, 4) after checking it holds finite rigid transforms (proper rotation,
    last row 0 0 0 1); ``single``: exactly one (4, 4) transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4) or (single and T.shape != (4, 4)) or not np.all(np.isfinite(T)):
        many = "a finite 4x4 rigid transform" if single else "finite 4x4 rigid transforms"
        raise BodyError(f"{name} must be {many}, got shape {T.shape}")
    R = T[..., :3, :3]
    err = np.abs(np.einsum("...ji,...jk->...ik", R, R) - np.eye(3)).max()
    if err > 1e-6 or np.any(np.linalg.det(R) < 0):
        raise BodyError(f"{name}: rotation part is not a proper rotation (|R^T R - I| = {err:.2g})")
    if np.any(np.abs(T[..., 3, :] - [0, 0, 0, 1]) > 1e-12):
        raise BodyError(f"{name}: last row must be [0, 0, 0, 1]")
    return T


@dataclass(frozen=True)
class Plane:
    """Infinite rigid plane through ``point`` whose unit ``normal`` points toward the object (free side)."""

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)

    def __post_init__(self):
        _vec3(self.point, "Plane point")
        _unit(self.normal, "Plane normal")

    def shape_frame(self) -> np.ndarray:
        return frame_from_z(self.point, self.normal)


@dataclass(frozen=True)
class Sphere:
    """Rigid sphere (e.g. an indenter) of ``radius`` [m] centred at ``center``."""

    radius: float
    center: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if not np.isfinite(self.radius) or self.radius <= 0:
            raise BodyError(f"Sphere radius must be > 0, got {self.radius!r}")

    def shape_frame(self) -> np.ndarray:
        return frame_from_z(self.center, (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class Capsule:
    """Rigid capsule: points within ``radius`` of the segment ``center +- half_length * direction``."""

    radius: float
    half_length: float
    center: tuple = (0.0, 0.0, 0.0)
    direction: tuple = (0.0, 0.0, 1.0)

    def __post_init__(self):
        if not np.isfinite(self.radius) or self.radius <= 0:
            raise BodyError(f"Capsule radius must be > 0, got {self.radius!r}")
        if not np.isfinite(self.half_length) or self.half_length < 0:
            raise BodyError(f"Capsule half_length must be >= 0, got {self.half_length!r}")

    def shape_frame(self) -> np.ndarray:
        return frame_from_z(self.center, self.direction)


@dataclass(frozen=True)
class RoundedBox:
    """Rigid box with rounded edges and corners: all points within ``radius`` of the inner box
    ``|p - center| <= half_extents - radius`` (axis-aligned in the body frame). ``half_extents`` are those
    of the outer, rounded box [m]; ``radius`` = 0 gives a sharp box."""

    half_extents: tuple
    radius: float = 0.0
    center: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        h = _vec3(self.half_extents, "RoundedBox half_extents")
        if not np.isfinite(self.radius) or self.radius < 0 or np.any(h <= 0) or np.any(h < self.radius):
            raise BodyError(
                f"RoundedBox needs half_extents > 0 and 0 <= radius <= min(half_extents), "
                f"got {tuple(h)} and {self.radius!r}"
            )
        object.__setattr__(self, "half_extents", tuple(h))

    @property
    def inner_half_extents(self) -> np.ndarray:
        return np.asarray(self.half_extents) - self.radius

    def shape_frame(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = _vec3(self.center, "RoundedBox center")
        return T

    def triangle_mesh(self, edge_length: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the surface in the body frame (for display and graphs)."""
        import trimesh

        h, r = np.asarray(self.half_extents), self.radius
        if r > 0:
            box = trimesh.creation.box(extents=2 * (h - r) + 1e-12)
            sphere = trimesh.creation.icosphere(subdivisions=2, radius=r)
            mesh = trimesh.convex.convex_hull(
                (box.vertices[:, None, :] + sphere.vertices[None, :, :]).reshape(-1, 3)
            )
        else:
            mesh = trimesh.creation.box(extents=2 * h)
        return np.asarray(mesh.vertices) + _vec3(self.center, "center"), np.asarray(mesh.faces)


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """Closed rigid triangle mesh (e.g. a gripper finger pad) with outward-oriented faces [m]."""

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise BodyError("TriangleMesh vertices must be a finite (V, 3) array")
        if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= len(v):
            raise BodyError("TriangleMesh faces must be a (F, 3) array of valid vertex indices")
        # closed and outward: every edge used twice in opposite directions, positive enclosed volume
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        fwd = {tuple(x) for x in e.tolist()}
        if len(fwd) != len(e) or any((b, a) not in fwd for a, b in fwd):
            raise BodyError(
                "TriangleMesh must be closed and consistently oriented (signed distance needs it)"
            )
        volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
        if volume <= 0:
            raise BodyError("TriangleMesh faces must be oriented outward (enclosed volume is negative)")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    def shape_frame(self) -> np.ndarray:
        return np.eye(4)


SHAPE_KIND = {Plane: 0, Sphere: 1, Capsule: 2, TriangleMesh: 3, RoundedBox: 4}


@dataclass(frozen=True)
class Control:
    """How a body moves along ``axis`` (a unit vector in the body's pose frame).

    ``mode``: "fixed", "displacement" (travel prescribed) or "force" (force along the axis prescribed).
    ``dof``: name of the travel degree of freedom; bodies naming the same dof share it.
    """

    mode: str = "fixed"
    axis: tuple = (0.0, 0.0, 1.0)
    dof: str | None = None

    def __post_init__(self):
        if self.mode not in ("fixed", "displacement", "force"):
            raise BodyError(f"Control mode must be 'fixed', 'displacement' or 'force', got {self.mode!r}")
        object.__setattr__(self, "axis", tuple(_unit(self.axis, "Control axis")))

    @classmethod
    def fixed(cls) -> Control:
        return cls("fixed")

    @classmethod
    def displacement(cls, axis, dof: str | None = None) -> Control:
        return cls("displacement", axis, dof)

    @classmethod
    def force(cls, axis, dof: str | None = None) -> Control:
        return cls("force", axis, dof)


@dataclass(frozen=True, eq=False)
class RigidBody:
    """A named rigid body: shape, control, Coulomb friction coefficient with the object."""

    name: str
    shape: Plane | Sphere | Capsule | RoundedBox | TriangleMesh
    control: Control = field(default_factory=Control.fixed)
    friction: float = 0.0

    def __post_init__(self):
        if type(self.shape) not in SHAPE_KIND:
            raise BodyError(f"body {self.name!r}: unsupported shape {type(self.shape).__name__}")
        if not np.isfinite(self.friction) or self.friction < 0:
            raise BodyError(f"body {self.name!r}: friction coefficient must be >= 0, got {self.friction!r}")

    @property
    def dof_name(self) -> str | None:
        if self.control.mode == "fixed":
            return None
        return self.control.dof or self.name
