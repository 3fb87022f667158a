"""Run the DefGraspSim experiments (thesis §6.4) on sampled grasps of one object: pickup, reorientation,
linear and angular acceleration as quasi-static FEM problems; the 7 performance metrics (§6.5) and the
7 grasp features (Table 6.2) per grasp.

    python scripts/grasp_experiments.py                                  # 30 mm box, 2 grasps, CPU
    python scripts/grasp_experiments.py object=ellipsoid_20x20x20 num_grasps=10 youngs_modulus=2e4
    python scripts/grasp_experiments.py experiments=[pickup,linear] settings.num_directions=8

Config: configs/grasp_experiments.yaml. Logic: :mod:`defgraspnets.grasp.experiments`. Writes metrics.json and
experiments.png to ``out_dir``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("grasp_experiments")


@hydra.main(version_base="1.3", config_path="../configs", config_name="grasp_experiments")
def main(cfg: DictConfig) -> dict:
    import time

    from defgraspnets import fem
    from defgraspnets.eval.report import write_json
    from defgraspnets.grasp.datagen import resolve_object_mesh
    from defgraspnets.grasp.experiment_plots import plot_experiments
    from defgraspnets.grasp.experiments import ExperimentSettings, GraspExperiments, experiment_solver_options
    from defgraspnets.grasp.sampler import sample_antipodal_grasps

    settings = ExperimentSettings(**OmegaConf.to_container(cfg.settings))
    mesh = resolve_object_mesh(cfg.object, cfg.box.size, cfg.box.divisions, cfg.target_nodes, cfg.mesher)
    grasps = sample_antipodal_grasps(
        mesh,
        cfg.num_grasps,
        friction_coefficient=settings.friction,
        rotations_per_axis=cfg.rotations_per_axis,
        seed=cfg.seed,
    )
    if len(grasps) == 0:
        raise RuntimeError(f"no collision-free antipodal grasp found on {mesh.name}")
    material = fem.Material(cfg.youngs_modulus, cfg.poisson_ratio, cfg.density, model=cfg.material_model)
    experiments = GraspExperiments(
        mesh,
        grasps,
        material,
        settings,
        device=cfg.device,
        options=experiment_solver_options(linear_solver=cfg.linear_solver),
        progress=cfg.progress,
        directions_per_solver=cfg.directions_per_solver,
    )
    start = time.perf_counter()
    results = experiments.run(tuple(cfg.experiments))
    seconds = time.perf_counter() - start
    tests = results.linear or results.angular
    directions = None if tests is None else tests.directions.tolist()
    axes = None if results.reorientation is None else results.reorientation.axes.tolist()
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {
        "object": mesh.name,
        "num_vertices": mesh.num_vertices,
        "mass_kg": results.mass,
        "material": {"youngs_modulus_pa": cfg.youngs_modulus, "poisson_ratio": cfg.poisson_ratio,
                     "model": cfg.material_model,
                     "density_kg_m3": cfg.density},
        "settings": OmegaConf.to_container(cfg.settings),
        "experiments": list(cfg.experiments),
        "pickup_force_n": results.pickup.grasp_force,
        "acceleration_directions_gripper_frame": directions,
        "reorientation_axes_world": axes,
        "seconds": seconds,
        "seconds_per_experiment": results.extras["seconds"],
        "device": cfg.device,
        "grasps": results.per_grasp(),
    }  # fmt: skip
    write_json(out / "metrics.json", report)
    plot_experiments(out / "experiments.png", results, title=f"{mesh.name}, E = {cfg.youngs_modulus:.3g} Pa")
    held = sum(r["metrics"]["pickup_success"] for r in report["grasps"])
    log.info(
        "%s: %d grasps, %d picked up, %.1f s; wrote %s/metrics.json and experiments.png",
        mesh.name, len(grasps), held, seconds, out,
    )  # fmt: skip
    return report


if __name__ == "__main__":
    main()
