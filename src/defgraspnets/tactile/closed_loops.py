"""Closed-loop physical HRI on the FEM sensor (thesis §3.5): end-effector pose correction and forearm support.

Both applications run the same control law at 1 Hz (Figs. 3.9, 3.10). With the sensor's pose
S = (R, p) in the world, and its wrench estimate (F, tau) in the *sensor* frame (the base wrench: the
force and torque the contact exerts on the sensor, about its origin at the base, where the thesis's F/T
sensor sits), each step

    p <- p + clamp(k_F R F, dp_max)                      k_F = 0.1 m/N          (world frame)
    R <- R R_x(2 tau_x) R_y(2 tau_y) R_z(2 tau_z)         k_tau = 2 rad/(N m)     (body frame)

(the rotation vector k_tau tau is scaled down to at most dtheta_max). The force is turned into the
world with R before it moves p; the rotations are about the sensor's own axes through its origin.
Since (F, tau) is what the human exerts on the sensor, the law is an admittance: the sensor yields
along the applied force and turns with the applied torque (the instantaneous work F . dp + tau . w is
positive). The thesis's gains move the robot 0.1 m per newton; against the simulated membrane
(~200 N/m at the pole) a step is then far larger than the indentation, so the step clamp sets the pace
(the loop is a clamped descent: the contact force falls step by step, and once 0.1 m/N x F drops
below the clamp the next step overshoots, the contact opens and the sensor stops).

- **Pose correction** (:func:`run_pose_correction`): a rigid fingertip (sphere) is fixed in the world and
  pokes the sensor. Each step the FEM sensor is solved at the fingertip's pose in the sensor frame,
  inv(S) . T_fingertip, approached along the finger's push direction (also turned into the sensor
  frame): a fresh quasi-static indentation, so friction history between steps is not carried over.
  No contact (the finger no longer reaches the inflated membrane) gives the undeformed reading.
- **Forearm support** (:func:`run_forearm_support`): the forearm capsule rests pressed on the sensor
  (the thesis zeroes the wrench there, so both true and estimated wrenches are tared at rest) and is
  moved in the world (shear, twist). Friction drags the membrane, so the relative motion's whole history
  matters: each step replays it with :meth:`MembraneSimulator.press_and_move` (the relative pose before
  and after every sensor update), and the sensor follows with the same law.

The wrench estimator is pluggable: :func:`oracle_estimator` (the simulator's own base wrench) or
:class:`CNNWrenchEstimator` (the trained wrench CNN on the depth image, thesis §3.4).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.fem.bodies import check_rigid_transform
from defgraspnets.tactile.indenters import (
    CapsuleIndenter,
    IndenterError,
    PokeCommand,
    Pose,
    SphereIndenter,
    WorkspaceError,
)
from defgraspnets.tactile.sensor import Indentation, MembraneSimulator, TactileReading

__all__ = [
    "ESTIMATORS",
    "CNNWrenchEstimator",
    "ClosedLoopRun",
    "CorrectionGains",
    "Fingertip",
    "check_estimator",
    "forearm_rest_indentation",
    "forearm_support_runs",
    "make_estimator",
    "oracle_estimator",
    "place_fingertip",
    "pose_correction_runs",
    "pose_correction_step",
    "read_fingertip",
    "run_forearm_support",
    "run_pose_correction",
    "shear_twist_schedule",
]

#: a wrench estimator: one reading -> (6,) [N, N m] in the sensor frame
WrenchEstimator = Callable[[TactileReading], np.ndarray]


# ------------------------------------------------------------------------------ law
@dataclass(frozen=True)
class CorrectionGains:
    """Gains of the §3.5 law and the per-step clamp.

    Attributes:
        force_gain: k_F [m/N] (thesis: 0.1).
        torque_gain: k_tau [rad/(N m)] (thesis: 2).
        max_translation: dp_max, largest position step [m] (the step is scaled down, not cut per axis).
        max_rotation: dtheta_max, largest rotation step [rad] (norm of the rotation vector k_tau tau).
    """

    force_gain: float = 0.1
    torque_gain: float = 2.0
    max_translation: float = 0.001
    max_rotation: float = 0.01

    def __post_init__(self):
        for name in ("force_gain", "torque_gain", "max_translation", "max_rotation"):
            v = getattr(self, name)
            if not (np.isscalar(v) and np.isfinite(v) and v >= 0):
                raise ValueError(f"CorrectionGains.{name} must be a finite number >= 0, got {v!r}")


def _clamp(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v if n <= limit else v * (limit / n)


def pose_correction_step(sensor_pose, wrench, gains: CorrectionGains = CorrectionGains()) -> np.ndarray:
    """One update of the §3.5 law (module docstring): the sensor's next world pose (4, 4).

    Args:
        sensor_pose: (4, 4) sensor pose in the world.
        wrench: (6,) estimated (F [N], tau [N m]) in the sensor frame, about the sensor origin.
    """
    S = check_rigid_transform(sensor_pose, "sensor_pose", single=True)
    w = np.asarray(wrench, dtype=np.float64)
    if w.shape != (6,) or not np.all(np.isfinite(w)):
        raise ValueError(f"wrench must be a finite (6,) vector [N, N m], got {np.shape(wrench)}")
    R = S[:3, :3]
    out = S.copy()
    out[:3, 3] += _clamp(gains.force_gain * (R @ w[:3]), gains.max_translation)
    angles = _clamp(gains.torque_gain * w[3:], gains.max_rotation)
    out[:3, :3] = R @ Rotation.from_euler("XYZ", angles).as_matrix()  # R_x R_y R_z, body axes
    return out


# ------------------------------------------------------------------------------ estimators
def oracle_estimator(reading: TactileReading) -> np.ndarray:
    """The simulator's own base wrench (what an ideal wrist F/T sensor reads)."""
    return np.asarray(reading.base_wrench, dtype=np.float64).copy()


