# ruff: noqa: E501
"""What moves in the failed load increments of a squeeze ramp (benchmarks/squeeze_soft_failures_cpu.md).

One grasp per solver (the data path's grasps), 0 -> 15 N in ``--steps`` steps (or, with ``--travel T``, the
grip's travel 0 -> T mm in ``--steps`` travel-controlled steps); every load increment's attempt is recorded
with the state Newton left it in (before a failed one is restored): grip travel, force, Newton iterations,
the object's drift across the grasp axis, its rigid turn, min det F and the largest vertex move against the
last converged state.

    python scripts/squeeze_failed_attempts.py cuboid_70x35x20 1e4 0 --out out.json
"""

import argparse
import json

import numpy as np

from defgraspnets import fem
from defgraspnets.grasp.datagen import resolve_object_mesh
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import (
    FINGER_NAMES,
    GRIP_DOF,
    finger_contact_poses,
    make_squeeze_solver,
    pad_shape,
    squeeze_ramp,
    squeeze_solver_options,
)


def geometry(mesh, x, R0):
    u = x - mesh.points
    c = u.mean(axis=0)
    drift = c - (c @ R0[:, 1]) * R0[:, 1]
    X0 = mesh.points - mesh.points.mean(axis=0)
    U, _, Vt = np.linalg.svd(X0.T @ (x - x.mean(axis=0)))
    Rb = (U @ Vt).T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(Rb) - 1) / 2, -1, 1))))
    T = mesh.tets
    Dm = np.stack([mesh.points[T[:, i]] - mesh.points[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    Ds = np.stack([x[T[:, i]] - x[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    J = np.linalg.det(Ds) / np.linalg.det(Dm)
    return dict(drift_mm=float(np.linalg.norm(drift) * 1e3), turn_deg=ang, min_J=float(J.min()))


def parse_overrides(items):
    out = {}
    for kv in items:
        k, v = kv.split("=")
        out[k] = type(getattr(fem.SolverOptions(), k))(float(v) if "." in v or "e" in v else int(v))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("object")
    ap.add_argument("E", type=float)
    ap.add_argument("grasp", type=int)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--travel", type=float, default=0.0, help="travel control to this travel [mm]")
    ap.add_argument("--from-step", type=int, default=0, help="record attempts from this step on")
    ap.add_argument(
        "--debug-from-step", type=int, default=-1, help="solver DEBUG log (Newton residuals) from it"
    )
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    mesh = resolve_object_mesh(a.object, target_nodes=1000)
    grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    material = fem.Material(a.E, 0.3, 1000.0, model="neohookean")
    opts = squeeze_solver_options(linear_solver="direct", **parse_overrides(a.set))
    poses = finger_contact_poses(grasps[[a.grasp]])
    if a.travel:
        bodies = [
            fem.RigidBody(
                n, pad_shape(), control=fem.Control.displacement((0, 1, 0), dof=GRIP_DOF), friction=0.7
            )
            for n in FINGER_NAMES
        ]
        solver = fem.QuasiStaticSolver(mesh, bodies, material, batch_size=1, device="cpu", options=opts)
        for i, n in enumerate(FINGER_NAMES):
            solver.set_body_pose(n, poses[:, i])
    else:
        solver = make_squeeze_solver(mesh, grasps[[a.grasp]], material, 0.7, device="cpu", options=opts)
    R0 = poses[0, 0, :3, :3]
    N, D = mesh.num_vertices, solver.num_dofs
    attempts, step = [], [0]
    finish = solver._finish_increments

    import logging

    def spy(path, run, done):
        if 0 <= a.debug_from_step <= step[0] + 1:
            logging.basicConfig(format="%(message)s")
            logging.getLogger("defgraspnets.fem.solver").setLevel(logging.DEBUG)
        if step[0] >= a.from_step:
            x = solver._positions.numpy()[:N].astype(float)
            xref = solver._positions_ref.numpy()[:N].astype(float)
            g = geometry(mesh, x, R0)
            attempts.append(
                dict(
                    step=step[0],
                    lam_done=float(path.lam_done[0]),
                    lam_try=float(path.lam_try[0]),
                    ok=bool(run.ok[0]),
                    status=int(run.status[0]),
                    iters=int(run.iters[0]),
                    travel_mm=float(solver._travel.numpy()[:D][0] * 1e3),
                    travel_ref_mm=float(solver._travel_ref.numpy()[:D][0] * 1e3),
                    force=float(solver._dof_force.numpy()[0]),
                    max_move_mm=float(np.linalg.norm(x - xref, axis=1).max() * 1e3),
                    **g,
                )
            )
            t = attempts[-1]
            print(
                f"  step {t['step']} lam {t['lam_done']:.3f}->{t['lam_try']:.3f} ok {t['ok']} st {t['status']} "
                f"it {t['iters']} travel {t['travel_ref_mm']:.3f}->{t['travel_mm']:.3f} F {t['force']:.3f} "
                f"move {t['max_move_mm']:.2f} drift {t['drift_mm']:.2f} turn {t['turn_deg']:.2f} minJ {t['min_J']:.3f}",
                flush=True,
            )
        return finish(path, run, done)

    solver._finish_increments = spy
    rows = []
    if a.travel:
        for k, tr in enumerate(np.linspace(0, a.travel * 1e-3, a.steps + 1)[1:]):
            step[0] = k
            eq = solver.solve(targets={GRIP_DOF: float(tr)})
            rows.append(dict(travel_mm=float(eq.travel[GRIP_DOF][0] * 1e3), force=float(eq.dof_force[GRIP_DOF][0]),
                             status=int(eq.status[0])))  # fmt: skip
            print(f"step {k}: travel {rows[-1]['travel_mm']:.3f} force {rows[-1]['force']:.3f} st {rows[-1]['status']}",
                  flush=True)  # fmt: skip
            if eq.status[0]:
                break
    else:

        def on_level(k, eq):
            step[0] = k + 1
            rows.append(dict(travel_mm=float(eq.travel[GRIP_DOF][0] * 1e3), force=float(eq.dof_force[GRIP_DOF][0]),
                             status=int(eq.status[0])))  # fmt: skip

        squeeze_ramp(solver, 15.0, a.steps, on_step=lambda k, f, eq: on_level(k, eq))
        print("statuses", [r["status"] for r in rows][-3:], flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(dict(args=vars(a), steps=rows, attempts=attempts), f)


if __name__ == "__main__":
    main()
