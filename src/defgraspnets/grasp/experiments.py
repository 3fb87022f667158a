"""The DefGraspSim grasp experiments (thesis §6.4) as quasi-static equilibrium problems.

Every experiment starts like the squeeze ramp (:mod:`defgraspnets.grasp.squeeze`): the two force-controlled
finger pads close on the object at a candidate grasp, in zero gravity, until their total normal force is

    F_p = s m g / mu        (s = 1.3, the thesis' factor of safety; m = rho V the object's mass),

and then loads the grasped object with d'Alembert body loads (:class:`defgraspnets.fem.BodyLoad`), expressed
in the object frame, which moves with the gripper once the object is held:

- **pickup**: gravity ``(0, 0, -g)`` (the object frame is the world frame of the object at rest) ramped
  from 0 to g in ``pickup_steps`` equal steps while the fingers keep pressing with F_p;
- **reorientation**: the grasp force is raised to F_slip (below); after pickup the gripper turns the object
  about each of ``num_directions`` world axes k to the angles ``theta_j = j pi / J``, j = 1..J (thesis: 16
  axes, J = 4, 64 states). The held object only sees gravity turn: ``g_obj = R(k, theta)^T (0, 0, -g)``;
  the rotation is followed in ``reorientation_substeps`` sub-steps per angle (the solver interpolates loads
  linearly, so a sub-step is a chord of the rotation). Stress and deformation are recorded in each state;
- **linear acceleration**: in zero gravity the gripper accelerates along each of ``num_directions`` unit
  vectors d fixed in the gripper frame; the object feels ``-a d`` per unit mass. ``a`` is raised in
  ``acceleration_steps`` equal steps up to ``max_linear_acceleration`` (thesis: 50 m/s^2);
- **angular acceleration**: the same with an angular acceleration ``alpha`` about axes through the
  midpoint of the finger contact faces (the thesis' centre of rotation), load ``-alpha k x (X - c)`` per
  unit mass, up to ``max_angular_acceleration`` (thesis: 1000 rad/s^2). The angular velocity is zero (the
  test starts from rest and is quasi-static), so there is no centrifugal load.

**When is the object held?** A state holds the grasp when all of the following hold:

1. the solver found an equilibrium (``SolveStatus.CONVERGED``). Quasi-statically, an object that slides
   out of the pads, falls, or is pushed off a finger has none: the solver flags it ESCAPED or
   NOT_CONVERGED, and the last converged load (``Equilibrium.load_fraction`` of the increment) is the
   failure load;
2. both fingers still press: each finger's total normal force is at least ``min_finger_force_fraction``
   times its share F / 2 of the grasp force (loss of contact, the thesis' criterion);
3. the object does not slide along the pads: the *slide* of a finger, the mean over the surface vertices
   it pressed on when the grasp was formed of their displacement since then with the component along the
   finger's closing direction removed, ``mean_i |(I - n n^T)(u_i - u_i^0)|`` (the pads only move along n,
   so this is the motion of the object's skin relative to the pad), is at most ``max_slide`` [m]
   (default 1 mm, 6 % of the Franka pad). A sticking contact moves only by the penalty friction spring's
   stretch (``mu N / k_t``, micrometres), so the slide measures real sliding.

The load at which a state first fails is the experiment's threshold. Within the failing load step it is
located by the solver's bisection where no equilibrium is found (the last converged load fraction), and
by linear interpolation of the hold margin ``min(1 - slide / max_slide, N_min / (fraction F / 2) - 1)``
(positive while held) where a criterion fails. A grasp that survives the largest load gets the largest
load (``reached_limit`` says so), as in the thesis.

**Modelling choices where the thesis is silent or differs** (DESIGN decision 1, quasi-static FEM):

- the fingers stay force-controlled at F (the thesis freezes the finger joints after pickup); the total
  normal force is therefore exactly F throughout: along the closing axis a finger loses contact at
  ``a = F / m`` and, in zero gravity, the pads slide at ``a = mu F / m`` when the load is tangential to
  them (both from the object's balance, for a grasp axis through the centre of mass);
- F_slip: each contact patch is approximated by two point contacts at the ends of its longest chord L
  (the thesis' estimate), each carrying F / 4 with capacity ``mu F / 4``. In the worst orientation,
  gravity lies in the pad plane and perpendicular to the moment arm d of the centre of mass about the
  grasp axis (the ``perp_dist`` feature): each point then carries ``m g / 4`` plus ``m g d / (2 L)`` from the
  moment, so ``F >= (m g / mu)(1 + 2 d / L)``. With the same factor of safety,
  ``F_slip = max(F_p, F_p (1 + 2 d / L))`` (L at least the mesh's median surface edge);
- the 16 directions are regularly spaced: 8 points of a Fibonacci lattice on the upper unit hemisphere
  and their 8 complements (each vector's opposite is in the set, as the thesis requires). Linear and
  angular directions are fixed in the gripper frame (comparable across grasps); reorientation axes are
  world axes;
- the fields are recorded for the pickup state and each reorientation state; the acceleration tests only
  record thresholds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets import fem

from . import features as feat
from . import metrics as met
from .gripper import FRANKA_HAND, ParallelJawGripper
from .sampler import GraspSet
from .squeeze import (
    FINGER_NAMES,
    GRIP_DOF,
    finger_contact_poses,
    make_squeeze_solver,
    squeeze_ramp,
    squeeze_solver_options,
)

__all__ = [
    "AccelerationResult",
    "ExperimentSettings",
    "GraspExperimentResults",
    "GraspExperiments",
    "GraspFailure",
    "HoldState",
    "PickupResult",
    "ReorientationResult",
    "experiment_solver_options",
    "hold_state",
    "pickup_grasp_force",
    "reorientation_grasp_force",
    "reorientation_gravity",
    "sphere_directions",
]


class GraspFailure(IntEnum):
    """Why a loaded grasp is no longer held (see the module docstring)."""

    HELD = 0
    NO_EQUILIBRIUM = 1  # the solver found none: the object slides out, falls or is pushed off a finger
    LOST_CONTACT = 2  # a finger's normal force fell below min_finger_force_fraction of F / 2
    SLID = 3  # the object's skin slid more than max_slide along a pad
    NOT_GRASPED = 4  # the squeeze itself found no equilibrium: the experiment was not run


@dataclass(frozen=True)
class ExperimentSettings:
    """Parameters of the DefGraspSim experiments (SI units; thesis values by default).

    Args:
        friction: Coulomb mu between pads and object (thesis 0.7).
        safety_factor: s in F_p = s m g / mu (thesis 1.3).
        gravity: g [m/s^2].
        squeeze_steps: load steps of the squeeze 0 -> F_p.
        pickup_steps: steps of the gravity ramp 0 -> g.
        num_directions: directions of the acceleration tests and axes of the reorientation (even; thesis 16).
        reorientation_angles: J, the object is turned to j pi / J, j = 1..J (thesis 4).
        reorientation_substeps: solves per reorientation angle (chords of the rotation).
        max_linear_acceleration: largest tested linear acceleration [m/s^2] (thesis 50).
        max_angular_acceleration: largest tested angular acceleration [rad/s^2] (thesis 1000).
        acceleration_steps: equal steps of the acceleration ramps (a failing step is bisected by the solver
            where no equilibrium is found, interpolated where a state fails a hold criterion).
        max_slide: largest mean slide of a pad's contact vertices still counted as held [m].
        min_finger_force_fraction: a finger whose normal force drops below this fraction of F / 2 has lost
            contact.
    """

    friction: float = 0.7
    safety_factor: float = 1.3
    gravity: float = fem.STANDARD_GRAVITY
    squeeze_steps: int = 5
    pickup_steps: int = 5
    num_directions: int = 16
    reorientation_angles: int = 4
    reorientation_substeps: int = 2
    max_linear_acceleration: float = 50.0
    max_angular_acceleration: float = 1000.0
    acceleration_steps: int = 8
    max_slide: float = 1e-3
    min_finger_force_fraction: float = 0.02

    def __post_init__(self):
        positive = (
            "friction",
            "safety_factor",
            "gravity",
            "max_linear_acceleration",
            "max_angular_acceleration",
            "max_slide",
        )
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"ExperimentSettings.{name} must be a positive number, got {v!r}")
        counts = (
            "squeeze_steps",
            "pickup_steps",
            "reorientation_angles",
            "reorientation_substeps",
            "acceleration_steps",
        )
        for name in counts:
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"ExperimentSettings.{name} must be an integer >= 1, got {v!r}")
        n = self.num_directions
        if not (isinstance(n, (int, np.integer)) and n >= 2 and n % 2 == 0):
            raise ValueError(
                f"ExperimentSettings.num_directions must be an even integer >= 2 (directions come in "
                f"opposite pairs), got {n!r}"
            )
        if not 0 < self.min_finger_force_fraction < 1:
            raise ValueError(
                f"ExperimentSettings.min_finger_force_fraction must lie in (0, 1), got "
                f"{self.min_finger_force_fraction!r}"
            )


def experiment_solver_options(**overrides) -> fem.SolverOptions:
    """Solver settings of the experiments: the squeeze's (:func:`squeeze_solver_options`) with the per-tet
    stress recorded (the stress metric is per element), the sparse direct solver (robust on the nearly
    singular systems of an object about to slip, and fastest on small meshes), and a smaller budget for
    finding that a load has no equilibrium: 25 Newton iterations per increment, 3 load bisections (a failing
    load step is located to 1/8 of the step) and an escape at 10 % of the object's diagonal per increment.
    Near the friction limit Newton can stall before the limit is reached (reported as NOT_CONVERGED), so a
    smaller budget lowers some thresholds: measured on 2 sampled grasps x 16 directions of the 30 mm box
    (2-core CPU), the linear instability was 12.23 / 11.94 m/s^2 in 41 s with these settings, 12.76 /
    12.39 m/s^2 in 74 s with the engine's 40 iterations and 4 bisections. A grasp through the centre of
    mass is not affected (its thresholds match mu F / m and F / m, see tests/test_grasp_experiments.py).
    The squeeze path's 1 % Newton step cap (session 20) applies here too; re-measured with it (session 21,
    ``benchmarks/grasp_experiments_cpu_s21.json``, ``grasp_experiments_cuda_box960_shared_s21.json``),
    every experiment status is unchanged and the metrics move by at most 6 %. The squeeze's released
    increment stabilization (session 24) applies too: on 2 grasps x 8 directions at 200 kPa and 1 MPa (2-core
    CPU, ``benchmarks/grasp_experiments_stabilization_ab_cpu.json``) the 30 mm box's and a 60 mm cylinder's
    thresholds move by at most 1.7 % (the acceleration search's own resolution) at 1.3-1.4 times the time,
    and a 343-vertex capsule, whose curved first contact the plain solve could not establish (every
    experiment NOT_GRASPED), is picked up and gets all four experiments' metrics."""
    base = {
        "linear_solver": "direct",
        "record_tet_stress": True,
        "max_newton_iterations": 25,
        "max_load_bisections": 3,
        "escape_fraction": 0.1,
        # slip thresholds are what these experiments measure: Coulomb per contact to the Newton
        # tolerance, and no iteration budget that would flag a slow but holding grasp as lost
        "friction_rtol": 0.0,
        "max_newton_per_solve": 0,
        # the exact stick zone (the squeeze ramp's 5e-3 h stick zone was not measured on the experiments)
        "friction_stick_slip": 0.0,
        # nor the squeeze ramp's early force-maximum flag (measured on squeeze ramps only)
        "force_maximum_runaway": 0.0,
        # nor its proximal relax of failed releases (session 39): a load past the friction limit has no
        # equilibrium, and re-referenced springs would carry the object along a slow slide instead of
        # reporting it (measured: the off-axis grasp of tests/test_grasp_experiments.py then holds at F_p)
        "stabilization_relax": 0,
    }
    return squeeze_solver_options(**{**base, **overrides})


def pickup_grasp_force(
    mass: float, friction: float, safety_factor: float = 1.3, gravity=fem.STANDARD_GRAVITY
):
    """F_p = s m g / mu [N]: the total normal force whose friction carries the weight with factor s."""
    for name, v in (
        ("mass", mass),
        ("friction", friction),
        ("safety_factor", safety_factor),
        ("gravity", gravity),
    ):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"pickup_grasp_force: {name} must be positive, got {v!r}")
    return safety_factor * mass * gravity / friction