class CNNWrenchEstimator:
    """The trained wrench CNN (:class:`~defgraspnets.models.wrench_module.WrenchRegressionModule`) on the
    reading's depth image.

    Args:
        module: a loaded module (``predict_wrench``), or use :meth:`from_checkpoint`.
        reference: undeformed depth image (H, W) the CNN compares against; None = the one stored in the
            checkpoint (from its training data).
    """

    def __init__(self, module, reference=None):
        if not hasattr(module, "predict_wrench"):
            raise TypeError(f"module must provide predict_wrench, got {type(module).__name__}")
        self.module = module
        self.reference = None if reference is None else np.asarray(reference, dtype=np.float32)

    @classmethod
    def from_checkpoint(cls, path, reference=None, map_location="cpu") -> CNNWrenchEstimator:
        """Load ``path`` (FileNotFoundError with the path if it is missing)."""
        from defgraspnets.models.wrench_module import WrenchRegressionModule

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"wrench CNN checkpoint not found: {path} (train one, e.g. scripts/wrench_pipeline.sh, "
                "or run with estimator=oracle)"
            )
        return cls(WrenchRegressionModule.from_checkpoint(path, map_location=map_location), reference)

    def __call__(self, reading: TactileReading) -> np.ndarray:
        if reading.depth is None:
            raise ValueError("the CNN estimator needs rendered readings (a simulator with a camera)")
        import torch

        with torch.no_grad():
            w = self.module.predict_wrench(reading.depth.depth, reference=self.reference)
        return np.asarray(w, dtype=np.float64).reshape(6)


#: the wrench estimators :func:`make_estimator` builds
ESTIMATORS = ("oracle", "cnn")


