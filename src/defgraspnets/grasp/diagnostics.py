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
) -> list[dict]:
    """Walk one grasp (a one-grasp ``GraspSet``) with both pads displacement-controlled to each of the
    increasing ``travels`` [m] in turn; stops at the first failed step. Returns per step ``travel_mm``,
    ``force`` (the grip's total normal force [N]), ``status`` and ``newton`` iterations."""
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
    for target in travels:
        eq = solver.solve(targets={GRIP_DOF: float(target)})
        rows.append(
            {
                "travel_mm": float(eq.travel[GRIP_DOF][0] * 1e3),
                "force": float(eq.dof_force[GRIP_DOF][0]),
                "status": int(eq.status[0]),
                "newton": int(eq.newton_iterations[0]),
            }
        )
        if eq.status[0] != 0:
            break
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