def reorientation_grasp_force(pickup_force: float, moment_arm, patch_length, min_length: float) -> np.ndarray:
    """F_slip = F_p max(1, 1 + 2 d / L) [N] per grasp (module docstring): ``moment_arm`` d (G,) [m], the
    distance of the centre of mass from the grasp axis; ``patch_length`` L (G,) [m], the contact patch's
    longest chord (floored at ``min_length``)."""
    d = np.asarray(moment_arm, dtype=np.float64)
    L = np.maximum(np.asarray(patch_length, dtype=np.float64), min_length)
    if d.shape != L.shape or np.any(~np.isfinite(d)) or np.any(d < 0):
        raise ValueError(f"moment_arm must be finite lengths >= 0 shaped like patch_length, got {d!r}")
    if not (np.isfinite(pickup_force) and pickup_force > 0) or not min_length > 0:
        raise ValueError("pickup_force and min_length must be positive")
    return pickup_force * (1.0 + 2.0 * d / L)


def sphere_directions(count: int = 16) -> np.ndarray:
    """(count, 3) unit vectors regularly spaced on the sphere, in opposite pairs: ``count / 2`` points of a
    Fibonacci lattice on the upper hemisphere (z_i = 1 - (i + 1/2) / h, azimuth i times the golden angle)
    each followed by its complement (rows 2i and 2i + 1 are opposite)."""
    if not (isinstance(count, (int, np.integer)) and count >= 2 and count % 2 == 0):
        raise ValueError(f"count must be an even integer >= 2, got {count!r}")
    h = count // 2
    i = np.arange(h)
    z = 1.0 - (i + 0.5) / h
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z**2)
    up = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return np.stack([up, -up], axis=1).reshape(count, 3)


