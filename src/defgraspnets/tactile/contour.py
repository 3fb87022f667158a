"""Tactile contour following (thesis ch. 4, eqs 4.1-4.6).

A three-term discrete-time controller moves the end effector (the sensor frame, pose
``(p, R)`` in the world) along an object while regulating the contact force and keeping the
contact on the soft membrane:

    p(t+1) = K_v v_o(t) - K_f (F_des - F(t)) n_o(t) + p(t)                               (4.1)
    R(t+1) = Rot(omega(t), K_theta theta(t)) R(t)                                        (4.2)

    n_o = (n_r - (n_r . v_o) v_o) / || n_r - (n_r . v_o) v_o ||                           (4.3)
    omega = n_r x n_o                                                                     (4.4)
    theta = arccos(n_r . n_o)                                                             (4.5)

- ``v_o`` (object tangent) — **edge mode**: the normalized first principal component of the
  deformed point cloud; **surface mode**: the first principal component of the deformed points
  within ``plane_band`` (0.1 cm in the thesis) of the plane through their centroid with the
  user-chosen normal ``n_p``. Its sign is free; it is chosen to agree with a reference
  direction (the practitioner's convention, or the previous tangent).
- ``n_r`` — the unit sensor central axis. With eq. (4.1) as written, the force term moves the
  sensor along ``-n_o`` when ``F < F_des``, i.e. toward the object, so ``n_r`` points from the
  membrane back into the housing (away from the object): ``n_r = -R a`` for the approach axis
  ``a`` of the sensor frame (``a = +z``, the camera's optical axis, by default).
- ``F`` — a measured force [N] or the depth-only proxy ``F~`` of eq. (4.6)
  (:func:`defgraspnets.tactile.force_models.depth_force_proxy`); ``K_f`` converts its units to metres.
- Rotation is applied in the world frame about the *contact*: the centroid ``c`` of the deformed cloud
  (``rotation_pivot="contact"``, default), ``p(t+1) = c + Rot (p(t) - c) + Delta p_(4.1)``, so the contact
  moves by exactly the tracking and force terms of eq. (4.1) and the alignment term only turns the sensor
  over it. Rotating about the end-effector origin instead (``"origin"``) adds a swing of
  ``K_theta theta |c - p|`` at the contact that eq. (4.1) does not command: with the sensor's frame at the
  camera base, 0.18 m behind the membrane pole, a 32 deg turn of the edge at a shelf corner swung the
  membrane 26 mm into the side panel in one step (true force 2.2 -> 10.6 N) while ``K_v`` is 1 cm.

Before contact (fewer than ``min_contact_points`` deformed points) the controller moves
``K_v`` along a fixed ``search_direction`` with no rotation, as in §4.3.

The controller is a pure function of (deformed points in the sensor frame, sensor pose, force
measure, parameters) plus the tangent sign reference; :class:`ContourFollower` only carries
the previous tangent between steps. Closed-loop runs on the simulated membrane sensor (FEM)
are built on top of this module; the unit tests close the loop with a geometric contact model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from defgraspnets.fem.bodies import check_rigid_transform

__all__ = [
    "ContourCommand",
    "ContourFollower",
    "ContourParameters",
    "ContourRunMetrics",
    "alignment_rotation",
    "axis_angle_matrix",
    "contour_following_step",
    "contour_run_metrics",
    "object_normal",
    "object_tangent",
]

_EPS = 1e-12


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    n = np.linalg.norm(a)
    if n < _EPS:
        raise ValueError(f"{name} must be non-zero")
    return a / n


def _points(points, name: str = "deformed_points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains non-finite coordinates")
    return p


def _first_principal_component(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[0]


def axis_angle_matrix(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation matrix ``Rot(axis, angle)``; identity for a zero axis or angle."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if n < _EPS or abs(angle) < _EPS:
        return np.eye(3)
    k = a / n
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)


# ----------------------------------------------------------------------------- state quantities


def object_tangent(
    points_world,
    mode: Literal["edge", "surface"],
    plane_normal=None,
    plane_band: float = 1.0e-3,
    reference_direction=None,
) -> np.ndarray:
    """Object tangent ``v_o`` from the deformed cloud (world frame), §4.2.

    Edge mode: first principal component of all points. Surface mode: first principal
    component of the points within ``plane_band`` [m] of the plane through the centroid with
    normal ``plane_normal`` (``n_p``). The sign makes ``v_o . reference_direction >= 0``.

    Raises:
        ValueError: if fewer than 2 points are available for the principal component.
    """
    p = _points(points_world, "points_world")
    if mode == "edge":
        sel = p
    elif mode == "surface":
        if plane_normal is None:
            raise ValueError("surface mode needs the user plane normal n_p")
        n_p = _unit(plane_normal, "plane_normal")
        if not plane_band > 0:
            raise ValueError(f"plane_band must be > 0 m, got {plane_band}")
        sel = p[np.abs((p - p.mean(axis=0)) @ n_p) <= plane_band]
    else:
        raise ValueError(f"mode must be 'edge' or 'surface', got {mode!r}")
    if sel.shape[0] < 2:
        raise ValueError(f"{mode} mode: {sel.shape[0]} deformed point(s) selected, need at least 2")
    v = _first_principal_component(sel)
    if mode == "surface":
        v = v - (v @ n_p) * n_p  # the band has finite width; keep v_o in the motion plane
        v /= np.linalg.norm(v)
    if reference_direction is not None and v @ np.asarray(reference_direction, dtype=np.float64) < 0:
        v = -v
    return v


def object_normal(sensor_axis, tangent) -> np.ndarray:
    """Eq. (4.3): the normalized projection of the sensor axis ``n_r`` onto the plane normal to ``v_o``."""
    n_r = _unit(sensor_axis, "sensor_axis")
    v_o = _unit(tangent, "tangent")
    proj = n_r - (n_r @ v_o) * v_o
    norm = np.linalg.norm(proj)
    if norm < 1e-9:
        raise ValueError("sensor axis is parallel to the object tangent: n_o of eq. (4.3) is undefined")
    return proj / norm


def alignment_rotation(sensor_axis, normal) -> tuple[np.ndarray, float]:
    """Eqs (4.4)-(4.5): axis ``omega = n_r x n_o`` (unit, or zero) and angle ``theta = arccos(n_r . n_o)``."""
    n_r = _unit(sensor_axis, "sensor_axis")
    n_o = _unit(normal, "normal")
    omega = np.cross(n_r, n_o)
    theta = float(np.arccos(np.clip(n_r @ n_o, -1.0, 1.0)))
    norm = np.linalg.norm(omega)
    return (omega / norm if norm > _EPS else np.zeros(3)), theta


# ----------------------------------------------------------------------------- controller


@dataclass(frozen=True)
class ContourParameters:
    """Gains and settings of the contour-following controller.

    Attributes:
        tracking_step: ``K_v`` [m per step] (1 cm at 1 Hz in §4.3).
        force_gain: ``K_f`` [m per unit of the force measure].
        alignment_gain: ``K_theta`` in (0, 1].
        desired_force: ``F_des`` in the units of the force measure (N, or m for ``F~``).
        mode: "edge" or "surface".
        plane_normal: ``n_p`` (world), required in surface mode.
        plane_band: half-width of the slab around the motion plane [m] (0.1 cm in the thesis).
        approach_axis: sensor-frame axis pointing out through the membrane toward the object;
            ``n_r = -R approach_axis``.
        search_direction: world direction moved before contact.
        travel_direction: world direction fixing the sign of ``v_o`` when no previous tangent is known.
        min_contact_points: fewer deformed points than this means no contact.
        rotation_pivot: world point the alignment rotation of eq. (4.2) turns about: "contact" (the
            centroid of the deformed cloud; the contact then moves by exactly eq. 4.1's step) or
            "origin" (the end-effector origin, which also swings the contact by ``K_theta theta`` times
            its lever arm).
    """

    tracking_step: float
    force_gain: float
    alignment_gain: float
    desired_force: float
    mode: Literal["edge", "surface"] = "edge"
    plane_normal: tuple[float, float, float] | None = None
    plane_band: float = 1.0e-3
    approach_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    search_direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    travel_direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    min_contact_points: int = 10
    rotation_pivot: Literal["contact", "origin"] = "contact"

    def __post_init__(self):
        if not self.tracking_step > 0:
            raise ValueError(f"tracking_step K_v must be > 0 m, got {self.tracking_step}")
        if not self.force_gain >= 0:
            raise ValueError(f"force_gain K_f must be >= 0, got {self.force_gain}")
        if not 0 < self.alignment_gain <= 1:
            raise ValueError(f"alignment_gain K_theta must lie in (0, 1], got {self.alignment_gain}")
        if not np.isfinite(self.desired_force):
            raise ValueError(f"desired_force must be finite, got {self.desired_force}")
        if self.mode not in ("edge", "surface"):
            raise ValueError(f"mode must be 'edge' or 'surface', got {self.mode!r}")
        if self.mode == "surface" and self.plane_normal is None:
            raise ValueError("surface mode needs plane_normal n_p")
        if self.plane_normal is not None:
            _unit(self.plane_normal, "plane_normal")
        for name in ("approach_axis", "search_direction", "travel_direction"):
            _unit(getattr(self, name), name)
        if self.rotation_pivot not in ("contact", "origin"):
            raise ValueError(f"rotation_pivot must be 'contact' or 'origin', got {self.rotation_pivot!r}")
        if self.min_contact_points < 2:
            raise ValueError(f"min_contact_points must be >= 2, got {self.min_contact_points}")


@dataclass(frozen=True)
class ContourCommand:
    """Output of one controller step.

    Attributes:
        position: p(t+1) [m], world.
        rotation: R(t+1), world <- sensor.
        translation: p(t+1) - p(t) [m] (eq. 4.1's step plus, unless the rotation pivots about the
            end-effector origin, the origin's swing about the contact).
        rotation_vector: ``K_theta theta omega`` [rad], world frame (R(t+1) = exp([rv]x) R(t)).
        in_contact: whether the deformed cloud counted as contact.
        tangent, normal: ``v_o`` and ``n_o`` (world, NaN when not in contact).
        alignment_angle: ``theta`` [rad] (0 when not in contact).
    """

    position: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    rotation_vector: np.ndarray
    in_contact: bool
    tangent: np.ndarray
    normal: np.ndarray
    alignment_angle: float

    @property
    def pose(self) -> np.ndarray:
        """(4, 4) homogeneous world <- sensor transform at t + 1."""
        t = np.eye(4)
        t[:3, :3] = self.rotation
        t[:3, 3] = self.position
        return t


def contour_following_step(
    deformed_points,
    sensor_pose,
    force: float,
    params: ContourParameters,
    tangent_reference=None,
) -> ContourCommand:
    """One step of eqs (4.1)-(4.5).

    Args:
        deformed_points: (N, 3) deformed membrane points in the sensor frame [m].
        sensor_pose: (4, 4) world <- sensor transform at time t.
        force: current force measure F(t) (or ``F~`` of eq. 4.6).
        params: controller gains and settings.
        tangent_reference: world direction the tangent should agree with (the previous
            tangent); ``params.travel_direction`` when None.
    """
    pose = check_rigid_transform(sensor_pose, "sensor_pose", single=True)
    rot, pos = pose[:3, :3], pose[:3, 3]
    pts = _points(deformed_points)
    if not np.isfinite(force):
        raise ValueError(f"force measure must be finite, got {force}")
    nan3 = np.full(3, np.nan)
    if pts.shape[0] < params.min_contact_points:
        step = params.tracking_step * _unit(params.search_direction, "search_direction")
        return ContourCommand(pos + step, rot.copy(), step, np.zeros(3), False, nan3, nan3, 0.0)

    world = pts @ rot.T + pos
    ref = params.travel_direction if tangent_reference is None else tangent_reference
    v_o = object_tangent(world, params.mode, params.plane_normal, params.plane_band, ref)
    n_r = -(rot @ _unit(params.approach_axis, "approach_axis"))
    n_o = object_normal(n_r, v_o)
    omega, theta = alignment_rotation(n_r, n_o)

    step = params.tracking_step * v_o - params.force_gain * (params.desired_force - force) * n_o  # (4.1)
    rotvec = params.alignment_gain * theta * omega  # (4.2)
    turn = axis_angle_matrix(omega, params.alignment_gain * theta)
    pivot = world.mean(axis=0) if params.rotation_pivot == "contact" else pos
    new_pos = pivot + turn @ (pos - pivot) + step
    return ContourCommand(new_pos, turn @ rot, new_pos - pos, rotvec, True, v_o, n_o, theta)


@dataclass
class ContourFollower:
    """Stateful wrapper of :func:`contour_following_step` that keeps the tangent sign continuous.

    The previous tangent is the sign reference of the next one, so the sensor keeps travelling
    the same way along a curved edge; contact loss resets it to ``params.travel_direction``.
    """

    params: ContourParameters
    previous_tangent: np.ndarray | None = field(default=None)

    def reset(self) -> None:
        self.previous_tangent = None

    def step(self, deformed_points, sensor_pose, force: float) -> ContourCommand:
        cmd = contour_following_step(deformed_points, sensor_pose, force, self.params, self.previous_tangent)
        self.previous_tangent = cmd.tangent.copy() if cmd.in_contact else None
        return cmd


# ----------------------------------------------------------------------------- run metrics


@dataclass(frozen=True)
class ContourRunMetrics:
    """Summary of a logged contour-following run.

    Attributes:
        contact_fraction: fraction of steps in contact (after first contact if ``from_first_contact``).
        force_rms_error: RMS of ``F - F_des`` over in-contact steps (force units; NaN if none).
        path_length: sum of step lengths of the end-effector position [m].
        distance_along: net displacement along ``direction`` [m] (NaN if no direction given).
        housing_contact_steps: number of steps with contact on the rigid housing.
    """

    contact_fraction: float
    force_rms_error: float
    path_length: float
    distance_along: float
    housing_contact_steps: int


def contour_run_metrics(
    positions,
    in_contact,
    force,
    desired_force: float,
    housing_contact=None,
    direction=None,
    from_first_contact: bool = True,
) -> ContourRunMetrics:
    """Metrics of a logged trajectory of T steps.

    Args:
        positions: (T, 3) end-effector positions [m].
        in_contact: (T,) bool, membrane contact per step.
        force: (T,) force measure per step.
        desired_force: ``F_des``.
        housing_contact: (T,) bool, contact with the rigid housing per step (None: none logged).
        direction: world direction for :attr:`ContourRunMetrics.distance_along`.
        from_first_contact: count the contact fraction from the first contact step on (the
            approach phase is not a failure to keep contact).
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1:
        raise ValueError(f"positions must have shape (T, 3) with T >= 1, got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("positions contain non-finite values")
    t = p.shape[0]
    c = np.asarray(in_contact)
    f = np.asarray(force, dtype=np.float64)
    if c.shape != (t,) or c.dtype != np.bool_:
        raise ValueError(f"in_contact must be a boolean array of shape ({t},), got {c.shape} {c.dtype}")
    if f.shape != (t,):
        raise ValueError(f"force must have shape ({t},), got {f.shape}")
    if housing_contact is None:
        h = np.zeros(t, dtype=bool)
    else:
        h = np.asarray(housing_contact)
        if h.shape != (t,) or h.dtype != np.bool_:
            raise ValueError(f"housing_contact must be a boolean array of shape ({t},)")

    if from_first_contact and c.any():
        frac = float(c[np.argmax(c) :].mean())
    else:
        frac = float(c.mean())
    fc = f[c]
    if not np.isfinite(fc).all():
        raise ValueError("force is non-finite on in-contact steps")
    rms = float(np.sqrt(np.mean((fc - desired_force) ** 2))) if fc.size else np.nan
    path = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    along = np.nan if direction is None else float((p[-1] - p[0]) @ _unit(direction, "direction"))
    return ContourRunMetrics(frac, rms, path, along, int(h.sum()))
