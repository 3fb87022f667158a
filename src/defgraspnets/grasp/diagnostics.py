"""What a squeezed object is doing: geometry of one squeeze state against the pads, for tracing failed ramps.

A squeeze ramp that stops (``FORCE_MAXIMUM``, ``NOT_CONVERGED``) leaves its last converged state; these
functions say what that state looks like, in the terms that tell a real grasp failure from a numerical one
(``benchmarks/squeeze_soft_failures_cpu.md``): how far the object drifted across the grasp axis and turned
(a hinge about a pad's edge, a roll), how crushed its elements are (det F), where the pads touch it, how far
the contacts slid along the pads and whether material wraps around a pad's rim. ``travel_controlled_path``
walks the same grasp under displacement control, where a force-controlled ramp cannot pass a limit point:
its force against travel shows whether the path has a force maximum at all.

Used by ``scripts/squeeze_soft_failures.py`` and ``scripts/squeeze_force_maximum_trace.py``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from defgraspnets import fem

from .gripper import FRANKA_HAND, ParallelJawGripper
from .metrics import best_rigid_transform
from .squeeze import FINGER_NAMES, GRIP_DOF, finger_contact_poses, pad_shape

__all__ = [
    "deformation_jacobians",
    "rigid_turn",
    "squeeze_state_geometry",
    "travel_controlled_path",
]


def deformation_jacobians(mesh: fem.TetMesh, points) -> np.ndarray:
    """(M,) det F of every tet at the deformed ``points`` (N, 3): volume ratio to rest (< 0: inverted)."""
    x = np.asarray(points, dtype=np.float64)
    if x.shape != mesh.points.shape:
        raise ValueError(f"points must be {mesh.points.shape}, got {x.shape}")
    T = mesh.tets
    rest = np.stack([mesh.points[T[:, i]] - mesh.points[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    now = np.stack([x[T[:, i]] - x[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    return np.linalg.det(now) / np.linalg.det(rest)


def rigid_turn(mesh: fem.TetMesh, points) -> tuple[float, np.ndarray]:
    """Angle [rad] and unit axis of the best-fit rotation (Kabsch) that takes the rest shape to ``points``."""
    R, _ = best_rigid_transform(mesh.points, np.asarray(points, dtype=np.float64))
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    norm = np.linalg.norm(axis)
    return angle, (axis / norm if norm > 1e-15 else np.array([0.0, 0.0, 1.0]))


def squeeze_state_geometry(
    mesh: fem.TetMesh,
    displacement,
    finger_poses,
    travel: float,
    contact_normal_force: dict,
    contact_threshold: float,
    gripper: ParallelJawGripper = FRANKA_HAND,
) -> dict:
    """The object of one squeeze state against the two pads, as plain numbers (lengths in mm, angles in deg).

    Args:
        mesh: the object at rest.
        displacement: (N, 3) its displacement [m].
        finger_poses: (2, 4, 4) the fingers' frames at first contact (``finger_contact_poses`` of the grasp:
            pad face at y = 0, closing along +y).
        travel: each pad's travel along its closing direction from first contact [m].
        contact_normal_force: {finger name: (S,) normal contact force per surface vertex [N]} of this state
            (``Equilibrium.contact_normal_force[name][problem]``).
        contact_threshold: a vertex touches a pad where its normal force exceeds this [N].
        gripper: the pads' size.

    Returns: ``travel_mm``; ``gap0_mm`` / ``gap_mm`` between the pad faces at first contact / now;
    ``drift_mm`` (the centroid's move across the grasp axis) and ``drift_pad_xz_mm`` (along the first pad's x
    and z); ``turn_deg`` (best-fit rigid turn) and ``turn_axis_vs_grasp_deg``; ``min_J`` and
    ``tets_J_below_0.2``; and per pad (``pads``): ``contacts``, ``normal_force``, the contacts' slide along
    the pad (``slip_mean_mm``, ``slip_max_mm``), ``contacts_off_face`` (beyond the pad's face), ``wrap_mm``
    (how far surface material outside the face lies behind the moved face plane: the pad sank in by that
    much), the contact patch's extent (``contact_x_extent_mm``, ``contact_z_extent_mm``) and
    ``footprint_vertices_left`` (surface vertices in front of the face at rest that no longer touch it).
    """
    u = np.asarray(displacement, dtype=np.float64)
    poses = np.asarray(finger_poses, dtype=np.float64)
    if u.shape != mesh.points.shape or poses.shape != (2, 4, 4):
        raise ValueError(f"displacement must be {mesh.points.shape} and finger_poses (2, 4, 4)")
    x = mesh.points + u
    surf = mesh.surface_vertices
    width, _, length = gripper.pad_size
    R0 = poses[0, :3, :3]
    closing = R0[:, 1]
    out = {"travel_mm": travel * 1e3}
    out["gap0_mm"] = float(abs((poses[1, :3, 3] - poses[0, :3, 3]) @ closing) * 1e3)
    out["gap_mm"] = out["gap0_mm"] - 2 * travel * 1e3
    centroid = u.mean(axis=0)
    out["drift_mm"] = float(np.linalg.norm(centroid - (centroid @ closing) * closing) * 1e3)
    out["drift_pad_xz_mm"] = [float(centroid @ R0[:, 0] * 1e3), float(centroid @ R0[:, 2] * 1e3)]
    angle, axis = rigid_turn(mesh, x)
    out["turn_deg"] = float(np.degrees(angle))
    out["turn_axis_vs_grasp_deg"] = float(np.degrees(np.arccos(min(1.0, abs(axis @ closing)))))
    J = deformation_jacobians(mesh, x)
    out["min_J"], out["tets_J_below_0.2"] = float(J.min()), int((J < 0.2).sum())
    pads = []
    for i, name in enumerate(FINGER_NAMES):
        R, t = poses[i, :3, :3], poses[i, :3, 3]
        p = (x[surf] - t) @ R  # surface points in the finger frame at first contact
        p0 = (mesh.points[surf] - t) @ R
        force = np.asarray(contact_normal_force[name], dtype=np.float64)
        if force.shape != surf.shape:
            raise ValueError(
                f"contact_normal_force[{name!r}] must hold one force per surface vertex {surf.shape}"
            )
        c = force > contact_threshold
        slide = np.linalg.norm((u[surf] @ R)[:, [0, 2]], axis=1)  # along the pad (it moves along y only)
        off_face = (np.abs(p[:, 0]) > width / 2) | (np.abs(p[:, 2]) > length / 2)
        in_footprint = (np.abs(p0[:, 0]) < width / 2) & (np.abs(p0[:, 2]) < length / 2)
        behind = travel - p[:, 1]  # > 0: behind the moved pad's face plane
        pads.append(
            {
                "contacts": int(c.sum()),
                "normal_force": float(force.sum()),
                "slip_mean_mm": float(slide[c].mean() * 1e3) if c.any() else 0.0,
                "slip_max_mm": float(slide[c].max() * 1e3) if c.any() else 0.0,
                "contacts_off_face": int((c & off_face).sum()),
                "wrap_mm": float(max(behind[off_face].max(), 0.0) * 1e3) if off_face.any() else 0.0,
                "contact_x_extent_mm": float(np.ptp(p[c, 0]) * 1e3) if c.any() else 0.0,
                "contact_z_extent_mm": float(np.ptp(p[c, 2]) * 1e3) if c.any() else 0.0,
                "footprint_vertices_left": int((in_footprint & ~c & (p0[:, 1] > -1e-3)).sum()),
            }
        )
    out["pads"] = pads
    return out


def travel_controlled_path(
    mesh: fem.TetMesh,
    grasp,
    material: fem.Material,
    travels,
    friction: float = 0.7,
    options: fem.SolverOptions | None = None,
    device="cpu",
    trace: bool = False,
) -> list[dict]:
    """Walk one grasp (a one-grasp ``GraspSet``) with both pads displacement-controlled to each of the
    increasing ``travels`` [m] in turn; stops at the first failed step. Returns per step ``travel_mm``,
    ``force`` (the grip's total normal force [N]), ``status`` and ``newton`` iterations, and the converged
    state's ``self_intersection_summary`` (with self-contact on, its pairs too). ``trace``: each step's
    ``NewtonTrace`` records under ``trace`` (energy scans of its first 3 failed line searches)."""
    bodies = [
        fem.RigidBody(name, pad_shape(), control=fem.Control.displacement((0.0, 1.0, 0.0), dof=GRIP_DOF),
                      friction=friction)
        for name in FINGER_NAMES
    ]  # fmt: skip
    solver = fem.QuasiStaticSolver(mesh, bodies, material, batch_size=1, device=device, options=options)
    poses = finger_contact_poses(grasp)
    for i, name in enumerate(FINGER_NAMES):
        solver.set_body_pose(name, poses[:, i])
    rows = []
    tracer = NewtonTrace(solver) if trace else None
    for target in travels:
        if tracer is not None:
            tracer.records, tracer.scans = [], 3
        eq = solver.solve(targets={GRIP_DOF: float(target)})
        rows.append(
            {
                "travel_mm": float(eq.travel[GRIP_DOF][0] * 1e3),
                "force": float(eq.dof_force[GRIP_DOF][0]),
                "status": int(eq.status[0]),
                "newton": int(eq.newton_iterations[0]),
            }
        )
        if tracer is not None:
            rows[-1]["trace"] = tracer.records
        if eq.status[0] != 0:
            break
        on = solver if solver.options.self_contact > 0 else None
        rows[-1].update(self_intersection_summary(mesh, mesh.points + eq.displacement[0], on))
    if tracer is not None:
        tracer.close()
    return rows


def self_intersection_summary(mesh: fem.TetMesh, points, solver: fem.QuasiStaticSolver | None = None) -> dict:
    """How far a state (deformed ``points``, (N, 3)) passes through itself: the surface vertices strictly
    inside the object's own tets (``inside``, as the data path's check without self-contact), those of them
    deeper than self-contact holds (``inside_beyond_contact_depth``, the check with it;
    ``fem.self_contact.self_contact_depth``) and, where ``solver`` has self-contact on (and is at this
    state), its active pairs and their largest penetration [m]."""
    from defgraspnets.fem.self_contact import self_contact_depth

    x = np.asarray(points, dtype=float)
    beyond = mesh.surface_vertices_inside(x, depth=self_contact_depth(mesh))
    out = {"inside": int(mesh.surface_vertices_inside(x).size)}
    out["inside_beyond_contact_depth"] = int(beyond.size)
    if solver is not None and solver.options.self_contact > 0:
        force, penetration = solver.self_contact_forces()
        out["self_contact_pairs"] = int((penetration[0] > 0).sum())
        out["self_contact_max_penetration"] = float(penetration[0].max())
        out["self_contact_force_sum"] = float(np.abs(force[0]).sum() / 2)
    return out


def energy_along_newton_step(solver: fem.QuasiStaticSolver, steps) -> tuple[np.ndarray, np.ndarray]:
    """(len(steps), B) total energy Pi and its self-contact part at q + t dq for each step length t of
    ``steps``, with the solver's current state q, its last Newton direction dq (``system.increment``) and
    the self-contact pairs of its last assembly: the function its line search just compared. For tracing a
    line search that failed (its state and direction are still the solver's). Private solver internals."""
    B, T = solver.batch_size, solver._line_search_trials
    steps = np.asarray(steps, dtype=float)
    active = solver._active_array(np.ones(B, dtype=bool))
    total, contact = [], []
    for c0 in range(0, len(steps), T):
        chunk = steps[c0 : c0 + T]
        total.append(solver._energies_along(np.repeat(chunk[:, None], B, axis=1), active))
        states = len(chunk) * B
        sc = wp.zeros(states, dtype=wp.float64, device=solver.device)
        if solver._self_contact is not None:
            solver._self_contact.add_energy(
                solver._positions_trial, states, solver._youngs, *solver._self_contact_law(), active, sc
            )
        contact.append(sc.numpy().reshape(len(chunk), B))
    return np.concatenate(total), np.concatenate(contact)


class NewtonTrace:
    """Records every Newton iteration of ``solver`` (one problem): the line search's verdict and step, the
    residual (the solver's DEBUG log) and, after the step, the active self-contact pairs at the new state
    (the solver's model, and how many of them the "prism" rule would not hold), their largest penetration
    and summed force; at the first ``scans`` failed line searches (or steps cut below 1e-6 of the first
    trial) after the first ``scan_after`` iterations the energy along the tried step
    (``energy_along_newton_step``; after an accepted vanishing step, from the new state). ``records`` is
    a list of dicts, in order."""

    def __init__(
        self, solver: fem.QuasiStaticSolver, scans: int = 3, scan_points: int = 201, scan_after: int = 0
    ):
        import logging

        from defgraspnets.fem.self_contact import SelfContact

        self.solver, self.records, self.scans, self.scan_points = solver, [], scans, scan_points
        self.scan_after = scan_after
        self._residual = None
        self._prism = None
        if solver._self_contact is not None and solver._self_contact.model != "prism":
            self._prism = SelfContact(solver.mesh, solver.pattern, 1, solver.contact_length, solver.device)
        trace = self

        class _Handler(logging.Handler):
            def emit(self, record):
                if record.msg.startswith("newton it"):
                    trace._residual = float(record.args[2])

        self._logger = logging.getLogger("defgraspnets.fem.solver")
        self._handler = _Handler(logging.DEBUG)
        self._logger.addHandler(self._handler)
        # restored by close(): left at DEBUG, every later Newton iteration of the process would build a record
        self._logger_state = (self._logger.level, self._logger.disabled)
        self._logger.setLevel(logging.DEBUG)
        self._logger.disabled = False  # hydra's disabled job logging turns off the loggers that exist
        self._original = solver._line_search
        solver._line_search = self._line_search

    def close(self) -> None:
        self.solver._line_search = self._original
        self._logger.removeHandler(self._handler)
        self._logger.setLevel(self._logger_state[0])
        self._logger.disabled = self._logger_state[1]

    def _line_search(self, working, max_step):
        s = self.solver
        failed, first_trial, alpha = self._original(working, max_step)
        r = {
            "residual": self._residual,
            "line_search_failed": int(failed[0]),
            "first_trial": float(first_trial[0]),
            "alpha": float(alpha[0]),
            # gradient . dq of the step (the line search's predicted slope, < 0: a descent direction)
            "slope": float(s._step_stats.numpy()[0][0]),
        }
        stalled = failed[0] == 1 or alpha[0] < 1e-6 * first_trial[0]  # rejected, or a vanishing step
        if stalled and self.scans > 0 and len(self.records) >= self.scan_after:
            self.scans -= 1
            t = np.linspace(0.0, float(first_trial[0]), self.scan_points)
            total, contact = energy_along_newton_step(s, t)
            r["scan"] = {
                "t": t.tolist(),
                "energy": total[:, 0].tolist(),
                "self_contact": contact[:, 0].tolist(),
            }
        if s._self_contact is not None:
            # fresh pairs at the state after the step (the next assembly pairs anew)
            force, pen = s.self_contact_forces()
            r["pairs"] = int((pen[0] > 0).sum())
            r["max_penetration"] = float(pen[0].max())
            r["force_sum"] = float(np.abs(force[0]).sum() / 2)
            if self._prism is not None:
                law = s._self_contact_law()
                _, pen_prism = self._prism.forces(s._positions, s._youngs, *law)
                r["pairs_not_prism"] = int(((pen[0] > 0) & (pen_prism[0] == 0)).sum())
        self.records.append(r)
        return failed, first_trial, alpha
