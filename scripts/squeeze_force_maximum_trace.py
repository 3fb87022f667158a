"""Per-increment trace of squeeze ramps (benchmarks/squeeze_force_maximum_cpu.md): one grasp per solver,
0-15 N in ``steps`` steps, every load increment's Newton iterations, wall time, target force and the grip's
travel at the end of the attempt (converged or not), written as JSON; with ``geometry=true`` also the state
Newton left the attempt in, before a failed one is restored (benchmarks/squeeze_soft_failures_cpu.md): the
largest vertex move in the increment, the object's drift across the grasp axis, its rigid turn and min det F.

    python scripts/squeeze_force_maximum_trace.py youngs_modulus=1e4 'grasps=[16,64]' out=trace.json
    python scripts/squeeze_force_maximum_trace.py mesh=cuboid_30x30x30 'solver={force_maximum_runaway: 0.0}'
    python scripts/squeeze_force_maximum_trace.py mesh=cuboid_70x35x20 geometry=true \
        'solver={force_maximum_runaway: 0.0}'

Config: configs/squeeze_force_maximum_trace.yaml. Uses the solver's private load-stepping hooks.
"""

import json
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from defgraspnets import fem
from defgraspnets.grasp.diagnostics import deformation_jacobians, rigid_turn
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import (
    finger_contact_poses,
    make_squeeze_solver,
    squeeze_ramp,
    squeeze_solver_options,
)

ROOT = Path(__file__).resolve().parents[1]


@hydra.main(version_base="1.3", config_path="../configs", config_name="squeeze_force_maximum_trace")
def main(cfg: DictConfig) -> None:
    E = float(cfg.youngs_modulus)
    ids = [int(x) for x in cfg.grasps]
    out = cfg.out
    extra = OmegaConf.to_container(cfg.solver, resolve=True) if cfg.solver is not None else {}
    if cfg.mesh == "test":
        mesh = fem.TetMesh.load(ROOT / "tests" / "data" / "cuboid_30x30x30_ftetwild.vtu")
        grasps = sample_antipodal_grasps(mesh, num_grasps=100, friction_coefficient=0.7, seed=0)
    elif Path(cfg.mesh).suffix:
        mesh = fem.TetMesh.load(Path(cfg.mesh))
        grasps = sample_antipodal_grasps(mesh, num_grasps=int(cfg.num_grasps), seed=0)
    else:
        from defgraspnets.grasp.datagen import resolve_object_mesh

        mesh = resolve_object_mesh(cfg.mesh, target_nodes=int(cfg.target_nodes))
        grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    steps = int(cfg.steps)
    material = fem.Material(E, 0.3, 1000.0, model="neohookean")
    results = []
    for g in ids:
        options = squeeze_solver_options(linear_solver="direct", **extra)
        solver = make_squeeze_solver(mesh, grasps[[g]], material, 0.7, device="cpu", options=options)
        attempts, started = [], [0.0]
        finish, begin = solver._finish_increments, solver._begin_increments

        def spy_begin(path, run, mask, begin=begin, started=started):
            started[0] = time.perf_counter()
            return begin(path, run, mask)

        closing = finger_contact_poses(grasps[[g]])[0, 0, :3, 1]  # the grasp axis

        def spy_finish(path, run, done, finish=finish, attempts=attempts, started=started, solver=solver,
                       closing=closing):  # fmt: skip
            D = solver.num_dofs
            attempts.append(
                dict(
                    target=float(path.end["dof"][0, 0]),
                    lam_done=float(path.lam_done[0]),
                    lam_try=float(path.lam_try[0]),
                    ok=bool(run.ok[0]),
                    status=int(run.status[0]),
                    iters=int(run.iters[0] + path.held_newton[0]),
                    travel=float(solver._travel.numpy()[:D][0]),
                    travel_ref=float(solver._travel_ref.numpy()[:D][0]),
                    load=float(solver._dof_force.numpy()[0]),
                    t=time.perf_counter() - started[0],
                )
            )
            if cfg.geometry:  # the state Newton left (not yet restored where the attempt failed)
                N = mesh.num_vertices
                x = solver._positions.numpy()[:N].astype(np.float64)
                x_start = solver._positions_ref.numpy()[:N].astype(np.float64)
                drift = (x - mesh.points).mean(axis=0)
                attempts[-1].update(
                    max_move=float(np.linalg.norm(x - x_start, axis=1).max()),
                    drift=float(np.linalg.norm(drift - (drift @ closing) * closing)),
                    turn_deg=float(np.degrees(rigid_turn(mesh, x)[0])),
                    min_det_f=float(deformation_jacobians(mesh, x).min()),
                )
            return finish(path, run, done)

        solver._finish_increments, solver._begin_increments = spy_finish, spy_begin
        t0 = time.perf_counter()
        eqs = squeeze_ramp(solver, 15.0, steps)
        wall = time.perf_counter() - t0
        status = [int(eq.status[0]) for eq in eqs]
        results.append(
            dict(
                grasp=g,
                wall=wall,
                status=status,
                travel=[float(eq.travel["grip"][0]) for eq in eqs],
                newton=[int(eq.newton_iterations[0]) for eq in eqs],
                attempts=attempts,
            )
        )
        reached = sum(s == 0 for s in status)
        print(f"grasp {g}: status {status[-1]}, {reached} steps reached, {wall:.1f} s", flush=True)
    with open(out, "w") as f:
        json.dump(results, f)


if __name__ == "__main__":
    main()
