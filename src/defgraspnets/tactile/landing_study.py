"""How the membrane's FEM contact resolves a small indenter: force against depth of radial pokes at four
landing points of the coarse (cap 8) membrane's pole region, for membranes and contact settings
(``SolverOptions.contact_subdivisions``) side by side (``scripts/benchmark_triangle_contact.py``).

The landing points are taken on the cap-8 outer surface near the pole: the pole (a vertex), a neighbouring
vertex, the midpoint of the edge between them and the centroid of a triangle at the pole. Every poke goes
radially (towards the centre of the dome) through its landing point, so an exact model would give the four
curves alike; every membrane is poked along the same four directions. The sensor is sealed at 1.5 kPa gauge
(isothermal), friction 0.5, the sensor's solver options on the simulator's device. Measured in
``benchmarks/fem_triangle_contact_cpu.md``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from defgraspnets.tactile.membrane import MembraneSensor

LANDING_POINTS = ("pole", "vertex", "edge", "centroid")


def landing_points(sensor: MembraneSensor) -> dict[str, np.ndarray]:
    """The four landing points (3,) [m] of ``sensor``'s rest geometry, named as :data:`LANDING_POINTS`: the
    outer vertex nearest the pole, a second vertex of one of its triangles, the midpoint of the edge between
    them and that triangle's centroid."""
    points = sensor.mesh.points
    outer = sensor.outer_vertices
    pole = outer[np.argmin(np.linalg.norm(points[outer] - sensor.dimensions.outer_pole, axis=1))]
    face = sensor.outer_faces[np.any(sensor.outer_faces == pole, axis=1)][0]
    vertex = next(v for v in face if v != pole)
    return {
        "pole": points[pole],
        "vertex": points[vertex],
        "edge": 0.5 * (points[pole] + points[vertex]),
        "centroid": points[face].mean(axis=0),
    }


def radial_poke_series(sim, direction, depths) -> dict:
    """One radial poke of ``sim``'s indenter along the unit ``direction`` (from the dome's centre outwards),
    to the deepest of ``depths`` [m] past first touch, read at each depth: contact force magnitudes [N] (None
    where not converged), the Newton iterations of the path (failed increments included) and its seconds.
    A poke that never touches a contact point (vertex contact: a small sphere between the vertices) is
    recorded with every reading failed and the error's text."""
    from defgraspnets.tactile.indenters import Pose, WorkspaceError
    from defgraspnets.tactile.sensor import Indentation

    depths = np.asarray(depths, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    dims = sim.sensor.dimensions
    start = dims.center + (dims.outer_radius + 0.03) * direction
    item = Indentation(Pose(tuple(start)), float(depths[-1]), tuple(-direction))
    passes, t0 = sim.solver.newton_passes, time.perf_counter()
    try:
        series = sim.indent_series([item], depths / depths[-1], render=False)
    except WorkspaceError as error:
        failed = [None] * len(depths)
        return {"force": failed, "converged": [False] * len(depths), "newton": 0, "seconds": 0.0,
                "error": str(error)}  # fmt: skip
    readings = [r[0] for r in series]
    return {
        "force": [float(np.linalg.norm(r.contact_force)) if r.converged else None for r in readings],
        "converged": [bool(r.converged) for r in readings],
        "newton": int(sim.solver.newton_passes - passes),
        "seconds": time.perf_counter() - t0,
    }


def run_landing_study(
    configs: Sequence[Sequence[int]],
    depths: Sequence[float],
    radius: float = 0.005,
    points: Sequence[str] = LANDING_POINTS,
    layers: int = 2,
    gauge_pressure: float = 1500.0,
    device: str | None = None,
    report=None,
) -> dict:
    """Pokes of a sphere of ``radius`` [m] at the ``points`` landing points (:func:`landing_points` of the
    cap-8 membrane, the same directions for every membrane) for each ``(cap_divisions,
    contact_subdivisions)`` of ``configs``, read at ``depths`` [m], the FEM on Warp's ``device`` (None: its
    current one) with the sensor's solver options for it (:func:`.sensor.membrane_solver_options`).
    ``report(cap, n, name, run)`` is called after each poke (progress lines). Returns the JSON-ready
    results: depths, radius, layers, landing directions, and per config "cap:n" its set-up seconds, contact
    points and per landing point :func:`radial_poke_series`."""
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane

    unknown = sorted(set(points) - set(LANDING_POINTS))
    if unknown:
        raise ValueError(f"landing points {unknown} unknown; choose from {list(LANDING_POINTS)}")
    depths = np.asarray(depths, dtype=np.float64)
    if depths.ndim != 1 or not len(depths) or np.any(~np.isfinite(depths)) or np.any(np.diff(depths) <= 0):
        raise ValueError(f"depths must be increasing finite values [m], got {depths.tolist()}")
    if depths[0] <= 0:
        raise ValueError(f"depths must be positive [m], got {depths.tolist()}")
    coarse = build_membrane(cap_divisions=8, layers=2)
    center = coarse.dimensions.center
    landing = {name: x - center for name, x in landing_points(coarse).items() if name in points}
    results = {
        "depths": depths.tolist(),
        "radius": float(radius),
        "layers": int(layers),
        "landing": {name: (d / np.linalg.norm(d)).tolist() for name, d in landing.items()},
        "runs": {},
    }
    for cap, n in configs:
        sensor = build_membrane(cap_divisions=int(cap), layers=int(layers))
        t0 = time.perf_counter()
        indenter = SphereIndenter(radius=radius)
        sim = make_simulator(
            sensor, indenter, gauge_pressure, True, intrinsics=None, device=device,
            contact_subdivisions=int(n),
        )  # fmt: skip
        run = {"setup_seconds": time.perf_counter() - t0, "contact_points": sim.solver.num_contact_points}
        run["points"] = {}
        for name in points:
            run["points"][name] = radial_poke_series(sim, results["landing"][name], depths)
            if report is not None:
                report(int(cap), int(n), name, run["points"][name])
        results["runs"][f"{cap}:{n}"] = run
    return results