def check_estimator(kind: str, ckpt_path=None, cnn_reference: str = "checkpoint") -> None:
    """Check an estimator choice before any simulation: ``kind`` one of :data:`ESTIMATORS` (ValueError);
    for ``"cnn"`` the checkpoint ``ckpt_path`` must exist (FileNotFoundError naming it) and
    ``cnn_reference`` be ``"checkpoint"`` or ``"simulator"`` (ValueError)."""
    if kind not in ESTIMATORS:
        raise ValueError(f"estimator must be 'oracle' or 'cnn', got {kind!r}")
    if kind != "cnn":
        return
    if ckpt_path is None or not Path(ckpt_path).is_file():
        raise FileNotFoundError(
            f"wrench CNN checkpoint not found: {ckpt_path} (train it first, or run estimator=oracle)"
        )
    if cnn_reference not in ("checkpoint", "simulator"):
        raise ValueError(f"cnn_reference must be 'checkpoint' or 'simulator', got {cnn_reference!r}")


def make_estimator(
    kind: str, sim: MembraneSimulator, ckpt_path=None, cnn_reference: str = "checkpoint"
) -> WrenchEstimator:
    """The wrench estimator ``kind`` (checked by :func:`check_estimator`) for ``sim``: the oracle, or the
    CNN of ``ckpt_path`` comparing against the checkpoint's undeformed image (``cnn_reference=
    "checkpoint"``) or ``sim``'s own (``"simulator"``)."""
    check_estimator(kind, ckpt_path, cnn_reference)
    if kind == "oracle":
        return oracle_estimator
    reference = sim.reference_depth().depth if cnn_reference == "simulator" else None
    return CNNWrenchEstimator.from_checkpoint(ckpt_path, reference=reference)


# ------------------------------------------------------------------------------ records
@dataclass
class ClosedLoopRun:
    """One closed-loop run (n control steps).

    Attributes:
        poses: (n + 1, 4, 4) sensor poses in the world; step k reads at poses[k] and moves to poses[k + 1].
        true_wrench: (n, 6) the simulator's base wrench [N, N m], sensor frame (tared for forearm support).
        estimated_wrench: (n, 6) the estimator's wrench the law used (tared likewise).
        contact: (n,) whether the indenter touched the membrane.
        indentation: (n,) pose correction: the fingertip's depth beyond first contact [m] along its push
            direction; forearm support: the press depth.
        stopped: why the run ended early ("" = all steps done).
        push_direction: (3,) world unit vector of the initial push (pose correction) or None.
    """

    poses: np.ndarray
    true_wrench: np.ndarray
    estimated_wrench: np.ndarray
    contact: np.ndarray
    indentation: np.ndarray
    stopped: str = ""
    push_direction: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def positions(self) -> np.ndarray:
        """(n + 1, 3) sensor origin in the world [m]."""
        return self.poses[:, :3, 3]

    @property
    def displacement(self) -> np.ndarray:
        """(n + 1, 3) sensor origin minus its start [m] (world frame)."""
        return self.positions - self.positions[0]

    @property
    def rotation(self) -> np.ndarray:
        """(n + 1, 3) rotation vector of R_0^T R_k [rad]: the turn since the start, in its body axes."""
        R0 = self.poses[0, :3, :3]
        return np.stack([Rotation.from_matrix(R0.T @ T[:3, :3]).as_rotvec() for T in self.poses])

    @property
    def force_magnitude(self) -> np.ndarray:
        """(n,) |F| of the true wrench [N]."""
        return np.linalg.norm(self.true_wrench[:, :3], axis=1)

    def to_dict(self) -> dict:
        out = {
            "steps": len(self.contact),
            "stopped": self.stopped,
            "poses": self.poses.tolist(),
            "displacement_m": self.displacement.tolist(),
            "rotation_rad": self.rotation.tolist(),
            "true_wrench": self.true_wrench.tolist(),
            "estimated_wrench": self.estimated_wrench.tolist(),
            "force_magnitude_N": self.force_magnitude.tolist(),
            "contact": self.contact.tolist(),
            "indentation_m": self.indentation.tolist(),
            **self.meta,
        }
        if self.push_direction is not None:
            out["push_direction"] = self.push_direction.tolist()
            out["displacement_along_push_m"] = (self.displacement @ self.push_direction).tolist()
        return out


