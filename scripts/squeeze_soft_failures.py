# ruff: noqa: E501
"""Diagnose failing squeeze ramps of soft objects (benchmarks/squeeze_soft_failures_cpu.md).

For each grasp (one problem per solver, the data path's grasps: ``sample_antipodal_grasps(mesh, 100,
friction_coefficient=0.7, rotations_per_axis=4, seed=0)``), ramp 0 -> 15 N in ``steps`` steps with the squeeze
options (plus ``--set key=value`` overrides) and report, at the last converged step: force, grip travel per
pad, the gap left between the pads, contact vertices per pad, how far those vertices slid along the pads
(tangential displacement in the pad frame; the pads only move along their normals), the object's rigid
drift across the grasp axis (its centroid), how deep material wraps around a pad (surface vertices outside
the pad's footprint that lie behind the moved pad's face plane: the pad sank in by that much), min det F, the grasp's turn about the grasp axis.
Optionally continue a flagged ramp under *travel* control (``--travel-continue``): the force along the
equilibrium path past the last converged force step, to tell a real force maximum from a numerical one.

    python scripts/squeeze_soft_failures.py cuboid_70x35x20 1e4 0 4 8 --out out.json
"""

import argparse
import json
import time

import numpy as np

from defgraspnets import fem
from defgraspnets.grasp.datagen import resolve_object_mesh
from defgraspnets.grasp.gripper import FRANKA_HAND
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


