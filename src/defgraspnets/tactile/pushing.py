"""Planar quasi-static pushing of an object on a table by a round pusher (for thesis §5.5).

Model (Lynch, Maekawa & Tanie 1992; Lee & Cutkosky 1991): the object slides on the table with
Coulomb friction ``mu_s`` under a uniform support pressure over its footprint, total normal
load ``N`` (its weight). Its *limit surface* — the set of friction wrenches ``w = (f_x, f_y, m)``
(object frame, about the footprint centroid) the table can apply while the object slides — is
approximated by the ellipsoid

    H(w) = (f_x^2 + f_y^2) / f_max^2 + m^2 / m_max^2 = 1,   f_max = mu_s N,   m_max = c f_max,

with the characteristic length ``c = m_max / f_max = (1/A) int_A |r| dA`` (mean distance of the
footprint from its centroid; ``2R/3`` for a disc). Quasi-statically the pusher wrench lies on
the limit surface and the object twist ``V = (v_x, v_y, omega)`` is normal to it:
``V ∝ grad H ∝ (f_x, f_y, m / c^2)``. A point contact at ``r_c = (x_c, y_c)`` with inward
normal ``n`` transmits forces in the friction cone ``f = n + s mu_c t``, ``|s| <= 1``
(pusher-object friction ``mu_c``); the object's contact point then moves with

    v_c(f) = (V_x - omega y_c, V_y + omega x_c),   V(f) = (f_x, f_y, (x_c f_y - y_c f_x) / c^2).

The images of the friction-cone edges ``f_l = n + mu_c t`` and ``f_r = n - mu_c t`` bound the
*motion cone*. If the pusher velocity ``v_p = a v_c(f_l) + b v_c(f_r)`` with ``a, b >= 0`` the
contact sticks and ``V = a V(f_l) + b V(f_r)`` (this reproduces Lynch's closed form
``v_x = ((c^2 + x_c^2) v_px + x_c y_c v_py) / (c^2 + x_c^2 + y_c^2)`` etc.); otherwise it slides
on the nearer edge, scaled so the normal velocities agree: ``V = (v_p.n / v_c(f_e).n) V(f_e)``.
If the pusher moves away from the contact, the object stays.

Shapes are footprints in the object frame (centroid at the origin): a :class:`Capsule` (a
stadium: segment along x of half-length ``L`` swept by radius ``r``; a disc for ``L = 0``) and
a :class:`Rectangle` (the prism). The pusher is a disc of radius ``r_p`` (the palm's section at
the contact height). Motion is integrated in small pusher substeps with the exact SE(2)
exponential; residual penetration is removed by shifting the object along the contact normal.

Not modelled: dynamics, pusher-pressing-from-above (twisting an object under the palm),
walls/corridors, tipping or rolling.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np

__all__ = [
    "Capsule",
    "PushResult",
    "PushingModel",
    "Rectangle",
    "characteristic_length",
    "contact_twist",
    "push",
]

_EPS = 1e-12


@dataclass(frozen=True)
class Capsule:
    """Stadium footprint: points within ``radius`` of the segment ``[-L, L] x {0}``, L = half_length [m]."""

    radius: float
    half_length: float = 0.0

    def __post_init__(self):
        if not self.radius > 0 or not self.half_length >= 0:
            raise ValueError(
                f"capsule needs radius > 0 and half_length >= 0 m, got {self.radius}, {self.half_length}"
            )

    @property
    def extent(self) -> tuple[float, float]:
        return self.half_length + self.radius, self.radius

    def closest_boundary(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boundary point, outward unit normal and signed distance of points q (..., 2), object frame."""
        s = np.stack([np.clip(q[..., 0], -self.half_length, self.half_length), np.zeros(q.shape[:-1])], -1)
        v = q - s
        dist = np.linalg.norm(v, axis=-1)
        normal = np.where(dist[..., None] > _EPS, v / np.maximum(dist, _EPS)[..., None], [0.0, 1.0])
        return s + self.radius * normal, normal, dist - self.radius