# ------------------------------------------------------------------------------ pose correction
@dataclass(frozen=True)
class Fingertip:
    """A rigid spherical fingertip fixed in the world: its centre (3,) [m] and the unit direction (3,) along
    which it pushed in (world frame; the approach used for every quasi-static solve)."""

    center: np.ndarray
    direction: np.ndarray

    def __post_init__(self):
        c = np.asarray(self.center, dtype=np.float64)
        d = np.asarray(self.direction, dtype=np.float64)
        if c.shape != (3,) or d.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(d))):
            raise ValueError("Fingertip center and direction must be finite (3,) vectors")
        if np.linalg.norm(d) < 1e-12:
            raise ValueError("Fingertip direction must be non-zero")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "direction", d / np.linalg.norm(d))


def _require_sphere(sim: MembraneSimulator) -> None:
    if not isinstance(sim, MembraneSimulator):
        raise TypeError(f"sim must be a MembraneSimulator, got {type(sim).__name__}")
    if not isinstance(sim.indenter, SphereIndenter):
        raise IndenterError(f"the fingertip is a sphere indenter, got {type(sim.indenter).__name__}")


def place_fingertip(
    sim: MembraneSimulator, command: PokeCommand, sensor_pose=None, backoff: float = 0.01
) -> Fingertip:
    """The world fingertip of a poke: it approaches the contact point (``command.phi``,
    ``command.contact_radius``) along ``command.direction()`` and sits ``command.depth`` [m] beyond first
    contact with the *inflated* membrane of the sensor at ``sensor_pose``."""
    _require_sphere(sim)
    S = check_rigid_transform(np.eye(4) if sensor_pose is None else sensor_pose, "sensor_pose", single=True)
    d = command.direction()
    p, n = sim.sensor.dimensions.outer_surface_point(command.phi, command.contact_radius)
    start = p + sim.indenter.radius * n - backoff * d
    t0 = sim.onset_travel(Indentation(Pose(start), 0.0, tuple(d)))
    center = start + (t0 + command.depth) * d
    return Fingertip(S[:3, :3] @ center + S[:3, 3], S[:3, :3] @ d)


def read_fingertip(
    sim: MembraneSimulator, sensor_pose, fingertip: Fingertip, render: bool = True, max_step: float = 0.002
) -> tuple[TactileReading, float]:
    """Solve the sensor at ``sensor_pose`` with the fixed ``fingertip``; returns (reading, depth [m]).

    The fingertip's centre and push direction are taken into the sensor frame (inverse(S) . T_fingertip)
    and the sphere is pressed along that direction from first contact to its centre (depth > 0). Out of
    reach (depth <= 0, or its line of approach misses the membrane) gives the inflated reference reading
    (zero wrench, reference image) and depth 0.
    """
    _require_sphere(sim)
    S = check_rigid_transform(sensor_pose, "sensor_pose", single=True)
    R, p = S[:3, :3], S[:3, 3]
    c = R.T @ (fingertip.center - p)
    d = R.T @ fingertip.direction
    try:
        t0 = sim.onset_travel(Indentation(Pose(c), 0.0, tuple(d)))
    except WorkspaceError:
        t0 = np.inf  # the approach line never meets the membrane
    depth = -float(t0)
    if not depth > 0:
        ref = sim.reference
        frame = sim.reference_depth() if render and sim.camera is not None else None
        reading = TactileReading(
            positions=ref.positions.copy(),
            depth=frame,
            contact_force=np.zeros(3),
            base_wrench=np.zeros(6),
            rim_force=ref.rim_force.copy(),
            gauge_pressure=ref.gauge_pressure,
            gas_volume=ref.gas_volume,
            depth_travel=0.0,
            indenter_position=c,
            indenter_pose=Pose(c),
            converged=True,
            solve_time=0.0,
        )
        return reading, 0.0
    reading = sim.indent(
        [Indentation(Pose(c - depth * d), depth, tuple(d))], render=render, max_step=max_step
    )[0]
    return reading, depth


