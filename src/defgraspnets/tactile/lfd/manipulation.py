"""Mixed object manipulation by learning from demonstration in simulation (thesis §5.5).

Task (§5.5): starting above an object in a table quadrant, lower the palm onto it; if it is a *capsule*,
push it through a corridor and off the table edge; if it is the rectangular *prism*, rotate it in place
until its length is parallel to the table edge. Ten demonstrations of each subtask (eight capsules and
the prism), a 4-state HMM on ``o = [S, A]`` with the §5.3 input ``S = [c, lambda, e_1]`` (9-D, world
frame) and the 6-D end-effector twist ``A = [v, omega]``, and the GMRa policy (eqs 5.17-5.18) executed
from unseen starts.

World frame (SI): table top ``z = 0``, the table occupies ``y <= 0`` and its edge closest to the robot
is the line ``y = 0`` along x. The corridor is the free strip ``|x| <= w/2`` between two walls (boxes of
thickness ``t_w`` and height ``h_w``) running from ``y = -L_c`` to the edge. Objects are extrusions of
:mod:`defgraspnets.tactile.pushing` footprints (:class:`~defgraspnets.tactile.pushing.Capsule`,
:class:`~defgraspnets.tactile.pushing.Rectangle`) from ``z = 0`` to their height ``h``.

Sensing: every step the fast membrane model (:class:`~defgraspnets.tactile.contour_sim.TactileSimulation`)
touches the SDF of table + walls + object at its current pose; the depth camera and the contact-core test
give the deformed points and :func:`~defgraspnets.tactile.lfd.features.tactile_features` the input S.

Object motion (quasi-static, planar; the palm points straight down, its outer dome is a sphere of radius
``R`` whose lowest point, the pole, is at height ``z_p``):

- *flank contact* (the pole's xy lies outside the footprint): the palm pushes the object's top edge with
  its dome. In the plane of the object's top face lowered by the push indentation ``delta_p`` the dome is
  a disc of radius ``r_p = sqrt(R^2 - (z_p + R - (h - delta_p))^2)`` (0 if the dome is higher): the membrane
  has to be indented by ``delta_p`` before its force overcomes the table friction, so the rigid disc of
  :func:`~defgraspnets.tactile.pushing.push` is this section. The pusher's xy motion moves the object by the
  limit-surface pushing model; a disc that grows into the object when the palm is lowered shifts the
  object out along the contact normal (the wedge effect of a descending dome).
- *pressing* (the pole's xy lies over the footprint and the membrane touches the object with force
  ``F_n``): the object sticks to the palm and follows its planar motion (translation of the pole, yaw
  about it) when the palm-object friction can supply the table friction, i.e. for rotation
  ``mu_c F_n c_patch >= mu_s (m g + F_n) c_obj`` (ellipsoidal limit surfaces; ``c_patch`` is the mean
  distance of the membrane's contact columns from their centroid, ``c_obj`` the object's characteristic
  length); otherwise it stays.
- an object whose centroid crosses the table edge tips off and falls (it leaves the scene).

Walls are not an obstacle of the pushing model: an object footprint overlapping a wall is a *failure*
(the capsule left the corridor), not a contact.

Success (SI): capsule — it ends off the table (centroid ``y > 0``), it crossed the edge inside the corridor
(``|x| <= w/2``), and its footprint never overlapped a wall; prism — it is on the table at the end, its
yaw is within ``yaw_tolerance`` (default 5 deg) of the edge direction modulo pi, and its centroid moved
less than ``max_prism_shift`` (default 0.02 m: rotated *in place*). The rigid housing touching anything is a
failure of both.

Teachers are scripted controllers with privileged object poses (the thesis's kinesthetic teacher),
lowering at constant speed. Capsule (default ``capsule_approach="above"``, thesis Fig. 5.8: the palm
begins above the capsule and is lowered onto it): down until the membrane is indented ``delta_t``, then
drag the pressed capsule (it sticks to the palm) along the desired heading ``d = (-k_x x_o, 1)`` toward
the corridor axis (``x_o`` the object's offset) at that indentation, then retract upward after it fell.
The alternative ``"behind"`` starts behind the capsule, lowers to the push height (the dome's flank meets
the object's top edge on the way) and pushes at that height along ``u + k_u (u - d)`` (``u`` the unit
vector from the pole to the object). Prism: down until the membrane is indented ``delta_t``, turning at
the yaw rate ``-k_psi psi`` (psi the prism yaw modulo pi, clipped) from the first contact on
(``rotate_on_contact``) until aligned, then hold it pressed for ``align_hold_steps`` (8) steps.

What the policy can learn is what the §5.3 input explains. Flank pushing a disc with the convex dome is
unstable (the pusher-object offset grows), and the flank teacher's lateral corrections depend on ``u``,
which the world-frame ``[c, lambda, e_1]`` of a small, nearly isotropic contact patch does not carry
(a linear fit of the demonstrated lateral velocity on S explains ~20 % of its variance, on the privileged
offset ~80 %): its policies pushed straight on, lost 22 of 50 capsules over seeds 0-9 (off-centre drift
past the pusher or into a wall) and sometimes took the large capsules for the prism. A dragged capsule
moves with the palm, so ``c`` locates it and the steering is a function of ``c_x`` (~85 % explained).
A prism teacher that waits for ``delta_t`` before turning shows zero yaw rate at large ``psi`` while
touching; GMR's per-state linear regression explains that with ``lambda`` and mis-predicts the yaw rate at
the executed indentation (stopping short, or overshooting).

Sensor resolution matters for the prism: its orientation reaches the policy only through ``e_1`` of the
contact core. On the cap-12 membrane mesh ``e_1`` is off by 5-13 deg (median / 90th percentile) and the
policy stops 6-30 deg short; the cap-20 mesh, contact core 0.7 and a 5 mm indentation give 1 / 3 deg.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.contour_sim import TactileSimulation, pose_from
from defgraspnets.tactile.lfd.experiments import (
    Demonstration,
    EdgeFollowingPolicy,
    fit_edge_following_policy,
)
from defgraspnets.tactile.lfd.features import demonstration_observations, tactile_features
from defgraspnets.tactile.pushing import Capsule, PushingModel, Rectangle, push
from defgraspnets.tactile.sdf import BoxSDF, SignedDistance, UnionSDF

__all__ = [
    "CAPSULES",
    "CAPSULE_APPROACHES",
    "MANIPULATION_FEATURES",
    "PRISM",
    "ExtrudedFootprintSDF",
    "ManipulationObject",
    "ManipulationRun",
    "ManipulationWorld",
    "PalmGeometry",
    "StepOutcome",
    "TeacherParameters",
    "demonstrate",
    "evaluate_success",
    "fit_manipulation_policy",
    "mirror_start",
    "mixed_manipulation_experiment",
    "move_object",
    "rollout_manipulation",
    "sample_start",
]

#: §5.5: 9-D input — centroid, principal variances, first principal vector.
MANIPULATION_FEATURES = ("centroid", "principal_variances", "e1")

_G = 9.81

#: How the teacher handles a capsule (:class:`TeacherParameters`).
CAPSULE_APPROACHES = ("above", "behind")


def _check_capsule_approach(approach: str) -> None:
    if approach not in CAPSULE_APPROACHES:
        raise ValueError(f"capsule_approach must be one of {CAPSULE_APPROACHES}, got {approach!r}")


class ExtrudedFootprintSDF(SignedDistance):
    """A planar footprint at pose ``(x, y, theta)`` extruded from ``z = 0`` to ``z = height`` [m].

    ``phi = |max(q, 0)| + min(max(q), 0)`` with ``q = (d_2D, |z - h/2| - h/2)`` (exact for an extrusion).
    """

    def __init__(self, shape: Capsule | Rectangle, pose, height: float):
        if not height > 0:
            raise ValueError(f"height must be > 0 m, got {height}")
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError("pose must be a finite (x, y, theta)")
        self.shape, self.pose, self.height = shape, p, float(height)

    def distance(self, points) -> np.ndarray:
        x = np.asarray(points, dtype=np.float64)
        c, s = np.cos(self.pose[2]), np.sin(self.pose[2])
        d = x[:, :2] - self.pose[:2]
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
        d2 = self.shape.closest_boundary(local)[2]
        dz = np.abs(x[:, 2] - 0.5 * self.height) - 0.5 * self.height
        q = np.stack([d2, dz], axis=1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


@dataclass(frozen=True)
class ManipulationObject:
    """An object of the task: footprint, height [m], mass [kg], kind ``"capsule"`` or ``"prism"``."""

    name: str
    shape: Capsule | Rectangle
    height: float
    mass: float
    kind: str

    def __post_init__(self):
        if self.kind not in ("capsule", "prism"):
            raise ValueError(f"kind must be 'capsule' or 'prism', got {self.kind!r}")
        if not self.height > 0 or not self.mass > 0:
            raise ValueError("height and mass must be > 0")


def _capsule(name, diameter, height, density=1000.0):
    radius = diameter / 2
    return ManipulationObject(name, Capsule(radius), height, density * np.pi * radius**2 * height, "capsule")


#: Eight upright capsules (§5.5: diameters 1-5 cm, heights 1.5-1.7 cm): disc footprints, 1000 kg/m^3.
CAPSULES = (
    _capsule("capsule_d10", 0.010, 0.015),
    _capsule("capsule_d15", 0.015, 0.016),
    _capsule("capsule_d20", 0.020, 0.017),
    _capsule("capsule_d25", 0.025, 0.015),
    _capsule("capsule_d30", 0.030, 0.016),
    _capsule("capsule_d35", 0.035, 0.017),
    _capsule("capsule_d40", 0.040, 0.015),
    _capsule("capsule_d50", 0.050, 0.016),
)
#: The 7.5 x 1 x 2 cm prism (§5.5) lying on its 7.5 x 1 cm face (2 cm high), 15 g.
PRISM = ManipulationObject("prism", Rectangle(0.0375, 0.005), 0.02, 0.015, "prism")


@dataclass(frozen=True)
class PalmGeometry:
    """The outer dome as a sphere: radius [m] and the sensor-frame height of the pole [m]."""

    radius: float
    pole_height: float

    @classmethod
    def from_simulation(cls, sim: TactileSimulation) -> PalmGeometry:
        """Least-squares sphere (centre on the axis) through the outer cap within 30 mm of the pole."""
        o = sim.model.outer_reference
        top = o[:, 2].max()
        cap = o[o[:, 2] > top - 0.03]
        a = np.c_[2 * cap[:, 2], np.ones(len(cap))]
        zc, k = np.linalg.lstsq(a, (cap**2).sum(axis=1), rcond=None)[0]
        return cls(float(np.sqrt(k + zc**2)), float(top))

    def section_radius(self, pole_z: float, z: float) -> float:
        """Radius [m] of the dome's section at height ``z``, pole at ``pole_z`` (0 if the dome is above z)."""
        dz = pole_z + self.radius - z
        if dz >= self.radius:
            return 0.0
        return self.radius if dz <= 0 else float(np.sqrt(self.radius**2 - dz**2))

    def pose(self, pole_xyz, yaw: float = 0.0) -> np.ndarray:
        """Sensor pose pointing down with its pole at ``pole_xyz`` [m], turned by ``yaw`` [rad] about z."""
        t = pose_from(np.asarray(pole_xyz, dtype=np.float64) + [0.0, 0.0, self.pole_height], (0, 0, -1))
        t[:3, :3] = Rotation.from_euler("z", yaw).as_matrix() @ t[:3, :3]
        return t

    def pole(self, pose) -> np.ndarray:
        t = np.asarray(pose, dtype=np.float64)
        return t[:3, :3] @ np.array([0.0, 0.0, self.pole_height]) + t[:3, 3]


