"""Benchmark the grasp generator's work per object: the squeeze ramp and each DefGraspSim experiment
(pickup, reorientation, linear and angular acceleration) timed separately, written as JSON.

    python scripts/benchmark_grasp_experiments.py                         # 30 mm box, 2 grasps, CPU
    python scripts/benchmark_grasp_experiments.py device=cuda num_grasps=16 settings.num_directions=16
    python scripts/benchmark_grasp_experiments.py objects=[box,cuboid_30x30x30] out=benchmarks/x.json

A warm-up (one-step squeeze, pickup and angular test of one grasp) loads the Warp kernels first; its time
is reported apart. The JSON is rewritten after every object. Config: configs/benchmark_grasp_experiments.yaml;
logic: :func:`defgraspnets.grasp.datagen.time_grasp_experiments`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_grasp_experiments")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets import fem
    from defgraspnets.eval.machine import machine_info
    from defgraspnets.grasp.datagen import (
        resolve_experiment_settings,
        resolve_experiments,
        resolve_object_mesh,
        time_grasp_experiments,
    )
    from defgraspnets.grasp.experiments import experiment_solver_options
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import squeeze_solver_options

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(cfg.device)
    names = resolve_experiments(cfg.experiments)
    settings = resolve_experiment_settings(OmegaConf.to_container(cfg.settings, resolve=True), cfg.friction)
    material = fem.Material(cfg.youngs_modulus, cfg.poisson_ratio, cfg.density, model=cfg.material_model)
    squeeze_options = squeeze_solver_options(
        linear_solver=cfg.linear_solver, max_newton_per_solve=cfg.max_newton_per_step
    )
    experiment_options = experiment_solver_options(linear_solver=cfg.experiment_linear_solver)
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "benchmark": "grasp_experiments",
        "machine": {
            **machine_info(str(device) if device.is_cuda else "cpu"),
            "warp": wp.__version__,
            # other work on a shared machine slows the timings down: the 1/5/15-minute load at the start
            "load_average": [round(v, 2) for v in os.getloadavg()],
        },
        "material": {"youngs_modulus_pa": cfg.youngs_modulus, "poisson_ratio": cfg.poisson_ratio,
                     "model": cfg.material_model,
                     "density_kg_m3": cfg.density},
        "experiments": list(names),
        "settings": dataclasses.asdict(settings),
        "config": OmegaConf.to_container(cfg, resolve=True),
        "objects": [],
    }  # fmt: skip
    for spec in cfg.objects:
        mesh = resolve_object_mesh(spec, cfg.box.size, cfg.box.divisions, cfg.target_nodes, cfg.mesher)
        grasps = sample_antipodal_grasps(
            mesh, num_grasps=cfg.num_grasps, friction_coefficient=cfg.friction, seed=cfg.seed
        )
        if len(grasps) == 0:
            raise RuntimeError(f"no collision-free antipodal grasp found on {mesh.name}")
        timing = time_grasp_experiments(
            mesh, grasps, material, settings, names, cfg.steps, cfg.max_force, str(device),
            squeeze_options, experiment_options, cfg.directions_per_solver,
        )  # fmt: skip
        entry = {
            "object": mesh.name,
            "vertices": mesh.num_vertices,
            "tets": mesh.num_tets,
            "mass_kg": float(mesh.mass(cfg.density)),
            **timing,
        }
        record["objects"].append(entry)
        out.write_text(json.dumps(record, indent=2) + "\n")
        stages = {"squeeze_ramp": entry["squeeze_ramp"], **entry["experiments"]}
        for stage, t in stages.items():
            rate = "-" if t["grasps_per_s"] is None else f"{t['grasps_per_s']:.3g}"
            print(
                f"{mesh.name} ({mesh.num_vertices} vertices, {len(grasps)} grasps) {stage:>13}: "
                f"{t['seconds']:7.2f} s, {rate} grasps/s, status {t['status_per_grasp']}",
                flush=True,
            )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