def run_pose_correction(
    sim: MembraneSimulator,
    fingertip: Fingertip,
    estimator: WrenchEstimator = oracle_estimator,
    steps: int = 5,
    gains: CorrectionGains = CorrectionGains(),
    sensor_pose=None,
    render: bool | None = None,
    max_step: float = 0.002,
    callback: Callable[[int, ClosedLoopRun], None] | None = None,
) -> ClosedLoopRun:
    """End-effector pose correction (thesis Fig. 3.9) against a fixed fingertip, ``steps`` control steps.

    ``render`` (default: only when the estimator is not the oracle) renders the depth image each step.
    A failed FEM solve stops the run (``stopped`` says so; its step is not recorded).
    """
    _require_sphere(sim)
    if not callable(estimator):
        raise TypeError("estimator must be callable: reading -> (6,) wrench")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if render is None:
        render = estimator is not oracle_estimator
    S = check_rigid_transform(np.eye(4) if sensor_pose is None else sensor_pose, "sensor_pose", single=True)
    poses, true_w, est_w, contact, depth = [S], [], [], [], []
    stopped = ""
    run = None
    for k in range(int(steps)):
        reading, delta = read_fingertip(sim, S, fingertip, render=render, max_step=max_step)
        if not reading.converged:
            stopped = f"FEM solve failed at step {k}"
            break
        w_est = np.asarray(estimator(reading), dtype=np.float64).reshape(6)
        true_w.append(reading.base_wrench.copy())
        est_w.append(w_est)
        contact.append(delta > 0)
        depth.append(delta)
        S = pose_correction_step(S, w_est, gains)
        poses.append(S)
        run = _record(poses, true_w, est_w, contact, depth, "", fingertip.direction)
        if callback is not None:
            callback(k, run)
    run = _record(poses, true_w, est_w, contact, depth, stopped, fingertip.direction)
    run.meta.update(gains=asdict(gains), application="pose_correction")
    return run


def _record(poses, true_w, est_w, contact, depth, stopped, push) -> ClosedLoopRun:
    return ClosedLoopRun(
        poses=np.stack(poses),
        true_wrench=np.array(true_w, dtype=np.float64).reshape(-1, 6),
        estimated_wrench=np.array(est_w, dtype=np.float64).reshape(-1, 6),
        contact=np.array(contact, dtype=bool),
        indentation=np.array(depth, dtype=np.float64),
        stopped=stopped,
        push_direction=None if push is None else np.asarray(push, dtype=np.float64),
    )


# ------------------------------------------------------------------------------ forearm support
def forearm_rest_indentation(sim: MembraneSimulator, depth: float, backoff: float = 0.01) -> Indentation:
    """The forearm's rest press: the capsule (axis along sensor x) lowered onto the pole by ``depth`` [m]
    beyond first contact, as :func:`~defgraspnets.tactile.datasets.forearm_paths`."""
    if not isinstance(sim.indenter, CapsuleIndenter):
        raise IndenterError(f"the forearm is a capsule indenter, got {type(sim.indenter).__name__}")
    top = sim.sensor.dimensions.outer_pole + np.array([0.0, 0.0, sim.indenter.radius + backoff])
    return Indentation(Pose(top), depth, (0.0, 0.0, -1.0))


