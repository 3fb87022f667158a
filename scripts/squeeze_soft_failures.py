"""Diagnose failing squeeze ramps (benchmarks/squeeze_soft_failures_cpu.md): status, force reached and the
last converged state's geometry against the pads per grasp; optionally the force along a travel-controlled
re-walk.

    python scripts/squeeze_soft_failures.py object=cuboid_70x35x20 youngs_modulus=1e4 'grasps=[0,4,8]'
    python scripts/squeeze_soft_failures.py object=cylinder_r20_h40 youngs_modulus=2.154e4 travel_continue=8

Config: configs/squeeze_soft_failures.yaml. Logic: defgraspnets.grasp.diagnostics.
"""

import json
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from defgraspnets import fem
from defgraspnets.grasp.datagen import resolve_object_mesh
from defgraspnets.grasp.diagnostics import (
    NewtonTrace,
    self_intersection_summary,
    squeeze_state_geometry,
    travel_controlled_path,
)
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import (
    GRIP_DOF,
    finger_contact_poses,
    make_squeeze_solver,
    squeeze_ramp,
    squeeze_solver_options,
)


@hydra.main(version_base="1.3", config_path="../configs", config_name="squeeze_soft_failures")
def main(cfg: DictConfig) -> None:
    mesh = (
        fem.TetMesh.load(Path(cfg.object))
        if Path(str(cfg.object)).suffix
        else resolve_object_mesh(cfg.object, target_nodes=int(cfg.target_nodes))
    )
    grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    material = fem.Material(float(cfg.youngs_modulus), 0.3, 1000.0, model="neohookean")
    overrides = OmegaConf.to_container(cfg.solver, resolve=True) or {}
    options = squeeze_solver_options(**{"linear_solver": "direct", **overrides})
    steps, max_force = int(cfg.steps), float(cfg.max_force)
    print(f"{cfg.object}: {mesh.num_vertices} vertices, E = {cfg.youngs_modulus:g} Pa", flush=True)
    results = []
    for g in [int(i) for i in cfg.grasps]:
        grasp = grasps[[g]]
        solver = make_squeeze_solver(mesh, grasp, material, 0.7, device="cpu", options=options)
        trace = None
        if cfg.trace:
            trace = NewtonTrace(solver, scans=int(cfg.trace_scans), scan_after=int(cfg.trace_scan_after))
        start = time.perf_counter()
        eqs = squeeze_ramp(solver, max_force, steps)
        if trace is not None:
            trace.close()
        status = [int(eq.status[0]) for eq in eqs]
        solved = [k for k, s in enumerate(status) if s == 0]
        failed = next((k for k, s in enumerate(status) if s != 0), None)
        r = {
            "grasp": g,
            "wall_s": time.perf_counter() - start,
            "final_status": status[-1],
            "force_reached": max_force * (solved[-1] + 1) / steps if solved else 0.0,
            "fail_step": failed,
            "travel_mm": [float(eqs[k].travel[GRIP_DOF][0] * 1e3) for k in solved],
            "newton": [int(eq.newton_iterations[0]) for eq in eqs],
        }
        if trace is not None:
            r["trace"] = trace.records  # every Newton iteration of the ramp, in order
        if solved:
            last = eqs[solved[-1]]
            r["last"] = squeeze_state_geometry(
                mesh,
                last.displacement[0],
                finger_contact_poses(grasp)[0],
                float(last.travel[GRIP_DOF][0]),
                {name: f[0] for name, f in last.contact_normal_force.items()},
                contact_threshold=1e-4 * r["force_reached"],
            )
            # the solver rests at the last converged state (a failed increment is restored)
            r["last"].update(self_intersection_summary(mesh, mesh.points + last.displacement[0], solver))
        print(f"grasp {g}: status {r['final_status']}, {r['force_reached']:.1f} N reached, "
              f"{sum(r['newton'])} Newton iterations, {r['wall_s']:.1f} s, "
              f"{r.get('last', {}).get('inside')} surface vertices inside", flush=True)  # fmt: skip
        if int(cfg.travel_continue) > 0 and failed is not None and solved:
            reached = r["travel_mm"][-1] * 1e-3
            travels = list(np.linspace(0.0, reached, 21)[1:])
            travels += [reached + float(cfg.travel_step) * k for k in range(1, int(cfg.travel_continue) + 1)]
            keep = {k: v for k, v in overrides.items() if k.startswith("self_contact")}  # the walk's too
            walk = {"force_maximum_runaway": 0.0, "max_newton_per_solve": 400, **keep}
            walk.update(OmegaConf.to_container(cfg.travel_solver, resolve=True) or {})
            walk = squeeze_solver_options(**{"linear_solver": "direct", **walk})
            r["travel_path"] = travel_controlled_path(
                mesh, grasp, material, travels, options=walk, trace=bool(cfg.trace)
            )
            for row in r["travel_path"][20:]:
                print(f"   travel {row['travel_mm']:.3f} mm: {row['force']:.3f} N, status {row['status']}, "
                      f"{row['newton']} Newton, {row.get('self_contact_pairs')} pairs, "
                      f"{row.get('inside')} / {row.get('inside_beyond_contact_depth')} inside (beyond cap)",
                      flush=True)  # fmt: skip
        results.append(r)
        with open(cfg.out, "w") as f:  # after every grasp
            json.dump({"config": OmegaConf.to_container(cfg, resolve=True), "results": results}, f)


if __name__ == "__main__":
    main()
