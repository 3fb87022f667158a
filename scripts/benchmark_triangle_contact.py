"""Sub-vertex contact on the membrane: force vs depth of the 1 cm fingertip (sphere r = 5 mm) at four landing
points of the coarse (cap 8) membrane, with vertex contact and with contact points on the triangles
(``contact_subdivisions`` n), against the cap-16 membrane with vertex contact.

    PYTHONPATH=src python scripts/benchmark_triangle_contact.py --out benchmarks/fem_triangle_contact_cpu.json
    PYTHONPATH=src python scripts/benchmark_triangle_contact.py --configs 8:1 8:3 16:1 --depths 0.005 0.01

The landing points are taken on the cap-8 outer surface near the pole: the pole (a vertex), a neighbouring
vertex, the midpoint of the edge between them and the centroid of a triangle at the pole. Every poke goes
radially (towards the centre of the dome) through its landing point, so the four curves of one membrane
would be the same for an exact contact model; every membrane is poked along the same four directions. The
sensor is sealed at 1.5 kPa gauge (isothermal), friction 0.5, the sensor's solver options on the CPU.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def landing_points(sensor) -> dict[str, np.ndarray]:
    """The four landing points (cap-8 rest geometry) named pole, vertex, edge, centroid."""
    points = sensor.mesh.points
    pole_pos = sensor.dimensions.outer_pole
    outer = sensor.outer_vertices
    pole = outer[np.argmin(np.linalg.norm(points[outer] - pole_pos, axis=1))]
    faces = sensor.outer_faces
    at_pole = faces[np.any(faces == pole, axis=1)]
    face = at_pole[0]
    others = [v for v in face if v != pole]
    vertex = others[0]
    return {
        "pole": points[pole],
        "vertex": points[vertex],
        "edge": 0.5 * (points[pole] + points[vertex]),
        "centroid": points[face].mean(axis=0),
    }


def poke_series(sim, direction: np.ndarray, depths: np.ndarray) -> dict:
    """One radial poke to the deepest depth, read at each depth: forces, Newton iterations, seconds."""
    from defgraspnets.tactile.indenters import Pose, WorkspaceError
    from defgraspnets.tactile.sensor import Indentation

    center = sim.sensor.dimensions.center
    start = center + (sim.sensor.dimensions.outer_radius + 0.03) * direction
    item = Indentation(Pose(tuple(start)), float(depths[-1]), tuple(-direction))
    solver, count = sim.solver, [0]
    newton_pass = solver._newton_pass

    def counted(run):  # one problem: a Newton pass is one Newton iteration (failed increments included)
        count[0] += 1
        return newton_pass(run)

    solver._newton_pass = counted
    t0 = time.perf_counter()
    try:
        series = sim.indent_series([item], depths / depths[-1], render=False)
    except WorkspaceError as error:  # vertex contact: the sphere passes between the vertices, no onset
        return {"force": [None] * len(depths), "converged": [False] * len(depths), "newton": 0,
                "seconds": 0.0, "error": str(error)}  # fmt: skip
    finally:
        seconds = time.perf_counter() - t0
        del solver._newton_pass
    return {
        "force": [float(np.linalg.norm(r[0].contact_force)) if r[0].converged else None for r in series],
        "converged": [bool(r[0].converged) for r in series],
        "newton": count[0],
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--configs", nargs="+", default=["8:1", "8:2", "8:3", "16:1"], help="cap:subdivisions"
    )
    parser.add_argument("--depths", nargs="+", type=float, default=[0.005, 0.01, 0.015, 0.02, 0.025])
    parser.add_argument("--radius", type=float, default=0.005, help="indenter sphere radius [m]")
    parser.add_argument("--points", nargs="+", default=["pole", "vertex", "edge", "centroid"])
    parser.add_argument("--layers", type=int, default=2, help="element layers through the membrane")
    parser.add_argument("--out", default=None, help="JSON file of the results")
    args = parser.parse_args()

    import warp as wp

    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane
    from defgraspnets.tactile.sensor import membrane_solver_options

    wp.config.quiet = True
    depths = np.asarray(args.depths)
    landing = landing_points(build_membrane(cap_divisions=8, layers=2))
    center = build_membrane(cap_divisions=8, layers=2).dimensions.center
    results = {
        "depths": depths.tolist(),
        "radius": args.radius,
        "layers": args.layers,
        "landing": {},
        "runs": {},
    }
    for name in args.points:
        d = landing[name] - center
        results["landing"][name] = (d / np.linalg.norm(d)).tolist()
    for config in args.configs:
        cap, n = (int(v) for v in config.split(":"))
        sensor = build_membrane(cap_divisions=cap, layers=args.layers)
        t0 = time.perf_counter()
        options = membrane_solver_options("cpu", contact_subdivisions=n)
        sim = make_simulator(
            sensor, SphereIndenter(radius=args.radius), 1500.0, closed=True, intrinsics=None, options=options
        )
        setup = time.perf_counter() - t0
        run = {"setup_seconds": setup, "contact_points": sim.solver.num_contact_points, "points": {}}
        for name in args.points:
            direction = np.asarray(results["landing"][name])
            run["points"][name] = poke_series(sim, direction, depths)
            r = run["points"][name]
            forces = " ".join("  fail" if f is None else f"{f:6.3f}" for f in r["force"])
            print(
                f"cap {cap:2d} n {n} {name:8s} F [N] {forces}"
                f"   newton {r['newton']:4d}  {r['seconds']:6.1f} s",
                flush=True,
            )
        results["runs"][config] = run
        if args.out:
            with open(args.out, "w") as f:
                json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