def min_det_f(mesh, x):
    X = mesh.points
    T = mesh.tets
    Dm = np.stack([X[T[:, i]] - X[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    Ds = np.stack([x[T[:, i]] - x[T[:, 0]] for i in (1, 2, 3)], axis=-1)
    J = np.linalg.det(Ds) / np.linalg.det(Dm)
    return float(J.min()), int((J < 0.2).sum())


def state_metrics(mesh, eq, poses, travel, force_ref):
    """Geometry of problem 0 of ``eq`` against the pads (``poses`` (2, 4, 4) finger frames at first contact)."""
    u = eq.displacement[0]
    x = mesh.points + u
    surf = mesh.surface_vertices
    w, _, ln = FRANKA_HAND.pad_size
    out = dict(travel_mm=travel * 1e3)
    # pad faces at first contact: y = 0 in each finger frame, closing along +y; moved by `travel`
    R0, t0 = poses[0, :3, :3], poses[0, :3, 3]
    t1 = poses[1, :3, 3]
    out["gap0_mm"] = float(abs((t1 - t0) @ R0[:, 1]) * 1e3)
    out["gap_mm"] = out["gap0_mm"] - 2 * travel * 1e3
    centroid_u = u.mean(axis=0)
    out["drift_mm"] = float(np.linalg.norm(centroid_u - (centroid_u @ R0[:, 1]) * R0[:, 1]) * 1e3)
    out["drift_pad_xz_mm"] = [float(centroid_u @ R0[:, 0] * 1e3), float(centroid_u @ R0[:, 2] * 1e3)]
    # best-fit rigid turn of the whole object (Kabsch), degrees, and its axis against the grasp axis
    X0 = mesh.points - mesh.points.mean(axis=0)
    U, _, Vt = np.linalg.svd(X0.T @ (x - x.mean(axis=0)))
    Rb = (U @ Vt).T
    if np.linalg.det(Rb) < 0:
        U[:, -1] *= -1
        Rb = (U @ Vt).T
    ang = np.arccos(np.clip((np.trace(Rb) - 1) / 2, -1, 1))
    axis = np.array([Rb[2, 1] - Rb[1, 2], Rb[0, 2] - Rb[2, 0], Rb[1, 0] - Rb[0, 1]])
    out["turn_deg"] = float(np.degrees(ang))
    out["turn_axis_vs_grasp_deg"] = float(
        np.degrees(np.arccos(min(1.0, abs(axis @ R0[:, 1]) / max(np.linalg.norm(axis), 1e-15))))
    )
    mind, nbad = min_det_f(mesh, x)
    out["min_J"], out["tets_J_below_0.2"] = mind, nbad
    pads = []
    for i, name in enumerate(FINGER_NAMES):
        R, t = poses[i, :3, :3], poses[i, :3, 3]
        p = (x[surf] - t) @ R  # surface points in the finger frame at first contact
        p0 = (mesh.points[surf] - t) @ R
        fn = eq.contact_normal_force[name][0]
        c = fn > 1e-4 * max(force_ref, 1e-9)
        ut = (u[surf] @ R)[:, [0, 2]]
        outside = (np.abs(p[:, 0]) > w / 2) | (np.abs(p[:, 2]) > ln / 2)
        beyond = travel - p[:, 1]  # > 0: behind the moved pad's face plane (the pad sank into the object)
        inside_fp = (np.abs(p0[:, 0]) < w / 2) & (np.abs(p0[:, 2]) < ln / 2)
        pads.append(
            dict(
                contacts=int(c.sum()),
                normal_force=float(fn.sum()),
                slip_mean_mm=float(np.linalg.norm(ut[c], axis=1).mean() * 1e3) if c.any() else 0.0,
                slip_max_mm=float(np.linalg.norm(ut[c], axis=1).max() * 1e3) if c.any() else 0.0,
                contacts_off_face=int((c & outside).sum()),
                wrap_mm=float(max(beyond[outside].max(), 0.0) * 1e3) if outside.any() else 0.0,
                contact_x_extent_mm=float(np.ptp(p[c, 0]) * 1e3) if c.any() else 0.0,
                contact_z_extent_mm=float(np.ptp(p[c, 2]) * 1e3) if c.any() else 0.0,
                footprint_vertices_left=int((inside_fp & ~c & (p0[:, 1] > -1e-3)).sum()),
            )
        )
    out["pads"] = pads
    return out


def run_ramp(mesh, grasps, g, material, steps, overrides):
    options = squeeze_solver_options(linear_solver="direct", **overrides)
    solver = make_squeeze_solver(mesh, grasps[[g]], material, 0.7, device="cpu", options=options)
    t0 = time.perf_counter()
    eqs = squeeze_ramp(solver, 15.0, steps)
    return solver, eqs, time.perf_counter() - t0


def travel_continue(mesh, grasps, g, material, start_eq, start_travel, dtravel, nsteps):
    """Travel-controlled continuation from a converged state: (travel, force, status) per step."""
    pad = pad_shape()
    bodies = [
        fem.RigidBody(n, pad, control=fem.Control.displacement((0.0, 1.0, 0.0), dof=GRIP_DOF), friction=0.7)
        for n in FINGER_NAMES
    ]
    opts = squeeze_solver_options(linear_solver="direct", force_maximum_runaway=0.0, max_newton_per_solve=400)
    solver = fem.QuasiStaticSolver(mesh, bodies, material, batch_size=1, device="cpu", options=opts)
    poses = finger_contact_poses(grasps[[g]])
    for i, n in enumerate(FINGER_NAMES):
        solver.set_body_pose(n, poses[:, i])
    rows = []
    # re-walk the path under travel control from zero (the force path's state cannot be injected simply)
    targets = list(np.linspace(0, start_travel, 21)[1:]) + [
        start_travel + dtravel * k for k in range(1, nsteps + 1)
    ]
    for tr in targets:
        eq = solver.solve(targets={GRIP_DOF: float(tr)})
        rows.append(
            dict(
                travel_mm=float(eq.travel[GRIP_DOF][0] * 1e3),
                force=float(eq.dof_force[GRIP_DOF][0]),
                status=int(eq.status[0]),
                newton=int(eq.newton_iterations[0]),
            )
        )
        print(f"   travel {rows[-1]['travel_mm']:.3f} mm force {rows[-1]['force']:.3f} N st {rows[-1]['status']}",
              flush=True)  # fmt: skip
        if eq.status[0] != 0:
            break
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("object")
    ap.add_argument("E", type=float)
    ap.add_argument("grasps", type=int, nargs="+")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--set", action="append", default=[], help="SolverOptions override key=value")
    ap.add_argument("--travel-continue", type=int, default=0, help="travel-controlled steps past the failure")
    ap.add_argument("--dtravel", type=float, default=0.25e-3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    overrides = {}
    for kv in a.set:
        k, v = kv.split("=")
        overrides[k] = type(getattr(fem.SolverOptions(), k))(float(v) if "." in v or "e" in v else int(v))
    mesh = resolve_object_mesh(a.object, target_nodes=1000)
    grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    material = fem.Material(a.E, 0.3, 1000.0, model="neohookean")
    print(f"{a.object}: {mesh.num_vertices} vertices, {len(grasps.poses)} grasps, E={a.E:g}", flush=True)
    results = []
    for g in a.grasps:
        solver, eqs, wall = run_ramp(mesh, grasps, g, material, a.steps, overrides)
        status = [int(eq.status[0]) for eq in eqs]
        ok = [k for k, s in enumerate(status) if s == 0]
        last = ok[-1] if ok else -1
        fail = next((k for k, s in enumerate(status) if s != 0), None)
        r = dict(
            grasp=g,
            wall_s=wall,
            final_status=status[-1],
            steps_reached=len(ok),
            force_reached=15.0 * (last + 1) / a.steps if ok else 0.0,
            fail_step=fail,
            fail_load_fraction=float(eqs[fail].load_fraction[0]) if fail is not None else None,
            travel_mm=[float(eq.travel[GRIP_DOF][0] * 1e3) for eq in eqs[: last + 1]],
            newton=[int(eq.newton_iterations[0]) for eq in eqs],
        )
        poses = finger_contact_poses(grasps[[g]])[0]
        if ok:
            r["last"] = state_metrics(
                mesh, eqs[last], poses, float(eqs[last].travel[GRIP_DOF][0]), r["force_reached"]
            )
        tr = r["travel_mm"]
        if len(tr) >= 3:
            df = 15.0 / a.steps
            r["secant_last"] = [
                df / max(tr[k] - tr[k - 1], 1e-9) for k in range(max(1, len(tr) - 4), len(tr))
            ]
        print(
            f"grasp {g}: status {r['final_status']} reached {r['force_reached']:.1f} N, fail step {fail}, "
            f"{wall:.1f} s, newton {sum(r['newton'])}",
            flush=True,
        )
        if ok:
            m = r["last"]
            print(
                f"   travel {m['travel_mm']:.2f} mm gap {m['gap0_mm']:.1f}->{m['gap_mm']:.1f} mm, minJ {m['min_J']:.3f}, "
                f"drift {m['drift_mm']:.2f} mm {m['drift_pad_xz_mm']}, turn {m['turn_deg']:.1f} deg "
                f"({m['turn_axis_vs_grasp_deg']:.0f} deg off the grasp axis), pads "
                + "; ".join(
                    f"c{p['contacts']} off{p['contacts_off_face']} slip {p['slip_mean_mm']:.2f}/{p['slip_max_mm']:.2f} "
                    f"wrap {p['wrap_mm']:.2f} ext {p['contact_x_extent_mm']:.1f}x{p['contact_z_extent_mm']:.1f}"
                    for p in m["pads"]
                ),
                flush=True,
            )
        if a.travel_continue and r["final_status"] != 0 and ok:
            r["travel_path"] = travel_continue(
                mesh, grasps, g, material, None, tr[-1] * 1e-3, a.dtravel, a.travel_continue
            )
        results.append(r)
        if a.out:
            with open(a.out, "w") as f:
                json.dump(
                    dict(object=a.object, E=a.E, steps=a.steps, overrides=overrides, results=results), f
                )


if __name__ == "__main__":
    main()