@dataclass(frozen=True)
class ManipulationWorld:
    """Table, corridor and contact constants (SI).

    Attributes:
        corridor_width: free width ``w`` between the walls [m].
        corridor_length: ``L_c`` [m] (walls from ``y = -L_c`` to the edge ``y = 0``).
        wall_thickness, wall_height: [m].
        push_indentation: ``delta_p`` [m] (see the module docstring).
        pusher_friction: ``mu_c`` membrane-object.
        support_friction: ``mu_s`` object-table.
        substep: pushing-model substep [m].
    """

    corridor_width: float = 0.10
    corridor_length: float = 0.12
    wall_thickness: float = 0.01
    wall_height: float = 0.01
    push_indentation: float = 0.004
    pusher_friction: float = 0.8
    support_friction: float = 0.3
    substep: float = 1.0e-3

    def __post_init__(self):
        for k in ("corridor_width", "corridor_length", "wall_thickness", "wall_height", "substep"):
            if not getattr(self, k) > 0:
                raise ValueError(f"{k} must be > 0 m, got {getattr(self, k)}")
        if not self.push_indentation >= 0:
            raise ValueError("push_indentation must be >= 0 m")

    def walls(self) -> list[BoxSDF]:
        hw, t, lc = self.corridor_width / 2, self.wall_thickness, self.corridor_length
        return [
            BoxSDF((s * (hw + t / 2), -lc / 2, self.wall_height / 2), (t / 2, lc / 2, self.wall_height / 2))
            for s in (-1.0, 1.0)
        ]

    def static_scene(self) -> list[SignedDistance]:
        table = BoxSDF((0.0, -0.25, -0.02), (0.3, 0.25, 0.02))
        return [table, *self.walls()]

    def scene(self, obj: ManipulationObject, pose, on_table: bool = True) -> SignedDistance:
        parts = self.static_scene()
        if on_table:
            parts.append(ExtrudedFootprintSDF(obj.shape, pose, obj.height))
        return UnionSDF(tuple(parts))

    def wall_overlap(self, obj: ManipulationObject, pose) -> bool:
        """Whether the footprint at ``pose`` overlaps a wall (checked on the footprint's boundary samples)."""
        pts = _footprint_samples(obj.shape, pose)
        hw, t, lc = self.corridor_width / 2, self.wall_thickness, self.corridor_length
        in_y = (pts[:, 1] > -lc) & (pts[:, 1] < 0.0)
        in_x = (np.abs(pts[:, 0]) > hw) & (np.abs(pts[:, 0]) < hw + t)
        return bool((in_y & in_x).any())


