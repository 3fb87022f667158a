"""Vertex-wise against sub-vertex contact of the fast membrane model (CPU).

    python scripts/benchmark_fast_membrane_contact.py
    python scripts/benchmark_fast_membrane_contact.py yaw_steps=41 'variants=[[0,0.0],[10,0.003]]'
    python scripts/benchmark_fast_membrane_contact.py 'variants=[[0,0.0]]' 'weightings=[count,depth]'

Config: configs/benchmark_fast_membrane_contact.yaml. For each contact setting
(:class:`~defgraspnets.tactile.fast_membrane.FastMembrane` ``contact_samples_per_face``,
``contact_edge_radius``) on the mixed-manipulation LfD sensor:

1. the prism yaw reading: the 7.5 x 1 x 2 cm prism (:data:`~defgraspnets.tactile.lfd.manipulation.PRISM`)
   in the LfD world, the palm pressed ``indentation`` into its top face at relative yaws -range..+range and
   a few lateral offsets; the reading is the angle of ``e_1`` of the observed contact core
   (:meth:`TactileSimulation.observe` -> :func:`~defgraspnets.tactile.lfd.features.tactile_features`, the
   LfD's path); reported: |reading - yaw| (median, 90th percentile, max), the readings that did not
   increase with the yaw and the number of distinct readings, for each feature weighting of ``weightings``
   (``count``: every core point once, ``depth``: weighted by its indentation beyond the core cut, see
   :class:`~defgraspnets.tactile.contour_sim.TactileSimulation` ``point_weighting``; the first is the
   variant's ``yaw_error_deg`` etc., all under ``yaw_by_weighting``);
2. a sphere pressed on the sensor axis: force against depth, the largest increment over the median one and
   the lateral share of the contact force (0 for a symmetric contact);
3. the solve time per state (median over the readings of 1).

Writes fast_membrane_contact.json to the run directory.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("benchmark_fast_membrane_contact")


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_fast_membrane_contact")
def main(cfg: DictConfig) -> dict:
    import numpy as np

    from defgraspnets.tactile.contour_sim import build_fast_simulation, pole_height
    from defgraspnets.tactile.fast_membrane import FastMembrane
    from defgraspnets.tactile.lfd.features import tactile_features
    from defgraspnets.tactile.lfd.manipulation import PRISM, ManipulationWorld, PalmGeometry
    from defgraspnets.tactile.sdf import SphereSDF

    t0 = time.perf_counter()
    sim = build_fast_simulation(**cfg.sensor, point_weighting="depth")  # obs.weights: the depth ramp
    weightings = list(cfg.weightings)
    base = sim.model
    palm = PalmGeometry.from_simulation(sim)
    world = ManipulationWorld()
    yaws = np.linspace(-cfg.yaw_range_deg, cfg.yaw_range_deg, cfg.yaw_steps)
    depths = np.linspace(*cfg.sphere_depths[:2], int(cfg.sphere_depths[2]))
    top = pole_height(sim)
    rows = []
    for samples, radius in cfg.variants:
        sim.model = base if samples == 0 else FastMembrane(
            base.sensor, base.reference, base.calibration,
            contact_samples_per_face=int(samples), contact_edge_radius=float(radius),
        )  # fmt: skip
        t1 = time.perf_counter()
        readings, times = {w: [] for w in weightings}, []
        for ox, oy in cfg.offsets:
            row = {w: [] for w in weightings}
            for yaw in yaws:
                obj = np.array([cfg.prism_center[0], cfg.prism_center[1], np.deg2rad(yaw)])
                pose = palm.pose([obj[0] + ox, obj[1] + oy, PRISM.height - cfg.indentation])
                obs = sim.observe(world.scene(PRISM, obj), pose)
                times.append(obs.state.solve_time)
                for w in weightings:
                    e1 = tactile_features(obs.points, pose, weights=obs.weights if w == "depth" else None).e1
                    angle = np.rad2deg(np.arctan2(e1[1], e1[0]))
                    row[w].append((angle + 90.0) % 180.0 - 90.0)  # orientation modulo 180 deg
            for w in weightings:
                readings[w].append(row[w])
        by_weighting = {}
        for w in weightings:
            reading = np.array(readings[w])
            error = np.abs(reading - yaws[None, :])
            steps = np.diff(reading, axis=1)
            by_weighting[w] = {
                "yaw_error_deg": {
                    "median": float(np.median(error)),
                    "p90": float(np.percentile(error, 90)),
                    "max": float(error.max()),
                },
                "yaw_steps_not_increasing": int((steps <= 0.01).sum()),
                "yaw_steps": int(steps.size),
                "distinct_readings": int(len(np.unique(np.round(reading, 2)))),
                "readings": int(reading.size),
                "yaw_readings_deg": reading.tolist(),
            }
            b = by_weighting[w]
            log.info(
                "m=%d r=%.1f mm, %s weighting: yaw error median %.2f p90 %.2f max %.2f deg, %d/%d steps not "
                "increasing, %d distinct readings", samples, radius * 1e3, w, *b["yaw_error_deg"].values(),
                b["yaw_steps_not_increasing"], b["yaw_steps"], b["distinct_readings"],
            )  # fmt: skip
        forces, lateral = [], []
        for d in depths:
            sphere = SphereSDF((0.0, 0.0, top + cfg.sphere_radius - d), cfg.sphere_radius)
            st = sim.model.solve(sphere, np.eye(4))
            forces.append(st.normal_force)
            lateral.append(float(np.linalg.norm(st.contact_force[:2]) / max(st.normal_force, 1e-12)))
        inc = np.diff(forces)
        rows.append(
            {
                "contact_samples_per_face": int(samples),
                "contact_edge_radius_m": float(radius),
                **{k: v for k, v in by_weighting[weightings[0]].items() if k != "yaw_readings_deg"},
                "yaw_by_weighting": by_weighting,
                "sphere_force_N": [float(f) for f in forces],
                "sphere_force_increment_max_over_median": float(inc.max() / np.median(inc)),
                "sphere_force_increment_min_N": float(inc.min()),
                "sphere_lateral_force_share_max": float(max(lateral)),
                "solve_time_median_s": float(np.median(times)),
                "solve_time_mean_s": float(np.mean(times)),
                "wall_time_s": time.perf_counter() - t1,
            }
        )
        r = rows[-1]
        log.info(
            "m=%d r=%.1f mm: sphere increment max/median %.2f (min %.3f N), lateral %.3f, solve %.1f ms",
            samples, radius * 1e3, r["sphere_force_increment_max_over_median"],
            r["sphere_force_increment_min_N"], r["sphere_lateral_force_share_max"],
            1e3 * r["solve_time_median_s"],
        )  # fmt: skip
    report = {
        "sensor": dict(cfg.sensor),
        "indentation_m": cfg.indentation,
        "yaws_deg": [float(y) for y in yaws],
        "offsets_m": [list(o) for o in cfg.offsets],
        "sphere_radius_m": cfg.sphere_radius,
        "sphere_depths_m": [float(d) for d in depths],
        "variants": rows,
        "wall_time_s": time.perf_counter() - t0,
    }
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fast_membrane_contact.json").write_text(json.dumps(report, indent=2))
    log.info("wrote %s", out / "fast_membrane_contact.json")
    return report


if __name__ == "__main__":
    main()