@dataclass(frozen=True)
class Rectangle:
    """Rectangular footprint ``[-half_length, half_length] x [-half_width, half_width]`` [m]."""

    half_length: float
    half_width: float

    def __post_init__(self):
        if not self.half_length > 0 or not self.half_width > 0:
            raise ValueError(
                f"rectangle half extents must be > 0 m, got {self.half_length}, {self.half_width}"
            )

    @property
    def extent(self) -> tuple[float, float]:
        return self.half_length, self.half_width

    def closest_boundary(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boundary point, outward unit normal and signed distance of points q (..., 2), object frame."""
        h = np.array([self.half_length, self.half_width])
        d = np.abs(q) - h
        outside = (d > 0).any(axis=-1)
        # outside: the clamped point; the normal points from it to q (corner-aware)
        clamped = np.clip(q, -h, h)
        v = q - clamped
        dist_out = np.linalg.norm(v, axis=-1)
        n_out = v / np.maximum(dist_out, _EPS)[..., None]
        # inside: project onto the nearest edge
        axis = np.argmax(d, axis=-1)  # the edge with the smallest inward distance
        sign = np.where(np.take_along_axis(q, axis[..., None], -1)[..., 0] >= 0, 1.0, -1.0)
        n_in = np.zeros(q.shape)
        np.put_along_axis(n_in, axis[..., None], sign[..., None], -1)
        p_in = q.copy()
        np.put_along_axis(p_in, axis[..., None], (sign * h[axis])[..., None], -1)
        dist_in = np.max(d, axis=-1)
        point = np.where(outside[..., None], clamped, p_in)
        normal = np.where(outside[..., None], n_out, n_in)
        return point, normal, np.where(outside, dist_out, dist_in)


Shape = Capsule | Rectangle


def characteristic_length(shape: Shape, resolution: int = 400) -> float:
    """``c = (1/A) int_A |r| dA`` [m] for uniform pressure over the footprint (midpoint-rule grid)."""
    if resolution < 10:
        raise ValueError(f"resolution must be >= 10, got {resolution}")
    ex, ey = shape.extent
    gx = (np.arange(resolution) + 0.5) / resolution * 2 * ex - ex
    gy = (np.arange(resolution) + 0.5) / resolution * 2 * ey - ey
    pts = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    inside = shape.closest_boundary(pts)[2] <= 0
    return float(np.linalg.norm(pts[inside], axis=1).mean())


def _perp(v: np.ndarray) -> np.ndarray:
    return np.array([-v[1], v[0]])


def _twist_of_force(force: np.ndarray, point: np.ndarray, c: float) -> np.ndarray:
    """Object twist direction ``(f_x, f_y, (x_c f_y - y_c f_x) / c^2)`` for a contact force (object frame)."""
    return np.array([force[0], force[1], (point[0] * force[1] - point[1] * force[0]) / c**2])


def _contact_velocity(twist: np.ndarray, point: np.ndarray) -> np.ndarray:
    return np.array([twist[0] - twist[2] * point[1], twist[1] + twist[2] * point[0]])


def contact_twist(
    contact_point, inward_normal, pusher_velocity, characteristic_length: float, pusher_friction: float
) -> tuple[np.ndarray, Literal["sticking", "sliding", "separating"]]:
    """Object twist ``(v_x, v_y, omega)`` [m/s, m/s, rad/s] in the object frame for a pusher point contact.

    Args:
        contact_point: (2,) contact location relative to the footprint centroid [m].
        inward_normal: (2,) unit normal pointing into the object.
        pusher_velocity: (2,) pusher velocity at the contact [m/s].
        characteristic_length: ``c`` [m] of the ellipsoidal limit surface.
        pusher_friction: ``mu_c`` >= 0.
    """
    r = np.asarray(contact_point, dtype=np.float64)
    n = np.asarray(inward_normal, dtype=np.float64)
    vp = np.asarray(pusher_velocity, dtype=np.float64)
    c = float(characteristic_length)
    if r.shape != (2,) or n.shape != (2,) or vp.shape != (2,):
        raise ValueError("contact_point, inward_normal and pusher_velocity must be 2-vectors")
    if not np.isfinite(np.concatenate([r, n, vp])).all():
        raise ValueError("contact quantities must be finite")
    if not c > 0:
        raise ValueError(f"characteristic length must be > 0 m, got {c}")
    if not pusher_friction >= 0:
        raise ValueError(f"pusher_friction must be >= 0, got {pusher_friction}")
    n = n / np.linalg.norm(n)
    vn = float(vp @ n)
    if vn <= 0:
        return np.zeros(3), "separating"
    t = _perp(n)
    edges = [n + pusher_friction * t, n - pusher_friction * t]
    twists = [_twist_of_force(f, r, c) for f in edges]
    cone = np.column_stack([_contact_velocity(tw, r) for tw in twists])
    det = np.linalg.det(cone)
    if abs(det) > 1e-12 * np.linalg.norm(cone) ** 2:
        a, b = np.linalg.solve(cone, vp)
        if a >= 0 and b >= 0:
            return a * twists[0] + b * twists[1], "sticking"
        edge = 1 if a < 0 else 0
        mode = "sliding"
    else:  # frictionless contact: the motion cone is a single ray
        edge, mode = 0, "sliding"
    v_edge = _contact_velocity(twists[edge], r)
    vn_edge = float(v_edge @ n)
    if vn_edge <= 0:
        raise RuntimeError("motion-cone edge has no normal velocity; contact geometry is degenerate")
    return (vn / vn_edge) * twists[edge], mode


def _se2_step(pose: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Apply the body-frame twist for unit time with the SE(2) exponential."""
    x, y, th = pose
    vx, vy, w = twist
    if abs(w) < 1e-12:
        dx, dy = vx, vy
    else:
        s, cw = np.sin(w), np.cos(w)
        dx = (s * vx - (1 - cw) * vy) / w
        dy = ((1 - cw) * vx + s * vy) / w
    c, s = np.cos(th), np.sin(th)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, th + w])