def _footprint_samples(shape, pose, n: int = 64) -> np.ndarray:
    """World xy points on the footprint boundary (n) and its centroid."""
    ex, ey = shape.extent
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    far = np.stack([2 * ex * np.cos(ang), 2 * ex * np.sin(ang)], axis=1)
    # project points of a large circle onto the boundary from outside (closest boundary points)
    pts = np.concatenate([shape.closest_boundary(far)[0], np.zeros((1, 2))])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return pts @ np.array([[c, s], [-s, c]]) + pose[:2]


def _characteristic(shape) -> float:
    return PushingModel(shape, 0.01).c


@dataclass(frozen=True)
class StepOutcome:
    """Object state after a palm move: pose, on table, mode ("free", "push", "wedge", "stick", "slip")."""

    pose: np.ndarray
    on_table: bool
    mode: str


def move_object(
    world: ManipulationWorld, palm: PalmGeometry, obj: ManipulationObject, pose, on_table: bool,
    pose_from_t, pose_to_t, normal_force: float, contact_columns_xy: np.ndarray,
) -> StepOutcome:  # fmt: skip
    """Quasi-static object motion for the palm moving from ``pose_from_t`` to ``pose_to_t`` (see the module).

    ``normal_force`` [N] and ``contact_columns_xy`` (K, 2) [m] (world xy of the membrane's contact
    columns) are the membrane state at ``pose_from_t`` with the object in ``pose``.
    """
    p = np.asarray(pose, dtype=np.float64).copy()
    if not on_table:
        return StepOutcome(p, False, "free")
    a, b = palm.pole(pose_from_t), palm.pole(pose_to_t)
    local_pole = _to_local(p, a[:2])
    over = float(obj.shape.closest_boundary(local_pole)[2]) < 0.0
    if over:  # pressing from above
        if normal_force <= 0 or len(contact_columns_xy) == 0:
            return StepOutcome(p, True, "free")
        cxy = contact_columns_xy
        c_patch = float(np.linalg.norm(cxy - cxy.mean(axis=0), axis=1).mean())
        holds = world.pusher_friction * normal_force * c_patch >= world.support_friction * (
            obj.mass * _G + normal_force
        ) * _characteristic(obj.shape)
        if not holds:
            return StepOutcome(p, True, "slip")
        r_from, r_to = np.asarray(pose_from_t)[:3, :3], np.asarray(pose_to_t)[:3, :3]
        dyaw = float(Rotation.from_matrix(r_to @ r_from.T).as_rotvec()[2])
        c, s = np.cos(dyaw), np.sin(dyaw)
        rel = p[:2] - a[:2]
        p[:2] = b[:2] + np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]])
        p[2] += dyaw
        return _fall(p, "stick")
    z_obj = obj.height - world.push_indentation
    r_new = palm.section_radius(b[2], z_obj)
    mode = "free"
    if r_new <= 0:
        return StepOutcome(p, True, mode)
    model = PushingModel(
        obj.shape, r_new, world.pusher_friction, world.support_friction, obj.mass * _G,
        characteristic_length=_characteristic(obj.shape),
    )  # fmt: skip
    # wedge: the section at the new height grown into the object at the old xy
    pt, normal, sd = obj.shape.closest_boundary(local_pole)
    gap = float(sd) - r_new
    if gap < 0:
        c, s = np.cos(p[2]), np.sin(p[2])
        n_world = np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]])
        p[:2] += gap * n_world  # normal points from the object to the pole: move away from it
        mode = "wedge"
    res = push(model, p, a[:2], b[:2] - a[:2], max_substep=world.substep)
    if res.in_contact and res.mode != "separating":
        mode = "push"
    return _fall(res.object_pose, mode)


