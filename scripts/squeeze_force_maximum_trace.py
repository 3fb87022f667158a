"""Per-increment trace of squeeze ramps (benchmarks/squeeze_force_maximum_cpu.md): one grasp per solver,
0-15 N in STEPS (default 50) steps, every load increment's Newton iterations, wall time, target force and
the grip's travel at the end of the attempt (converged or not), written as JSON.

    python scripts/squeeze_force_maximum_trace.py E GRASPS OUT.json ['{"force_maximum_runaway": 0.0}']

E: Young's modulus [Pa]; GRASPS: comma-separated grasp indices; the optional JSON overrides
squeeze_solver_options (linear_solver is "direct"). The mesh is tests/data/cuboid_30x30x30_ftetwild.vtu with
sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, seed=0); MESH1000=1: the data path's
cuboid_30x30x30 (target_nodes=1000; XDG_CACHE_HOME must hold the fTetWild mesh cache) and its 100 grasps;
MESHFILE=path (NG grasps, default 16): another tet mesh. Uses the solver's private load-stepping hooks.
"""

import json
import os
import sys
import time
from pathlib import Path

from defgraspnets import fem
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp, squeeze_solver_options

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    E = float(sys.argv[1])
    ids = [int(x) for x in sys.argv[2].split(",")]
    out = sys.argv[3]
    extra = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    if os.environ.get("MESH1000"):
        from defgraspnets.grasp.datagen import resolve_object_mesh

        mesh = resolve_object_mesh("cuboid_30x30x30", target_nodes=1000)
        grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    elif os.environ.get("MESHFILE"):
        mesh = fem.TetMesh.load(Path(os.environ["MESHFILE"]))
        grasps = sample_antipodal_grasps(mesh, num_grasps=int(os.environ.get("NG", 16)), seed=0)
    else:
        mesh = fem.TetMesh.load(ROOT / "tests" / "data" / "cuboid_30x30x30_ftetwild.vtu")
        grasps = sample_antipodal_grasps(mesh, num_grasps=100, friction_coefficient=0.7, seed=0)
    steps = int(os.environ.get("STEPS", 50))
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

        def spy_finish(path, run, done, finish=finish, attempts=attempts, started=started, solver=solver):
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