def reorientation_gravity(axes, angles, gravity: float = fem.STANDARD_GRAVITY) -> np.ndarray:
    """(A, K, 3) gravity in the object frame when the gripper has turned the held object by ``angles`` (K,)
    [rad] about the world ``axes`` (A, 3): ``g_obj = R(axis, angle)^T (0, 0, -g)``."""
    a = np.asarray(axes, dtype=np.float64)
    th = np.asarray(angles, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or np.any(np.linalg.norm(a, axis=1) < 1e-12):
        raise ValueError(f"axes must be non-zero vectors of shape (A, 3), got {a.shape}")
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    rotvec = a[:, None, :] * th[None, :, None]
    R = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*rotvec.shape[:2], 3, 3)
    return np.einsum("akji,j->aki", R, np.array([0.0, 0.0, -gravity]))


@dataclass
class HoldState:
    """Whether each of B loaded grasps is still held (module docstring), and the quantities tested."""

    held: np.ndarray  # (B,) bool
    failure: np.ndarray  # (B,) GraspFailure codes
    slide: np.ndarray  # (B,) largest of the two fingers' mean contact-vertex slide [m]
    finger_force: np.ndarray  # (B, 2) total normal force of each finger [N]
    margin: np.ndarray  # (B,) min(1 - slide / max_slide, weaker finger force / its minimum - 1): > 0 held


