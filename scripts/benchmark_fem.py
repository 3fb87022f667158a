"""Benchmark the FEM engine on the grasp squeeze ramp and write the timings as JSON.

    python scripts/benchmark_fem.py                                   # one ramp, 2-core CPU goal <= 10 s
    python scripts/benchmark_fem.py device=cuda num_grasps=100        # GPU goal: 100 ramps <= 30 s
    python scripts/benchmark_fem.py profile_phases=true               # + seconds per Newton phase
    python scripts/benchmark_fem.py barrier=true                      # every grasp waits at every step
    python scripts/benchmark_fem.py device=cuda profile_kernels=true  # + GPU busy time, top kernels, host ops

The first (cold) call compiles and loads the Warp kernels; the timed run is a second, warm run on a fresh
solver. Config: configs/benchmark_fem.yaml.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf


def factorizations(solver) -> int | None:
    """Matrix factorizations of all the solver's problems so far (None where the linear solver has none)."""
    from defgraspnets.fem.solver import FACTORIZING_SOLVERS

    if solver.linear_solver not in FACTORIZING_SOLVERS or not hasattr(solver.system, "factorizations"):
        return None
    return int(solver.system.factorizations.sum())


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_fem")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets import fem
    from defgraspnets.eval.machine import machine_info
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp, squeeze_solver_options

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(cfg.device)
    size = np.asarray(cfg.object.size, dtype=float)
    mesh = fem.TetMesh.box(size=size, divisions=tuple(cfg.object.divisions), origin=-size / 2, name="box")
    grasps = sample_antipodal_grasps(mesh, num_grasps=cfg.num_grasps, seed=cfg.seed)
    if cfg.grasp_indices is not None:
        chosen = np.asarray(list(cfg.grasp_indices), dtype=int)
        if chosen.size == 0 or chosen.min() < 0 or chosen.max() >= len(grasps):
            raise ValueError(
                f"grasp_indices must pick among the {len(grasps)} sampled grasps, got {list(chosen)}"
            )
        grasps = grasps[chosen]
    material = fem.Material(cfg.youngs_modulus, cfg.poisson_ratio, cfg.density, model=cfg.material_model)
    options = squeeze_solver_options(
        **cfg.solver,  # further SolverOptions fields (a misspelled one is a TypeError naming it)
        linear_solver=cfg.linear_solver,
        max_newton_per_solve=cfg.max_newton_per_step,
        # null config values keep the squeeze defaults
        **{
            key: cfg[key]
            for key in (
                "max_factor_reuse",
                "contact_smoothing",
                "relag_friction_on_retry",
                "max_step_fraction",
                "banded_min_problems",
                "line_search_trials",
            )
        },
    )

    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    # cold call: compiles / loads the kernels on a one-step ramp to the first force level
    solver = make_squeeze_solver(mesh, grasps, material, cfg.friction, device=device, options=options)
    start = time.perf_counter()
    squeeze_ramp(solver, cfg.max_force / cfg.steps, 1)
    wp.synchronize_device(device)
    cold = time.perf_counter() - start

    solver = make_squeeze_solver(mesh, grasps, material, cfg.friction, device=device, options=options)
    step_seconds, newton, krylov = [], np.zeros(len(grasps), dtype=int), []
    record = {
        "benchmark": "fem_squeeze_ramp",
        "machine": {**machine_info(str(device) if device.is_cuda else "cpu"), "warp": wp.__version__},
        "object": {
            "shape": "box",
            "size_m": size.tolist(),
            "vertices": mesh.num_vertices,
            "tets": mesh.num_tets,
        },
        "material": {
            "youngs_modulus_pa": cfg.youngs_modulus,
            "poisson_ratio": cfg.poisson_ratio,
            "model": cfg.material_model,
        },
        "grasps": len(grasps),
        "steps": cfg.steps,
        "max_force_n": cfg.max_force,
        # true: one solve() per force step, the batch waits at every step for its slowest grasp (lockstep);
        # false: each grasp goes on to its next step as soon as it reached the current one (solve_sequence)
        "barrier": bool(cfg.barrier),
        "linear_solver": solver.linear_solver,
        "solver_options": {
            k: getattr(options, k)
            for k in (
                "rtol",
                "contact_stiffness",
                "contact_smoothing",
                "max_factor_reuse",
                "relag_friction_on_retry",
                "banded_min_problems",
                "line_search_trials",
                "friction_lag_check",
                "friction_relag_iterations",
                "friction_stick_slip",
                *cfg.solver,
            )
            if hasattr(options, k)
        },
        "seconds_cold_first_step": cold,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    clock = [time.perf_counter()]

    def record_step(i, force, eq):
        # the JSON is rewritten after every step, so a run cut short still reports the steps it finished
        wp.synchronize_device(device)
        now = time.perf_counter()
        step_seconds.append(now - clock[0])
        clock[0] = now
        newton[:] += eq.newton_iterations
        krylov.append(int(eq.linear_iterations.max()))
        record.update(
            {
                "completed_steps": i + 1,
                "seconds": float(np.sum(step_seconds)),
                "seconds_per_ramp": float(np.sum(step_seconds)) / len(grasps),
                "step_seconds": [round(t, 4) for t in step_seconds],
                # the slowest grasp's own Newton iterations (with barrier=true the batch's iterations are
                # more: the sum over the steps of each step's slowest grasp, newton_iterations_step_max)
                "newton_iterations_total": int(newton.max()),
                "newton_iterations_per_step_mean": float(newton.mean() / (i + 1)),
                "newton_iterations_step_max": [
                    *record.get("newton_iterations_step_max", []),
                    int(eq.newton_iterations.max()),
                ],
                "newton_iterations_per_problem": newton.tolist(),
                # Newton passes of the batch (one assembly and at most one linear solve each)
                "newton_passes": int(solver.newton_passes),
                # how far the grasps are from the slowest one
                "newton_per_grasp": {
                    "median": float(np.median(newton)),
                    "p90": float(np.percentile(newton, 90)),
                    "max": int(newton.max()),
                    "slowest_grasps": np.argsort(-newton, kind="stable")[:5].tolist(),
                },
                "status_per_problem": eq.status.tolist(),
                "krylov_iterations_total": int(np.sum(krylov)),
                # matrix factorizations of all problems (FACTORIZING_SOLVERS; None for Krylov solvers)
                "factorizations": factorizations(solver),
                # the banded factorization's CUDA graphs (SolverOptions.factor_graphs), or None
                "factor_graphs": solver.system.factor_graph_counts(),
                "converged": int(eq.converged.sum()),
                "status_counts": {str(k): int(v) for k, v in zip(*np.unique(eq.status, return_counts=True))},
                "max_penetration_m": float(eq.max_penetration.max()),
                "grasp_force_reached_n": float(np.median(eq.dof_force["grip"])),
            }
        )
        out.write_text(json.dumps(record, indent=2) + "\n")
        if not cfg.progress:
            print(
                f"step {i + 1}/{cfg.steps}: {step_seconds[-1]:.2f} s, "
                f"Newton max {int(eq.newton_iterations.max())}",
                flush=True,
            )

    final = squeeze_ramp(
        solver, cfg.max_force, cfg.steps, progress=cfg.progress, on_step=record_step, barrier=cfg.barrier
    )[-1]
    if cfg.fields_out:
        # final displacement fields and statuses, to compare runs with different solver settings
        np.savez(cfg.fields_out, displacement=final.displacement, status=final.status)

    def profiled_ramp(profiler):
        """The ramp again on a fresh solver inside ``profiler(solver)``'s context: (profile, solver)."""
        fresh = make_squeeze_solver(mesh, grasps, material, cfg.friction, device=device, options=options)
        with profiler(fresh) as profile:
            squeeze_ramp(fresh, cfg.max_force, cfg.steps, progress=cfg.progress, barrier=cfg.barrier)
        return profile, fresh

    if cfg.profile_phases:
        # a second run of the same ramp on a fresh solver, every phase synchronized and timed
        from defgraspnets.fem.profiling import PhaseTimer

        phases, _ = profiled_ramp(PhaseTimer)
        record["phases"] = phases.summary()
        out.write_text(json.dumps(record, indent=2) + "\n")
        print("phases [s]:", {k: v["seconds"] for k, v in record["phases"].items() if k != "wall_seconds"})
    if cfg.profile_kernels:
        # and again under PyTorch's profiler: how busy the GPU is, its kernels, the host's operations
        from defgraspnets.fem.profiling import KernelProfile

        profile, fresh = profiled_ramp(lambda _: KernelProfile(device))
        record["kernel_profile"] = kp = profile.summary(passes=fresh.newton_passes)
        out.write_text(json.dumps(record, indent=2) + "\n")
        print(
            f"profiled: {kp['wall_seconds']} s, GPU busy {kp['gpu_busy_seconds']} s "
            f"({kp['gpu_busy_fraction']}), {kp['gpu_kernels']} kernels"
        )
    if cfg.profile_host:
        # and again under Python's profiler: where the host's time goes, its waits for the device included
        from defgraspnets.fem.profiling import HostProfile

        host, fresh = profiled_ramp(lambda _: HostProfile(device))
        record["host_profile"] = hp = host.summary(passes=fresh.newton_passes)
        out.write_text(json.dumps(record, indent=2) + "\n")
        print(f"host profile: {hp['wall_seconds']} s, {hp['wall_ms_per_pass']} ms per pass; top self time:")
        for r in hp["top_self"][:8]:
            print(f"  {r['self_seconds']:9.3f} s {r['calls']:8d} calls  {r['function']}")
    print(
        json.dumps(
            {
                k: record[k]
                for k in (
                    "grasps",
                    "steps",
                    "seconds",
                    "newton_iterations_total",
                    "newton_passes",
                    "newton_per_grasp",
                    "krylov_iterations_total",
                    "converged",
                    "factorizations",
                )
            },
            indent=None,
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