@dataclass(frozen=True)
class PushingModel:
    """An object on a table and a round pusher.

    Attributes:
        shape: object footprint (object frame, centroid at the origin).
        pusher_radius: ``r_p`` [m].
        pusher_friction: ``mu_c`` between pusher and object.
        support_friction: ``mu_s`` between object and table.
        normal_force: support load ``N`` [N] (the weight ``m g``).
        characteristic_length: ``c`` [m]; computed for uniform pressure over the footprint if None.
    """

    shape: Shape
    pusher_radius: float
    pusher_friction: float = 0.3
    support_friction: float = 0.3
    normal_force: float = 1.0
    characteristic_length: float | None = field(default=None)

    def __post_init__(self):
        if not self.pusher_radius > 0:
            raise ValueError(f"pusher_radius must be > 0 m, got {self.pusher_radius}")
        if not self.pusher_friction >= 0 or not self.support_friction > 0:
            raise ValueError("need pusher_friction >= 0 and support_friction > 0")
        if not self.normal_force > 0:
            raise ValueError(f"normal_force must be > 0 N, got {self.normal_force}")
        if self.characteristic_length is not None and not self.characteristic_length > 0:
            raise ValueError(f"characteristic_length must be > 0 m, got {self.characteristic_length}")

    @cached_property
    def c(self) -> float:
        """Characteristic length of the limit surface [m]."""
        return self.characteristic_length or characteristic_length(self.shape)

    @property
    def max_friction_force(self) -> float:
        """``f_max = mu_s N`` [N]."""
        return self.support_friction * self.normal_force

    def friction_wrench(self, twist) -> np.ndarray:
        """Pusher wrench (object frame) on the limit surface that gives the non-zero ``twist``."""
        v = np.asarray(twist, dtype=np.float64)
        scale = np.abs(v).max()
        if not scale > 0:
            raise ValueError("zero twist: the pusher wrench is not determined")
        v = v / scale  # the wrench depends only on the twist direction
        fm = self.max_friction_force
        mm = self.c * fm
        w = np.array([fm**2 * v[0], fm**2 * v[1], mm**2 * v[2]])
        norm = np.sqrt(fm**2 * (v[0] ** 2 + v[1] ** 2) + mm**2 * v[2] ** 2)
        return w / norm