def hold_state(
    equilibrium: fem.Equilibrium,
    reference: fem.Equilibrium,
    closing_directions,
    grasp_force,
    max_slide: float,
    min_finger_force_fraction: float,
) -> HoldState:
    """Test the three hold criteria of the module docstring.

    Args:
        equilibrium: the loaded state; reference: the state in which the grasp was formed (same solver).
        closing_directions: (B, 2, 3) unit closing direction of each finger (object frame).
        grasp_force: total normal grasp force F [N], scalar or (B,).
        max_slide: [m]; min_finger_force_fraction: of F / 2.
    """
    B = equilibrium.batch_size
    n = np.asarray(closing_directions, dtype=np.float64)
    if n.shape != (B, 2, 3):
        raise ValueError(f"closing_directions must have shape ({B}, 2, 3), got {n.shape}")
    F = np.broadcast_to(np.asarray(grasp_force, dtype=np.float64), (B,))
    surf = equilibrium.mesh.surface_vertices
    du = equilibrium.displacement[:, surf] - reference.displacement[:, surf]  # (B, S, 3)
    forces = np.stack([equilibrium.contact_normal_force[name].sum(axis=1) for name in FINGER_NAMES], axis=1)
    slides = np.full((B, 2), np.inf)
    for k, name in enumerate(FINGER_NAMES):
        touched = reference.contact_normal_force[name] > 0  # (B, S)
        tangential = du - np.einsum("bsj,bj->bs", du, n[:, k])[..., None] * n[:, k, None, :]
        dist = np.linalg.norm(tangential, axis=-1)
        count = touched.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            slides[:, k] = np.where(count > 0, (dist * touched).sum(axis=1) / np.maximum(count, 1), np.inf)
    slide = slides.max(axis=1)
    failure = np.full(B, GraspFailure.HELD, dtype=np.int64)
    failure[slide > max_slide] = GraspFailure.SLID
    failure[forces.min(axis=1) < min_finger_force_fraction * F / 2] = GraspFailure.LOST_CONTACT
    failure[~equilibrium.converged] = GraspFailure.NO_EQUILIBRIUM
    with np.errstate(invalid="ignore", divide="ignore"):
        margin = np.minimum(
            1.0 - slide / max_slide, forces.min(axis=1) / (min_finger_force_fraction * F / 2) - 1.0
        )
    return HoldState(failure == GraspFailure.HELD, failure, slide, forces, margin)


@dataclass
class PickupResult:
    """Pickup of G grasps: the grasp at F_p (features) and the state under full gravity (metrics)."""

    grasp_force: float  # F_p [N]
    squeezed: fem.Equilibrium  # at F_p, zero gravity
    picked: fem.Equilibrium  # under gravity (last converged state where the pickup failed)
    success: np.ndarray  # (G,) bool: held at every gravity step
    failure: np.ndarray  # (G,) GraspFailure code of the first failing step
    slide: np.ndarray  # (G,) slide at the last step [m]
    features: dict[str, np.ndarray]  # Table 6.2 at F_p, name -> (G,)
    slip_force: np.ndarray  # (G,) F_slip [N] for the reorientation
    max_von_mises: np.ndarray  # (G,) largest element von Mises stress under gravity [Pa]
    max_deformation: np.ndarray  # (G,) rigid-removed deformation from rest under gravity [m]
    strain_energy: np.ndarray  # (G,) [J]


@dataclass
class ReorientationResult:
    """Reorientation of G grasps about A axes to K angles at F_slip."""

    grasp_force: np.ndarray  # (G,) F_slip [N]
    axes: np.ndarray  # (A, 3) world axes
    angles: np.ndarray  # (K,) [rad]
    held: np.ndarray  # (G, A, K) bool: held in that state and all before it on its axis
    failure: np.ndarray  # (G, A) GraspFailure of the first failing state on the axis
    positions: np.ndarray  # (G, A, K, N, 3) deformed vertex positions [m]; NaN where not held
    von_mises: np.ndarray  # (G, A, K, N) vertex von Mises stress [Pa]; NaN where not held
    deformation: np.ndarray  # (G, A, K, N) rigid-removed deformation from rest [m]; NaN where not held
    max_von_mises: np.ndarray  # (G, A, K) largest element von Mises stress [Pa]; NaN where not held
    controllability: np.ndarray  # (G,) max deformation over the states held [m] (NaN if none)


@dataclass
class AccelerationResult:
    """Linear or angular acceleration tests of G grasps along D directions (gripper frame)."""

    kind: str  # "linear" [m/s^2] or "angular" [rad/s^2]
    grasp_force: float  # F_p [N]
    directions: np.ndarray  # (D, 3) unit vectors in the gripper frame
    limit: float  # largest tested acceleration
    threshold: np.ndarray  # (G, D) acceleration at which the grasp was lost (limit if never; NaN: not tested)
    failure: np.ndarray  # (G, D) GraspFailure (HELD where the limit was reached)
    # (G, D) SolveStatus where the failure is NO_EQUILIBRIUM: ESCAPED (the object ran away: no equilibrium)
    # or NOT_CONVERGED (Newton stalled near the friction limit: the threshold is then a lower bound)
    solver_status: np.ndarray
    instability: np.ndarray  # (G,) mean threshold over the directions
    # (G, D) Newton iterations each (grasp, direction) pair spent in the acceleration ramp (the squeeze not
    # counted): the cost of the test. A lost pair spends none after the step that lost it (its job stops)
    newton_iterations: np.ndarray | None = None

    @property
    def reached_limit(self) -> np.ndarray:
        return self.failure == GraspFailure.HELD