def shear_twist_schedule(
    steps: int, shear_per_step=(0.0, 0.0, 0.0), twist_per_step: float = 0.0
) -> np.ndarray:
    """(steps, 4, 4) world motions of the forearm relative to its rest pose: after step k it has moved by
    (k + 1) x ``shear_per_step`` [m] and turned by (k + 1) x ``twist_per_step`` [rad] about the world z axis
    through its rest position (applied as T_k A_rest with the turn about the rest centre: see
    :func:`run_forearm_support`)."""
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    s = np.asarray(shear_per_step, dtype=np.float64)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or not np.isfinite(twist_per_step):
        raise ValueError("shear_per_step must be a finite (3,) vector [m] and twist_per_step finite [rad]")
    out = np.broadcast_to(np.eye(4), (int(steps), 4, 4)).copy()
    for k in range(int(steps)):
        out[k, :3, :3] = Rotation.from_rotvec([0.0, 0.0, (k + 1) * twist_per_step]).as_matrix()
        out[k, :3, 3] = (k + 1) * s
    return out


def run_forearm_support(
    sim: MembraneSimulator,
    arm_motions,
    depth: float = 0.004,
    estimator: WrenchEstimator = oracle_estimator,
    gains: CorrectionGains = CorrectionGains(),
    sensor_pose=None,
    render: bool | None = None,
    max_step: float = 0.002,
) -> ClosedLoopRun:
    """Forearm support (thesis Fig. 3.10): the sensor follows a forearm that is sheared / twisted.

    The forearm rests pressed ``depth`` [m] on the sensor at ``sensor_pose`` (S_0); its rest world pose is
    A_0 = S_0 P (P: the pressed pose in the sensor frame). ``arm_motions`` (n, 4, 4) move it: at step k it
    is at A_k = A_0 D_k with D_k the motion about the rest centre, expressed in the rest frame (so
    :func:`shear_twist_schedule`'s translation and z-turn act along/about the sensor's rest axes). The
    wrench is tared at rest (thesis: "the force is initially zeroed at the resting position").
    The relative path between sensor and arm (before and after each sensor update) is replayed from the
    press every step, so friction history is exact; the cost grows with the step count.
    """
    if not isinstance(sim, MembraneSimulator):
        raise TypeError(f"sim must be a MembraneSimulator, got {type(sim).__name__}")
    press = forearm_rest_indentation(sim, depth)
    D = np.asarray(arm_motions, dtype=np.float64)
    if D.ndim != 3 or D.shape[1:] != (4, 4) or len(D) == 0:
        raise ValueError(f"arm_motions must have shape (n, 4, 4), got {np.shape(arm_motions)}")
    for i, m in enumerate(D):
        check_rigid_transform(m, f"arm_motions[{i}]", single=True)
    if render is None:
        render = estimator is not oracle_estimator
    S = check_rigid_transform(np.eye(4) if sensor_pose is None else sensor_pose, "sensor_pose", single=True)
    rest = sim.press_and_move([press], [np.eye(4)], render=render, max_step=max_step)[0][0]
    if not rest.converged:
        raise RuntimeError("the forearm's rest press did not converge")
    P = np.eye(4)
    P[:3, :3] = rest.indenter_pose.rotation.as_matrix()
    P[:3, 3] = rest.indenter_pose.position
    A0 = S @ P
    true_rest, est_rest = rest.base_wrench.copy(), np.asarray(estimator(rest), dtype=np.float64).reshape(6)
    P_inv = np.linalg.inv(P)

    def relative(S_, A_):  # the arm's motion in the sensor frame, applied to the pressed pose P
        return np.linalg.inv(S_) @ A_ @ P_inv

    history, poses, true_w, est_w, contact, depths = [], [S], [], [], [], []
    stopped = ""
    for k, Dk in enumerate(D):
        A = A0 @ Dk
        history.append(relative(S, A))
        reading = sim.press_and_move([press], np.stack(history), render=render, max_step=max_step)[-1][0]
        if not reading.converged:
            stopped = f"FEM solve failed (or the forearm slipped off) at step {k}"
            break
        w_true = reading.base_wrench - true_rest
        w_est = np.asarray(estimator(reading), dtype=np.float64).reshape(6) - est_rest
        true_w.append(w_true)
        est_w.append(w_est)
        contact.append(bool(np.linalg.norm(reading.contact_force) > 0))
        depths.append(depth)
        S = pose_correction_step(S, w_est, gains)
        poses.append(S)
        history.append(relative(S, A))
    run = _record(poses, true_w, est_w, contact, depths, stopped, None)
    run.meta.update(
        application="forearm_support",
        rest_wrench=true_rest.tolist(),
        arm_positions=[(A0 @ Dk)[:3, 3].tolist() for Dk in D[: len(true_w)]],
        arm_rotation=[
            Rotation.from_matrix((A0 @ Dk)[:3, :3]).as_rotvec().tolist() for Dk in D[: len(true_w)]
        ],
    )
    return run