@dataclass(frozen=True)
class PushResult:
    """State after :func:`push`.

    Attributes:
        object_pose: (x, y, theta) [m, m, rad], world.
        pusher_center: (2,) [m], world.
        in_contact: whether the pusher touched the object during the last substep.
        mode: contact mode of the last substep: "free", "sticking", "sliding" or "separating".
        contact_force: (2,) force of the pusher on the object [N], world (zero if not pushing).
    """

    object_pose: np.ndarray
    pusher_center: np.ndarray
    in_contact: bool
    mode: str
    contact_force: np.ndarray


def _rot(th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s], [s, c]])


def push(
    model: PushingModel, object_pose, pusher_center, pusher_displacement, max_substep: float = 5e-4
) -> PushResult:
    """Move the pusher by ``pusher_displacement`` [m] (world) and return the quasi-static object motion.

    The displacement is split into substeps of at most ``max_substep`` [m]; in each the pusher
    first travels freely up to contact, then the remainder pushes the object (:func:`contact_twist`).
    """
    pose = np.asarray(object_pose, dtype=np.float64).copy()
    q = np.asarray(pusher_center, dtype=np.float64).copy()
    d = np.asarray(pusher_displacement, dtype=np.float64)
    if pose.shape != (3,) or q.shape != (2,) or d.shape != (2,):
        raise ValueError("object_pose must be (3,), pusher_center and pusher_displacement (2,)")
    if not np.isfinite(np.concatenate([pose, q, d])).all():
        raise ValueError("push inputs must be finite")
    if not max_substep > 0:
        raise ValueError(f"max_substep must be > 0 m, got {max_substep}")

    def contact(pose, q):
        rot = _rot(pose[2])
        local = rot.T @ (q - pose[:2])
        point, normal, sd = model.shape.closest_boundary(local)
        return rot, point, normal, float(sd) - model.pusher_radius

    rot, _, _, gap0 = contact(pose, q)
    if gap0 < -1e-9:
        raise ValueError(f"pusher starts {-gap0:.3g} m inside the object")
    n_sub = max(1, int(np.ceil(np.linalg.norm(d) / max_substep)))
    step = d / n_sub
    mode, in_contact, force = "free", False, np.zeros(2)
    for _ in range(n_sub):
        rot, point, normal, gap = contact(pose, q)
        approach = -float((rot @ normal) @ step)  # speed toward the object along its normal
        remaining = step
        if gap > 0:
            if approach <= gap:
                q = q + step
                mode, in_contact, force = "free", False, np.zeros(2)
                continue
            frac = gap / approach
            q = q + frac * step
            remaining = (1.0 - frac) * step
            rot, point, normal, gap = contact(pose, q)
        in_contact = True
        twist, mode = contact_twist(point, -normal, rot.T @ remaining, model.c, model.pusher_friction)
        if mode == "separating" or not np.abs(twist).max() > 0:
            force = np.zeros(2)
        else:
            force = rot @ model.friction_wrench(twist)[:2]
            pose = _se2_step(pose, twist)
        q = q + remaining
        rot, point, normal, gap = contact(pose, q)
        if gap < 0:  # remove the discretization's residual penetration
            pose[:2] += gap * (rot @ normal)
    return PushResult(pose, q, in_contact, mode, force)