@dataclass
class GraspExperimentResults:
    """All experiments of G grasps on one object; :meth:`per_grasp` gives the metrics and features."""

    mass: float  # [kg]
    pickup: PickupResult
    reorientation: ReorientationResult | None = None
    linear: AccelerationResult | None = None
    angular: AccelerationResult | None = None
    extras: dict = field(default_factory=dict)

    def per_grasp(self) -> list[dict]:
        """One JSON-ready dict per grasp: the 7 performance metrics, the 7 features, forces and thresholds."""
        p = self.pickup
        G = len(p.success)
        nan = np.full(G, np.nan)
        lin = self.linear.instability if self.linear is not None else nan
        ang = self.angular.instability if self.angular is not None else nan
        ctrl = self.reorientation.controllability if self.reorientation is not None else nan
        out = []
        for g in range(G):
            rec = {
                "grasp": g,
                "metrics": met.performance_metrics(
                    p.success[g],
                    p.max_von_mises[g],
                    p.max_deformation[g],
                    p.strain_energy[g],
                    lin[g],
                    ang[g],
                    ctrl[g],
                ),
                "features": {k: _json_number(v[g]) for k, v in p.features.items()},
                "pickup_force_n": float(p.grasp_force),
                "slip_force_n": float(p.slip_force[g]),
                "pickup_failure": GraspFailure(int(p.failure[g])).name,
            }
            for res in (self.linear, self.angular):
                if res is not None:
                    rec[f"{res.kind}_thresholds"] = [_json_number(v) for v in res.threshold[g]]
                    rec[f"{res.kind}_failures"] = [GraspFailure(int(v)).name for v in res.failure[g]]
                    rec[f"{res.kind}_solver_status"] = [
                        fem.SolveStatus(int(v)).name for v in res.solver_status[g]
                    ]
            if self.reorientation is not None:
                rec["reorientation_states_held"] = int(self.reorientation.held[g].sum())
            out.append(rec)
        return out


def _json_number(v):
    v = float(v)
    return v if np.isfinite(v) else None