# ------------------------------------------------------------------------------ experiments
def pose_correction_runs(
    sim: MembraneSimulator,
    pokes: Mapping[str, Mapping],
    estimator: WrenchEstimator = oracle_estimator,
    steps: int = 5,
    gains: CorrectionGains = CorrectionGains(),
    log: Callable[[str], None] | None = print,
) -> tuple[dict[str, ClosedLoopRun], dict[str, dict]]:
    """Pose correction (:func:`run_pose_correction`, ``steps`` steps) against the fingertip of each named
    poke (keyword arguments of :class:`~defgraspnets.tactile.indenters.PokeCommand`, placed by
    :func:`place_fingertip` on the sensor at the identity).

    Returns:
        the runs by name, and their JSON-ready entries: ``poke``, :meth:`ClosedLoopRun.to_dict`,
        ``wall_time_s``. ``log`` gets one line per run (None: quiet).
    """
    runs, entries = {}, {}
    for name, poke in pokes.items():
        t = time.perf_counter()
        poke = dict(poke)
        tip = place_fingertip(sim, PokeCommand(**poke))
        runs[name] = run = run_pose_correction(sim, tip, estimator, steps=steps, gains=gains)
        entries[name] = {"poke": poke, **run.to_dict(), "wall_time_s": time.perf_counter() - t}
        if log is not None:
            log(
                f"{name}: |F| {np.round(run.force_magnitude, 3).tolist()} N, displacement along push "
                f"{np.round(run.displacement @ run.push_direction, 5).tolist()} m, "
                f"rotation {np.round(run.rotation[-1], 4).tolist()} rad"
            )
    return runs, entries


def forearm_support_runs(
    arm: MembraneSimulator,
    steps: int = 3,
    shear_per_step: Sequence[float] = (0.0, 0.002, 0.0),
    twist_per_step: float = 0.05,
    depth: float = 0.004,
    estimator: WrenchEstimator = oracle_estimator,
    gains: CorrectionGains = CorrectionGains(),
    log: Callable[[str], None] | None = print,
) -> tuple[dict[str, ClosedLoopRun], dict[str, dict]]:
    """Forearm support (:func:`run_forearm_support`, rest press ``depth`` [m]) twice, ``steps`` steps each:
    ``forearm_shear`` (the arm sheared by ``shear_per_step`` [m] per step) and ``forearm_twist`` (turned
    by ``twist_per_step`` [rad] per step about the world z axis).

    Returns:
        the runs by name, and their JSON-ready entries (:meth:`ClosedLoopRun.to_dict`, ``wall_time_s``).
        ``log`` gets one line per run (None: quiet).
    """
    runs, entries = {}, {}
    for name, shear, twist in [
        ("forearm_shear", shear_per_step, 0.0),
        ("forearm_twist", [0.0, 0.0, 0.0], twist_per_step),
    ]:
        t = time.perf_counter()
        runs[name] = run = run_forearm_support(
            arm,
            shear_twist_schedule(steps, list(shear), float(twist)),
            depth=depth,
            estimator=estimator,
            gains=gains,
        )
        entries[name] = {**run.to_dict(), "wall_time_s": time.perf_counter() - t}
        if log is not None:
            log(
                f"{name}: sensor displacement {np.round(run.displacement[-1], 5).tolist()} m, "
                f"rotation {np.round(run.rotation[-1], 4).tolist()} rad"
            )
    return runs, entries
