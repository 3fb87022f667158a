"""Benchmark the factorizing linear solvers of the FEM engine on real Newton systems; writes JSON.

    python scripts/benchmark_linear_solvers.py                 # 2-core CPU: direct, dense, banded
    python scripts/benchmark_linear_solvers.py device=cuda     # GPU: dense vs banded

Cases: the 960-vertex box of scripts/benchmark_fem.py in 100 Franka grasps after the first force step,
and the sealed, inflated tactile membrane at each cap resolution (defgraspnets.fem.profiling.
time_linear_solves does the timing). Config: configs/benchmark_linear_solvers.yaml.
"""

from __future__ import annotations

import json
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_linear_solvers")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets import fem
    from defgraspnets.eval.machine import machine_info
    from defgraspnets.fem.profiling import time_linear_solves
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp, squeeze_solver_options
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, PVState, build_membrane
    from defgraspnets.tactile.sensor import MembraneSimulator, membrane_solver_options

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(cfg.device)
    methods = list(cfg.methods or (["dense", "banded"] if device.is_cuda else ["direct", "dense", "banded"]))
    record = {
        "benchmark": "fem_linear_solvers",
        "machine": {**machine_info(str(device) if device.is_cuda else "cpu"), "warp": wp.__version__},
        "config": OmegaConf.to_container(cfg, resolve=True),
        "cases": [],
    }
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def report(name, vertices, result):
        record["cases"].append({"case": name, "vertices": vertices, **result})
        out.write_text(json.dumps(record, indent=2) + "\n")
        times = {m: [round(r["seconds"] * 1e3, 2) for r in rows] for m, rows in result["methods"].items()}
        print(
            f"{name}: {vertices} vertices, {result['unknowns']} unknowns, ms per call {times}, "
            f"banded flops {result['banded_flops_ratio']:.3f} of dense, "
            f"solutions agree to {result['max_relative_difference']:.1e}",
            flush=True,
        )

    g = cfg.grasp
    size = np.asarray(g.size, dtype=float)
    mesh = fem.TetMesh.box(size=size, divisions=tuple(g.divisions), origin=-size / 2, name="box")
    grasps = sample_antipodal_grasps(mesh, num_grasps=g.num_grasps, seed=0)
    solver = make_squeeze_solver(
        mesh,
        grasps,
        fem.Material(g.youngs_modulus, 0.3, 1000.0, model="neohookean"),
        0.7,
        device=device,
        # factor_graphs: the banded solver's CUDA graphs (SolverOptions.factor_graphs); null keeps the default
        options=squeeze_solver_options(linear_solver="dense", factor_graphs=cfg.factor_graphs),
    )
    squeeze_ramp(solver, g.first_force, 1)
    report("grasp_box", mesh.num_vertices, time_linear_solves(solver, methods, g.counts, cfg.repeats))
    del solver

    for cap in cfg.membrane_caps:
        sensor = build_membrane(cap_divisions=int(cap), layers=2)
        gas = PVState(
            ATMOSPHERIC_PRESSURE + cfg.membrane.gauge_pressure,
            sensor.cavity_volume + sensor.dimensions.housing_volume,
        )
        sim = MembraneSimulator(
            sensor,
            SphereIndenter(radius=0.01),
            gas,
            closed=True,
            batch_size=max(cfg.membrane.counts),
            intrinsics=None,
            options=membrane_solver_options(device, linear_solver="banded", factor_graphs=cfg.factor_graphs),
            device=device,
        )
        result = time_linear_solves(sim.solver, methods, cfg.membrane.counts, cfg.repeats)
        report(f"membrane_cap{cap}", sensor.mesh.num_vertices, result)
        del sim
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