class GraspExperiments:
    """The DefGraspSim experiments of G grasps on one object (module docstring), each batched over grasps
    (and directions) in one :class:`~defgraspnets.fem.QuasiStaticSolver`.

    Args:
        mesh: the object's tet mesh at rest, in its world pose (gravity is -z).
        grasps: the candidate grasps (a :class:`GraspSet`, or anything with ``poses`` and
            ``closing_distances`` that supports integer-array indexing).
        material: the object's material (its density gives the mass).
        settings: :class:`ExperimentSettings`.
        gripper: the parallel-jaw gripper.
        device: Warp device of the FEM.
        options: solver options (default :func:`experiment_solver_options`).
        progress: tqdm bars over the load steps.
        directions_per_solver: the acceleration tests stream their (grasp, direction) pairs through one
            solver of G x ``directions_per_solver`` problems (a problem whose pair has lost its grasp takes
            the next pair: the batch does not wait for its slowest direction at every load step). The
            thresholds do not depend on it with the exact linear solvers; CPU: 1 (the solver factors one
            problem at a time anyway), GPU: 16 (one H200: README, "DefGraspSim experiments").
    """

    def __init__(
        self,
        mesh: fem.TetMesh,
        grasps: GraspSet,
        material: fem.Material,
        settings: ExperimentSettings | None = None,
        gripper: ParallelJawGripper = FRANKA_HAND,
        device=None,
        options: fem.SolverOptions | None = None,
        progress: bool = False,
        directions_per_solver: int = 1,
    ):
        if not isinstance(mesh, fem.TetMesh):
            raise TypeError(f"mesh must be a fem.TetMesh, got {type(mesh).__name__}")
        if not isinstance(material, fem.Material):
            raise TypeError(f"material must be one fem.Material, got {type(material).__name__}")
        if len(grasps.poses) == 0:
            raise ValueError("no grasps to test")
        self.mesh = mesh
        self.grasps = grasps
        self.material = material
        self.settings = settings or ExperimentSettings()
        if not isinstance(self.settings, ExperimentSettings):
            raise TypeError(f"settings must be ExperimentSettings, got {type(self.settings).__name__}")
        self.gripper = gripper
        self.device = device
        self.options = options or experiment_solver_options()
        self.progress = progress
        if not (isinstance(directions_per_solver, (int, np.integer)) and directions_per_solver >= 1):
            raise ValueError(f"directions_per_solver must be an integer >= 1, got {directions_per_solver!r}")
        self.directions_per_solver = int(directions_per_solver)
        self.num_grasps = len(grasps.poses)
        self.masses = mesh.vertex_masses(material.density)  # (N,) [kg]
        self.mass = float(self.masses.sum())
        s = self.settings
        self.pickup_force = pickup_grasp_force(self.mass, s.friction, s.safety_factor, s.gravity)
        self.finger_frames = finger_contact_poses(grasps, gripper)  # (G, 2, 4, 4)
        self._squeeze_cache = None  # (key, solver, equilibrium) of the G grasps squeezed to F_p

    # ------------------------------------------------------------------ plumbing
    def _bar(self, iterable, desc: str):
        if not self.progress:
            return iterable
        from tqdm.auto import tqdm

        return tqdm(iterable, desc=desc, leave=False)

    def _solver(self, rows: np.ndarray) -> fem.QuasiStaticSolver:
        """A squeeze solver (pads at first contact, the experiments' friction and options) with one problem
        per entry of ``rows`` (indices of the grasps)."""
        return make_squeeze_solver(
            self.mesh,
            self.grasps[rows],
            self.material,
            friction=self.settings.friction,
            gripper=self.gripper,
            device=self.device,
            options=self.options,
        )

    def _squeeze(self) -> tuple[fem.QuasiStaticSolver, fem.Equilibrium]:
        """The G grasps squeezed to F_p once, in a solver of one problem per grasp, and their equilibrium at
        F_p; cached (per squeeze force, steps and friction) and never solved further: every experiment
        copies its state (:meth:`fem.QuasiStaticSolver.copy_state_from`) into a solver of its own."""
        s = self.settings
        key = (self.pickup_force, s.squeeze_steps, s.friction)
        cached = self._squeeze_cache
        if cached is None or cached[0] != key:
            solver = self._solver(np.arange(self.num_grasps))
            eqs = squeeze_ramp(solver, self.pickup_force, s.squeeze_steps, progress=self.progress)
            cached = self._squeeze_cache = (key, solver, eqs[-1])
        return cached[1], cached[2]

    def _squeezed(self, replicas: int, desc: str):
        """A solver with every grasp repeated ``replicas`` times (grasp-major), squeezed to F_p: the G grasps
        are squeezed once (:meth:`_squeeze`) and each problem takes the state of its grasp. With the exact
        linear solvers ("direct", "dense") a problem does not depend on its batch, so this is bit-identical
        to squeezing every replica (tests/test_grasp_experiments.py); with "cg" / "amg" (Krylov tolerances
        and iteration counts shared by the batch) it is the squeeze of a batch of G instead of G x replicas,
        equal to within the Newton tolerance. Returns the solver, the equilibrium at F_p of its problems,
        the closing directions and the grasp of each problem."""
        rows = np.repeat(np.arange(self.num_grasps), replicas)
        squeezed, eq = self._squeeze()
        solver = self._solver(rows)
        solver.copy_state_from(squeezed, rows)
        frames = self.finger_frames[rows]
        return solver, eq.take(rows), frames[:, :, :3, 1], rows

    def _hold(self, eq, reference, closing, force) -> HoldState:
        s = self.settings
        return hold_state(eq, reference, closing, force, s.max_slide, s.min_finger_force_fraction)

    def _stream_pairs(
        self, grasp_of: np.ndarray, jobs: list, reached, check, slots: int, source=None
    ) -> None:
        """Stream ``jobs`` (job i: load levels from the state of grasp ``grasp_of[i]`` in ``source``, a solver
        of one problem per grasp; default the shared squeeze) through ``slots`` problems
        (:meth:`fem.QuasiStaticSolver.solve_stream`; ``reached`` and ``check`` as its ``on_levels`` and
        ``check``): a problem whose job ended or was flagged takes the next job at once."""
        source = self._squeeze()[0] if source is None else source
        solver = self._solver(grasp_of[: min(len(jobs), slots)])

        def begin(problems, ids):
            solver.copy_state_from(source, rows=grasp_of[ids], into=problems)

        solver.solve_stream(jobs, begin, reached, check=check, progress=self.progress)

    def _gravity_ramp(self, solver, reference, closing, force, held, failure, desc):
        """Ramp gravity 0 -> (0, 0, -g) in pickup_steps; update held/failure in place; last equilibrium."""
        s = self.settings
        eq = reference
        for k in self._bar(range(1, s.pickup_steps + 1), desc):
            g = np.array([0.0, 0.0, -s.gravity * k / s.pickup_steps])
            eq = solver.solve(body_load=fem.BodyLoad(gravity=g))
            hs = self._hold(eq, reference, closing, force)
            newly = held & ~hs.held
            failure[newly] = hs.failure[newly]
            held &= hs.held
        return eq, hs

    # ------------------------------------------------------------------ experiments
    def pickup(self) -> PickupResult:
        """Squeeze to F_p, measure the features, ramp gravity; the pickup metrics under full gravity."""
        solver, squeezed, closing, _ = self._squeezed(1, "pickup")
        features = self.features(squeezed)
        held = squeezed.converged.copy()
        failure = np.where(held, GraspFailure.HELD, GraspFailure.NOT_GRASPED).astype(np.int64)
        picked, hs = self._gravity_ramp(solver, squeezed, closing, self.pickup_force, held, failure, "pickup")
        surf = self.mesh.surface_vertices
        normal = np.stack([squeezed.contact_normal_force[n] for n in FINGER_NAMES], axis=1)
        lengths = feat.contact_patch_lengths(squeezed.positions[:, surf], normal, self.finger_frames)
        slip_force = reorientation_grasp_force(
            self.pickup_force,
            np.nan_to_num(features["perp_dist"], nan=0.0),
            lengths.min(axis=1),
            self.mesh.median_surface_edge_length,
        )
        stress = picked.tet_stress if picked.tet_stress is not None else picked.vertex_stress
        return PickupResult(
            grasp_force=self.pickup_force,
            squeezed=squeezed,
            picked=picked,
            success=held,
            failure=failure,
            slide=hs.slide,
            features=features,
            slip_force=slip_force,
            max_von_mises=met.max_von_mises_stress(stress),
            max_deformation=met.max_deformation(self.mesh.points, picked.positions, self.masses),
            strain_energy=picked.strain_energy.copy(),
        )

    def features(self, squeezed: fem.Equilibrium) -> dict[str, np.ndarray]:
        """Table 6.2 features of the G grasps from their equilibrium at F_p (one problem per grasp)."""
        if squeezed.batch_size != self.num_grasps:
            raise ValueError(
                f"expected {self.num_grasps} problems (one per grasp), got {squeezed.batch_size}"
            )
        surf = self.mesh.surface_vertices
        normal = np.stack([squeezed.contact_normal_force[n] for n in FINGER_NAMES], axis=1)
        separation = self.gripper.opening_from_closing(self.grasps.closing_distances).sum(axis=1)
        return feat.grasp_features(
            squeezed.positions[:, surf],
            normal,
            squeezed.positions,
            self.masses,
            self.finger_frames,
            squeezed.travel[GRIP_DOF],
            separation,
            pad_length=self.gripper.pad_size[2],
        )

    def reorientation(self, grasp_force) -> ReorientationResult:
        """Squeeze to F_p, raise to ``grasp_force`` (F_slip, (G,) [N]), pick up, then turn gravity about
        each axis through the J angles; fields per state. Each grasp is raised and picked up once; every
        (grasp, axis) pair of a grasp still held is then one job of J x sub turning states from that state
        (as the acceleration tests' pairs), all in flight at once (one problem each): a pair stops where its
        grasp is lost, and no pair waits for the others at each step. (With fewer problems than pairs, on the
        2-core CPU the stream's per-level bookkeeping cost ~20 %.)"""
        s = self.settings
        G, N = self.num_grasps, self.mesh.num_vertices
        F = np.broadcast_to(np.asarray(grasp_force, dtype=np.float64), (G,)).copy()
        if np.any(~np.isfinite(F)) or np.any(F <= 0):
            raise ValueError(f"reorientation grasp forces must be positive [N], got {F}")
        axes = sphere_directions(s.num_directions)
        A, J, sub = len(axes), s.reorientation_angles, s.reorientation_substeps
        angles = np.pi * np.arange(1, J + 1) / J
        closing = self.finger_frames[:, :, :3, 1]  # (G, 2, 3)
        fine = np.pi * np.arange(1, J * sub + 1) / (J * sub)
        gravity = reorientation_gravity(axes, fine, s.gravity)  # (A, J * sub, 3)
        # each grasp is raised to F_slip (the hold reference) and picked up once: its axes share that path,
        # as they share the squeeze
        lifted = self._squeezed(1, "reorientation")[0]
        reference = lifted.solve(targets={GRIP_DOF: F})
        picked = reference.converged.copy()
        failure = np.where(picked, GraspFailure.HELD, GraspFailure.NOT_GRASPED).astype(np.int64)
        self._gravity_ramp(lifted, reference, closing, F, picked, failure, "reorientation pickup")
        # pair b = grasp * A + axis of a grasp held after pickup: one job, the J * sub reorientation sub-steps
        # from its grasp's picked-up state
        grasp_of = np.repeat(np.arange(G), A)
        failure = failure[grasp_of]
        todo = np.flatnonzero(picked[grasp_of])
        jobs = [
            [{"body_load": fem.BodyLoad(gravity=gravity[b % A, step])} for step in range(J * sub)]
            for b in todo
        ]
        held_state = np.zeros((G * A, J), dtype=bool)
        positions = np.full((G * A, J, N, 3), np.nan)
        vm = np.full((G * A, J, N), np.nan)
        deformation = np.full((G * A, J, N), np.nan)
        peak = np.full((G * A, J), np.nan)

        def held(ids, ks, part):
            b = todo[ids]
            g = grasp_of[b]
            hs = self._hold(part, reference.take(g), closing[g], F[g])
            failure[b[~hs.held]] = hs.failure[~hs.held]
            return np.where(hs.held, fem.SolveStatus.CONVERGED, fem.SolveStatus.ESCAPED)

        def reached(ids, ks, part):
            b = todo[ids]
            failure[b[~part.converged & (failure[b] == GraspFailure.HELD)]] = GraspFailure.NO_EQUILIBRIUM
            done = np.flatnonzero(part.converged & ((ks + 1) % sub == 0))
            if done.size:  # an angle reached and held: its fields
                b, j = b[done], (ks[done] + 1) // sub - 1
                eq = part.take(done)
                stress = eq.tet_stress if eq.tet_stress is not None else eq.vertex_stress
                held_state[b, j] = True
                positions[b, j] = eq.positions
                vm[b, j] = eq.von_mises
                deformation[b, j] = met.rigid_removed_deformation(self.mesh.points, eq.positions, self.masses)
                peak[b, j] = met.max_von_mises_stress(stress)

        if todo.size:
            self._stream_pairs(grasp_of[todo], jobs, reached, held, slots=todo.size, source=lifted)
        positions = positions.reshape(G, A * J, N, 3)
        return ReorientationResult(
            grasp_force=F,
            axes=axes,
            angles=angles,
            held=held_state.reshape(G, A, J),
            failure=failure.reshape(G, A),
            positions=positions.reshape(G, A, J, N, 3),
            von_mises=vm.reshape(G, A, J, N),
            deformation=deformation.reshape(G, A, J, N),
            max_von_mises=peak.reshape(G, A, J),
            controllability=met.deformation_controllability(self.mesh.points, positions, self.masses),
        )

    def acceleration(self, kind: str, directions=None) -> AccelerationResult:
        """Raise a linear (``kind="linear"``) or angular (``"angular"``) acceleration along each gripper-frame
        direction in equal steps until the grasp is lost (module docstring), in zero gravity at F_p.

        ``directions``: (D, 3) directions (axes) in the gripper frame, normalized here; default
        :func:`sphere_directions` (``settings.num_directions``)."""
        if kind not in ("linear", "angular"):
            raise ValueError(f"kind must be 'linear' or 'angular', got {kind!r}")
        s = self.settings
        limit = s.max_linear_acceleration if kind == "linear" else s.max_angular_acceleration
        if directions is None:
            dirs = sphere_directions(s.num_directions)
        else:
            dirs = np.asarray(directions, dtype=np.float64)
            norms = np.linalg.norm(dirs, axis=-1, keepdims=True) if dirs.ndim == 2 else None
            if dirs.ndim != 2 or dirs.shape[1] != 3 or len(dirs) == 0 or not np.all(np.isfinite(dirs)):
                raise ValueError(f"directions must be a finite (D, 3) array, got shape {dirs.shape}")
            if np.any(norms < 1e-12):
                raise ValueError("directions must be non-zero vectors")
            dirs = dirs / norms
        threshold, failure, status, newton = self._acceleration_stream(kind, dirs, limit)
        return AccelerationResult(
            kind=kind,
            grasp_force=self.pickup_force,
            directions=dirs,
            limit=limit,
            threshold=threshold,
            failure=failure,
            solver_status=status,
            instability=met.instability(threshold, limit),
            newton_iterations=newton,
        )

    def _acceleration_stream(self, kind: str, dirs: np.ndarray, limit: float):
        """(G, D) thresholds, failures, solver statuses and Newton iterations of the G grasps along the D
        directions ``dirs``. Every (grasp, direction) pair of a formed grasp is one job of
        ``acceleration_steps`` load levels, streamed (:meth:`fem.QuasiStaticSolver.solve_stream`) through
        G x ``directions_per_solver`` problems: a job starts from its grasp's squeezed state and stops where
        the grasp is lost, and its problem takes the next job at once, so no problem waits at every load
        step for the batch's slowest direction (each job's states are those of solving its steps one by
        one from the squeezed state)."""
        s = self.settings
        D, G = len(dirs), self.num_grasps
        squeezed, reference = self._squeeze()
        # pair = grasp * D + direction; directions fixed in the gripper frame, expressed in the object frame
        grasp_of = np.repeat(np.arange(G), D)
        world = np.einsum("gij,dj->gdi", self.grasps.poses[:, :3, :3], dirs).reshape(G * D, 3)
        center = self.finger_frames[:, :, :3, 3].mean(axis=1)  # midpoint of the contact faces, per grasp
        closing = self.finger_frames[:, :, :3, 1]  # (G, 2, 3)
        levels = limit * np.arange(1, s.acceleration_steps + 1) / s.acceleration_steps

        def load(j: int, a: float) -> fem.BodyLoad:
            if kind == "linear":
                return fem.BodyLoad(linear_acceleration=a * world[j])
            return fem.BodyLoad(angular_acceleration=a * world[j], rotation_center=center[grasp_of[j]])

        formed = reference.converged[grasp_of]
        threshold = np.where(formed, limit, np.nan)
        failure = np.where(formed, GraspFailure.HELD, GraspFailure.NOT_GRASPED).astype(np.int64)
        status = squeezed.status[grasp_of].copy()  # the squeeze's flag where no grasp was formed
        newton = np.zeros(G * D, dtype=np.int64)
        margin = np.ones(G * D)  # hold margin at the last level held (module docstring: criteria 2 and 3)
        todo = np.flatnonzero(formed)
        if todo.size == 0:
            return tuple(a.reshape(G, D) for a in (threshold, failure, status, newton))

        def below(k: np.ndarray) -> np.ndarray:
            """The acceleration of the level before each level k (0 before the first)."""
            return np.where(k > 0, levels[np.maximum(k - 1, 0)], 0.0)

        def held(ids, ks, part):
            j = todo[ids]
            g = grasp_of[j]
            hs = self._hold(part, reference.take(g), closing[g], self.pickup_force)
            lost = ~hs.held
            # a hold criterion failed: the margin interpolated linearly to zero between the last level held
            # and this one
            with np.errstate(invalid="ignore", divide="ignore"):
                t = np.clip(margin[j] / (margin[j] - hs.margin), 0.0, 1.0)
            prev = below(ks)
            threshold[j[lost]] = (prev + np.nan_to_num(t, nan=0.0) * (levels[ks] - prev))[lost]
            failure[j[lost]] = hs.failure[lost]
            margin[j[~lost]] = hs.margin[~lost]
            return np.where(lost, fem.SolveStatus.ESCAPED, fem.SolveStatus.CONVERGED)

        def reached(ids, ks, part):
            j = todo[ids]
            newton[j] += part.newton_iterations
            # no equilibrium (flagged by the solver, first report): located by its bisection in the step
            none = ~part.converged & (failure[j] == GraspFailure.HELD)
            if none.any():
                jj, kk = j[none], ks[none]
                prev = below(kk)
                threshold[jj] = prev + part.load_fraction[none] * (levels[kk] - prev)
                failure[jj] = GraspFailure.NO_EQUILIBRIUM
                status[jj] = part.status[none]

        jobs = [[{"body_load": load(int(j), a)} for a in levels] for j in todo]
        self._stream_pairs(grasp_of[todo], jobs, reached, held, slots=G * self.directions_per_solver)
        return tuple(a.reshape(G, D) for a in (threshold, failure, status, newton))

    def run(self, experiments=("pickup", "reorientation", "linear", "angular")) -> GraspExperimentResults:
        """Run the named experiments (pickup always runs: it gives the features and F_slip)."""
        known = {"pickup", "reorientation", "linear", "angular"}
        unknown = set(experiments) - known
        if unknown:
            raise ValueError(f"unknown experiments {sorted(unknown)}; choose from {sorted(known)}")
        seconds = {}
        start = time.perf_counter()
        pickup = self.pickup()
        seconds["pickup"] = time.perf_counter() - start
        results = GraspExperimentResults(mass=self.mass, pickup=pickup, extras={"seconds": seconds})
        for name in ("reorientation", "linear", "angular"):
            if name not in experiments:
                continue
            start = time.perf_counter()
            if name == "reorientation":
                results.reorientation = self.reorientation(pickup.slip_force)
            else:
                setattr(results, name, self.acceleration(name))
            seconds[name] = time.perf_counter() - start
        return results