def _fall(pose, mode) -> StepOutcome:
    return StepOutcome(pose, bool(pose[1] <= 0.0), mode)


def _to_local(pose, xy) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(xy) - pose[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


def _wrap_half_turn(angle: float) -> float:
    """Angle modulo pi into [-pi/2, pi/2) [rad] (a prism's orientation)."""
    return float((angle + np.pi / 2) % np.pi - np.pi / 2)


@dataclass(frozen=True)
class TeacherParameters:
    """Scripted teacher (SI, per control step of ``dt``).

    Attributes:
        dt: control period [s] (thesis: 5 Hz).
        lower_speed: lowering speed [m/s].
        indentation: prism: membrane indentation that ends the lowering and is held while rotating [m].
        push_height: capsule: pole height above the table that ends the lowering and is held [m].
        push_speed: pushing speed [m/s].
        steer_gain: ``k_x`` [1/m], desired object heading ``d ~ (-k_x x_o, 1)`` (toward the corridor axis).
        swing_gain: ``k_u``: the pusher moves along ``u + k_u (u - d)``, ``u`` the unit vector from the pole
            to the object: pushing beside the line of centres swings the object the other way, so aiming
            outside it turns ``u`` (the object's heading) toward ``d``.
        height_gain: fraction of the height (or indentation) error corrected per step.
        yaw_gain: ``k_psi`` per step.
        max_yaw_rate: [rad/s].
        retract_speed: upward speed after the capsule fell [m/s].
        hold_steps: capsule: steps of retraction after it fell.
        max_steps: a demonstration longer than this fails.
        align_tolerance: prism yaw at which the teacher stops rotating [rad].
        capsule_approach: ``"above"`` — the palm starts above the capsule (thesis Fig. 5.8a-b), is lowered
            onto it to ``indentation`` and drags the pressed capsule along ``d`` at ``push_speed`` (it sticks
            to the palm, :func:`move_object`); ``"behind"`` — the palm starts behind it and pushes it with
            the dome's flank at ``push_height`` along ``u + k_u (u - d)``. :func:`sample_start` places the
            palm accordingly. Dragging needs the pressed capsule to stick (:func:`move_object`): on the
            coarse cap-8 membrane too few contact columns touch the 10 mm capsule, it slips and the teacher
            does not finish.
        rotate_on_contact: prism: start turning at the first contact (pressing on to ``indentation``
            meanwhile). Then the demonstrated yaw rate is ``-k_psi psi`` during the whole contact, a
            function of the sensed orientation ``e_1``; turning only once ``indentation`` is reached also
            shows zero yaw rate at large ``psi`` while pressing, which the per-state linear regression of GMR
            explains with the patch size ``lambda`` and then mis-predicts at the executed indentation.
        align_hold_steps: prism: steps the aligned prism is held (pressed, zero yaw rate) before the end.
            They are the demonstrations of where to stop: GMR's linear regression of the yaw rate in the
            prism's contact state has to cross zero at the aligned reading, while it is pulled away from
            there by contact steps whose yaw rate is not a function of ``e_1`` (the capsules' first touch,
            omega = 0 at ``e_1`` along y; the per-demonstration error of the sensed ``e_1``, which
            constant features such as ``c_x`` absorb); with 3 held steps the policy stopped 5-8 deg short
            in 8 of 50 unseen prism starts (seeds 0-9), with 8 in 5 (by 5-7 deg).
    """

    dt: float = 0.2
    lower_speed: float = 0.015
    indentation: float = 0.005
    push_speed: float = 0.04
    steer_gain: float = 8.0
    swing_gain: float = 1.0
    push_height: float = 0.006
    height_gain: float = 0.5
    yaw_gain: float = 0.3
    max_yaw_rate: float = np.deg2rad(60.0)
    retract_speed: float = 0.04
    hold_steps: int = 3
    max_steps: int = 60
    align_tolerance: float = np.deg2rad(1.0)
    capsule_approach: str = "above"
    rotate_on_contact: bool = True
    align_hold_steps: int = 8

    def __post_init__(self):
        _check_capsule_approach(self.capsule_approach)


@dataclass(frozen=True)
class ManipulationRun:
    """One episode: sensor poses (T, 4, 4), inputs (T, 9), contact, housing contact (T,), object poses
    (T, 3) and on-table flags (T,) *at* each pose, object modes (T-1,) of each move, HMM weights (T, N) for
    policy rollouts (empty for the teacher), whether the object ever overlapped a wall, and the control
    period dt [s]."""

    obj: ManipulationObject
    poses: np.ndarray
    inputs: np.ndarray
    in_contact: np.ndarray
    housing_contact: np.ndarray
    object_poses: np.ndarray
    on_table: np.ndarray
    modes: tuple
    weights: np.ndarray
    wall_overlap: bool
    dt: float = 0.2

    def demonstration(self) -> Demonstration:
        return Demonstration(
            self.inputs, self.poses, self.in_contact,
            demonstration_observations(self.inputs, self.poses, self.dt),
        )  # fmt: skip


def sample_start(
    obj: ManipulationObject, palm: PalmGeometry, world: ManipulationWorld, rng, height=0.03,
    capsule_approach: str = "above",
):  # fmt: skip
    """Random start (object pose (3,), sensor pose (4, 4)) in the task quadrant.

    Capsule: object at ``x ~ U(-0.015, 0.015)``, ``y ~ U(-0.21, -0.17)`` m, any yaw; the pole 30 mm above the
    table, ``capsule_approach="above"``: above the object (``+-3`` mm, thesis Fig. 5.8a); ``"behind"``: behind
    the object (``-y``), placed so that the dome's flank meets the object's rear top edge when the pole is
    3 mm below that edge, with ``+-3`` mm noise. Both draw the same random numbers.
    Prism: centroid ``x ~ U(-0.03, 0.03)``, ``y ~ U(-0.22, -0.18)``, yaw ``U(-40, 40)`` deg; the pole above it
    (``+-3`` mm).
    """
    _check_capsule_approach(capsule_approach)
    if obj.kind == "capsule":
        pose = np.array([rng.uniform(-0.015, 0.015), rng.uniform(-0.21, -0.17), rng.uniform(-np.pi, np.pi)])
        ey = _extent_along(obj.shape, pose[2], np.array([0.0, 1.0]))
        behind = (
            ey + palm.section_radius(obj.height - 0.003, obj.height) if capsule_approach == "behind" else 0.0
        )
        pole = [pose[0] + rng.uniform(-0.003, 0.003), pose[1] - behind + rng.uniform(-0.003, 0.003), height]
    else:
        pose = np.array(
            [rng.uniform(-0.03, 0.03), rng.uniform(-0.22, -0.18), np.deg2rad(rng.uniform(-40, 40))]
        )
        pole = [pose[0] + rng.uniform(-0.003, 0.003), pose[1] + rng.uniform(-0.003, 0.003), height]
    return pose, palm.pose(pole)


def _extent_along(shape, theta, direction) -> float:
    """Support distance of the footprint (yaw ``theta``) along the world unit ``direction`` [m]."""
    pts = _footprint_samples(shape, np.array([0.0, 0.0, theta]))
    return float((pts @ direction).max())


def _features(sim, scene, pose):
    obs = sim.observe(scene, pose)
    return obs, tactile_features(obs.points, pose, weights=obs.weights).vector(MANIPULATION_FEATURES)


def _object_contact_xy(sim, obs, pose, obj, object_pose) -> np.ndarray:
    """World xy (K, 2) of the membrane's contact columns that touch the object (not the table or walls)."""
    cols = obs.state.contact_columns
    outer = sim.model.outer_reference[cols] + obs.state.column_displacement[cols]
    t = np.asarray(pose)
    world = outer @ t[:3, :3].T + t[:3, 3]
    on_object = ExtrudedFootprintSDF(obj.shape, object_pose, obj.height).distance(world) < 1.0e-3
    return world[on_object, :2]


def _apply_twist(pose, twist, dt) -> np.ndarray:
    out = np.asarray(pose, dtype=np.float64).copy()
    out[:3, 3] += twist[:3] * dt
    out[:3, :3] = Rotation.from_rotvec(twist[3:] * dt).as_matrix() @ out[:3, :3]
    return out


def _episode(sim, world, palm, obj, object_pose, sensor_pose, controller, steps, dt, policy=None):
    """Run ``controller(t, obs, s, sensor_pose, object_pose, on_table) -> twist or None`` (None stops)."""
    pose = np.asarray(sensor_pose, dtype=np.float64).copy()
    p, on = np.asarray(object_pose, dtype=np.float64).copy(), True
    log = {k: [] for k in ("pose", "input", "contact", "housing", "obj", "on", "mode", "w")}
    wall = world.wall_overlap(obj, p)
    for t in range(steps):
        obs, s = _features(sim, world.scene(obj, p, on), pose)
        log["pose"].append(pose.copy())
        log["input"].append(s)
        log["contact"].append(obs.in_contact)
        log["housing"].append(obs.housing_contact)
        log["obj"].append(p.copy())
        log["on"].append(on)
        twist = controller(t, obs, s, pose, p, on)
        if policy is not None:
            log["w"].append(policy.gmr.weights)
        if twist is None or t == steps - 1:
            break
        new = _apply_twist(pose, twist, dt)
        cxy = _object_contact_xy(sim, obs, pose, obj, p) if obs.in_contact and on else np.empty((0, 2))
        fn = obs.state.normal_force if len(cxy) else 0.0
        out = move_object(world, palm, obj, p, on, pose, new, fn, cxy)
        p, on, pose = out.pose, out.on_table, new
        log["mode"].append(out.mode)
        wall |= on and world.wall_overlap(obj, p)
    return ManipulationRun(
        obj, np.array(log["pose"]), np.array(log["input"]), np.array(log["contact"], dtype=bool),
        np.array(log["housing"], dtype=bool), np.array(log["obj"]), np.array(log["on"], dtype=bool),
        tuple(log["mode"]), np.array(log["w"]), bool(wall), dt,
    )  # fmt: skip


def _teacher(palm: PalmGeometry, world: ManipulationWorld, obj: ManipulationObject, tp: TeacherParameters):
    state = {"phase": "lower", "done": 0}

    def control(t, obs, s, pose, p, on):
        twist = np.zeros(6)
        pole = palm.pole(pose)
        indent = obs.state.max_displacement if obs.in_contact else 0.0
        flank = obj.kind == "capsule" and tp.capsule_approach == "behind"
        if state["phase"] == "lower":
            if flank and pole[2] <= tp.push_height + 1e-9:
                state["phase"] = "push"
            elif not flank and (
                indent >= tp.indentation or (obj.kind == "prism" and tp.rotate_on_contact and obs.in_contact)
            ):
                state["phase"] = "rotate" if obj.kind == "prism" else "drag"
            else:
                twist[2] = -min(tp.lower_speed, (pole[2] - tp.push_height) / tp.dt)
                return twist
        if flank:
            vz = tp.height_gain * (tp.push_height - pole[2]) / tp.dt
        else:
            vz = tp.height_gain * (indent - tp.indentation) / tp.dt if obs.in_contact else 0.0
        if state["phase"] == "push":
            if not on:
                state["phase"] = "after"
            else:
                d = np.array([-tp.steer_gain * p[0], 1.0])
                d /= np.linalg.norm(d)
                u = p[:2] - pole[:2]
                u /= np.linalg.norm(u)
                aim = u + tp.swing_gain * (u - d)
                v = tp.push_speed * aim / np.linalg.norm(aim)
                twist[:2], twist[2] = v, np.clip(vz, -tp.lower_speed, tp.lower_speed)
                return twist
        if state["phase"] == "drag":
            if not on:
                state["phase"] = "after"
            else:  # the pressed capsule follows the palm: move along d
                d = np.array([-tp.steer_gain * p[0], 1.0])
                twist[:2], twist[2] = (
                    tp.push_speed * d / np.linalg.norm(d),
                    np.clip(vz, -tp.lower_speed, tp.lower_speed),
                )
                return twist
        if state["phase"] == "after":
            state["done"] += 1
            if state["done"] > tp.hold_steps:
                return None
            twist[2] = tp.retract_speed
            return twist
        # rotate
        psi = _wrap_half_turn(p[2])
        if abs(psi) <= tp.align_tolerance:
            state["done"] += 1
            if state["done"] > tp.align_hold_steps:
                return None
        twist[5] = np.clip(-tp.yaw_gain * psi / tp.dt, -tp.max_yaw_rate, tp.max_yaw_rate)
        if abs(psi) <= tp.align_tolerance:
            twist[5] = 0.0
        twist[2] = np.clip(vz, -tp.lower_speed, tp.lower_speed)
        return twist

    return control


def demonstrate(
    sim: TactileSimulation, world: ManipulationWorld, palm: PalmGeometry, obj: ManipulationObject,
    object_pose, sensor_pose, teacher: TeacherParameters,
) -> ManipulationRun:  # fmt: skip
    """One scripted teacher demonstration; raises if the teacher does not finish in ``max_steps``."""
    run = _episode(
        sim, world, palm, obj, object_pose, sensor_pose, _teacher(palm, world, obj, teacher),
        teacher.max_steps, teacher.dt,
    )  # fmt: skip
    if len(run.poses) >= teacher.max_steps:
        raise RuntimeError(f"the teacher did not finish {obj.name} in {teacher.max_steps} steps")
    return run


def evaluate_success(
    run: ManipulationRun, world: ManipulationWorld, yaw_tolerance: float = np.deg2rad(5.0),
    max_prism_shift: float = 0.02,
) -> dict:  # fmt: skip
    """Success and its criteria for one episode (module docstring)."""
    out = {
        "object": run.obj.name,
        "kind": run.obj.kind,
        "steps": int(len(run.poses)),
        "housing_contact": bool(run.housing_contact.any()),
        "wall_overlap": run.wall_overlap,
    }
    final = run.object_poses[-1]
    if run.obj.kind == "capsule":
        off = not bool(run.on_table[-1])
        k = int(np.argmin(run.on_table)) if off else None
        # the object's position at the first step past the edge
        x_cross = float(run.object_poses[k][0]) if off else None
        inside = off and abs(x_cross) <= world.corridor_width / 2
        out.update(off_table=off, edge_crossing_x_m=x_cross, through_corridor=bool(inside))
        out["success"] = bool(off and inside and not run.wall_overlap and not out["housing_contact"])
    else:
        yaw_err = abs(_wrap_half_turn(final[2]))
        shift = float(np.linalg.norm(final[:2] - run.object_poses[0][:2]))
        on = bool(run.on_table[-1])
        out.update(final_yaw_error_deg=float(np.rad2deg(yaw_err)), shift_m=shift, on_table=on)
        out["success"] = bool(
            on and yaw_err <= yaw_tolerance and shift <= max_prism_shift and not out["housing_contact"]
        )
    return out


def fit_manipulation_policy(
    runs: list[ManipulationRun], n_states: int = 4, regularization: float = 1e-3, seed: int = 0,
    n_restarts: int = 1,
) -> EdgeFollowingPolicy:  # fmt: skip
    """Min-max normalize ``[S, A]`` of all demonstrations, Baum-Welch 4-state HMM, GMRa policy
    (``n_restarts``: see :func:`~defgraspnets.tactile.lfd.experiments.fit_edge_following_policy`)."""
    if len(runs) < 1:
        raise ValueError("need at least one demonstration")
    dt = runs[0].dt
    return fit_edge_following_policy(
        [r.demonstration() for r in runs], n_states, regularization, seed, dt, n_restarts
    )


def mirror_start(palm: PalmGeometry, object_pose, sensor_pose) -> tuple[np.ndarray, np.ndarray]:
    """The mirror image of a start about the corridor axis ``x = 0``: object ``(x, y, theta) -> (-x, y,
    -theta)``, palm pole ``x -> -x`` (the palm keeps its orientation)."""
    p = np.asarray(object_pose, dtype=np.float64) * [-1.0, 1.0, -1.0]
    pole = palm.pole(sensor_pose) * [-1.0, 1.0, 1.0]
    return p, palm.pose(pole)


def rollout_manipulation(
    sim: TactileSimulation, world: ManipulationWorld, palm: PalmGeometry, policy: EdgeFollowingPolicy,
    obj: ManipulationObject, object_pose, sensor_pose, steps: int,
) -> ManipulationRun:  # fmt: skip
    """Execute the learned policy: observe, predict ``[v, omega]`` (GMRa), move for dt; ``steps`` steps."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    policy.reset()

    def control(t, obs, s, pose, p, on):
        return policy.action(s)

    return _episode(sim, world, palm, obj, object_pose, sensor_pose, control, steps, policy.dt, policy)


def mixed_manipulation_experiment(
    sim: TactileSimulation,
    world: ManipulationWorld | None = None,
    teacher: TeacherParameters | None = None,
    n_demonstrations: int = 10,
    n_rollouts: int = 10,
    n_states: int = 4,
    rollout_steps: int = 45,
    seed: int = 0,
    regularization: float = 1e-3,
    yaw_tolerance: float = np.deg2rad(5.0),
    n_restarts: int = 5,
    mirror_demonstrations: tuple[str, ...] = ("prism",),
) -> dict:
    """§5.5: ``n_demonstrations`` capsule pushes (cycling through the 8 capsules) and as many prism
    rotations, fit the HMM, roll out from ``n_rollouts`` unseen starts (half capsules, half prism).

    ``n_restarts``: Baum-Welch restarts (:func:`fit_manipulation_policy`). ``mirror_demonstrations``: object
    kinds whose every second demonstration is the mirror image (:func:`mirror_start`) of the one before
    (the task is symmetric about the corridor axis; a random start is still drawn so that the other
    demonstrations do not change). With ten random prism yaws the demonstrated turns are unbalanced and
    the per-state linear regression of the yaw rate also leans on features that are even under the mirror
    (``e1_x``, ``c_y``, ``lambda``), which biases where the policy stops turning.
    """
    for kind in mirror_demonstrations:
        if kind not in ("capsule", "prism"):
            raise ValueError(f"mirror_demonstrations holds 'capsule' or 'prism', got {kind!r}")
    if n_demonstrations < 1 or n_rollouts < 2:
        raise ValueError("need n_demonstrations >= 1 and n_rollouts >= 2")
    world = world or ManipulationWorld()
    teacher = teacher or TeacherParameters()
    palm = PalmGeometry.from_simulation(sim)
    rng = np.random.default_rng(seed)
    demos, previous = [], {}
    for i in range(n_demonstrations):
        for obj in (CAPSULES[i % len(CAPSULES)], PRISM):
            start = sample_start(obj, palm, world, rng, capsule_approach=teacher.capsule_approach)
            if obj.kind in mirror_demonstrations and i % 2 == 1:
                prev_obj, prev_start = previous[obj.kind]
                obj, start = prev_obj, mirror_start(palm, *prev_start)
            previous[obj.kind] = (obj, start)
            demos.append(demonstrate(sim, world, palm, obj, *start, teacher))
    policy = fit_manipulation_policy(demos, n_states, regularization, seed, n_restarts)
    test_rng = np.random.default_rng(seed + 10_000)  # unseen starts
    rollouts, outcomes = [], []
    for i in range(n_rollouts):
        obj = CAPSULES[(3 * i + 1) % len(CAPSULES)] if i % 2 == 0 else PRISM
        start = sample_start(obj, palm, world, test_rng, capsule_approach=teacher.capsule_approach)
        run = rollout_manipulation(sim, world, palm, policy, obj, *start, rollout_steps)
        rollouts.append(run)
        outcomes.append(evaluate_success(run, world, yaw_tolerance))
    demo_outcomes = [evaluate_success(d, world, yaw_tolerance) for d in demos]
    by_kind = {
        k: {
            "successes": sum(o["success"] for o in outcomes if o["kind"] == k),
            "trials": sum(o["kind"] == k for o in outcomes),
        }
        for k in ("capsule", "prism")
    }
    return {
        "demonstrations": demos,
        "rollouts": rollouts,
        "policy": policy,
        "palm": palm,
        "world": world,
        "report": {
            "n_demonstrations": len(demos),
            "teacher_successes": sum(o["success"] for o in demo_outcomes),
            "teacher_outcomes": demo_outcomes,
            "hmm_states": policy.hmm.n_states,
            "hmm_restarts": int(n_restarts),
            "mirrored_demonstrations": list(mirror_demonstrations),
            "hmm_log_likelihood": policy.hmm.log_likelihood_history[-1]
            if policy.hmm.log_likelihood_history
            else None,
            "successes": sum(o["success"] for o in outcomes),
            "trials": len(outcomes),
            "successes_by_task": by_kind,
            "rollouts": outcomes,
            "yaw_tolerance_deg": float(np.rad2deg(yaw_tolerance)),
            "dt_s": teacher.dt,
        },
    }
