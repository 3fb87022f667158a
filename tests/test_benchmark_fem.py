"""scripts/benchmark_fem.py on CPU: a tiny squeeze benchmark writes a complete JSON (per-step timings,
per-grasp Newton iterations and status, seconds per solver phase), and a misspelled key is named; the
phase timer counts what the solver does and leaves it as it was."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from defgraspnets import fem
from defgraspnets.fem.profiling import PHASES, PhaseTimer, busy_seconds
from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "benchmark_fem.py"


def _run(tmp_path, *overrides):
    cmd = [sys.executable, str(SCRIPT), "progress=false", f"out={tmp_path / 'fem.json'}", *overrides]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)


#: a tiny benchmark: two grasps of a 64-vertex cube, three force steps
TINY = (
    "object.size=[0.03,0.03,0.03]",
    "object.divisions=[3,3,3]",
    "num_grasps=2",
    "steps=3",
    "youngs_modulus=1e6",
    "linear_solver=dense",
)


def test_benchmark_fem_writes_per_step_and_per_grasp_records(tmp_path):
    run = _run(
        tmp_path,
        *TINY,
        "profile_phases=true",
        "profile_kernels=true",
        "profile_host=true",
        "contact_smoothing=0.005",
        "+solver.friction_stick_slip=0.01",
    )
    assert run.returncode == 0, run.stderr[-2000:]
    record = json.loads((tmp_path / "fem.json").read_text())
    assert record["linear_solver"] == "dense"
    assert record["solver_options"]["contact_smoothing"] == 0.005  # the override, not the squeeze default
    assert record["solver_options"]["friction_stick_slip"] == 0.01  # any other SolverOptions field
    assert record["solver_options"]["friction_lag_check"] == 1000  # the squeeze default since session 44
    assert record["solver_options"]["friction_relag_iterations"] == 4  # the engine's, kept by the squeeze
    assert record["completed_steps"] == 3 and len(record["step_seconds"]) == 3
    assert record["object"]["vertices"] == 64 and record["grasps"] == 2
    per_grasp = np.array(record["newton_iterations_per_problem"])
    assert per_grasp.shape == (2,) and np.all(per_grasp > 0)
    assert record["newton_iterations_total"] == per_grasp.max()
    spread = record["newton_per_grasp"]
    assert spread["max"] == per_grasp.max() and spread["median"] == np.median(per_grasp)
    assert spread["slowest_grasps"][0] == int(np.argmax(per_grasp)) and len(spread["slowest_grasps"]) == 2
    assert len(record["newton_iterations_step_max"]) == 3
    assert sum(record["status_counts"].values()) == 2 == len(record["status_per_problem"])
    assert record["converged"] == 2  # a stiff cube squeezed by two pads: both ramps reach 15 N
    assert abs(record["grasp_force_reached_n"] - 15.0) < 1e-4
    assert record["machine"]["device"] == "cpu" and record["seconds"] > 0
    # the profiled second run: every phase ran, and the phases and the rest add up to its wall time
    phases = record["phases"]
    assert all(phases[p]["calls"] > 0 for p in PHASES)
    assert phases["linear_solve"]["calls"] >= per_grasp.max()
    total = sum(v["seconds"] for k, v in phases.items() if k != "wall_seconds")
    assert abs(total - phases["wall_seconds"]) < 1e-3 and phases["other"]["seconds"] >= 0
    # the run under PyTorch's profiler: on the CPU no GPU kernels, the dense solver's Cholesky among the
    # host's operations, and the same Newton passes as the timed run (a problem's path is deterministic)
    profile = record["kernel_profile"]
    assert profile["gpu_kernels"] == 0 and profile["gpu_busy_seconds"] == 0 and profile["top_kernels"] == []
    assert profile["passes"] == record["newton_passes"] > 0 and profile["wall_seconds"] > 0
    host = {op["name"]: op for op in profile["top_host_ops"]}
    assert "aten::linalg_cholesky_ex" in host and host["aten::linalg_cholesky_ex"]["calls"] > 0
    # the run under cProfile: the Newton pass among the repository's functions, called once per pass (the
    # same passes again), its cumulative time within the wall time; self times ranked, callers named
    python = record["host_profile"]
    assert python["passes"] == record["newton_passes"]
    repository = {r["function"].split("(")[-1].rstrip(")"): r for r in python["top_repository"]}
    newton = repository["_newton_pass"]
    assert newton["calls"] == record["newton_passes"] and newton["function"].startswith("defgraspnets/fem/")
    assert 0 < newton["cumulative_seconds"] <= python["wall_seconds"]
    own = [r["self_seconds"] for r in python["top_self"]]
    assert own == sorted(own, reverse=True) and len(python["callers_of_top_self"]) == 5
    assert all(python["callers_of_top_self"].values())  # every one of them has a caller


def test_busy_seconds_counts_overlapping_kernels_once():
    assert busy_seconds([]) == 0.0
    # [0, 2] and [1, 3] overlap into [0, 3]; [3, 4] touches it; [5, 5.5] stands alone; [0.5, 1] lies inside
    assert busy_seconds([(5.0, 5.5), (1.0, 3.0), (0.0, 2.0), (3.0, 4.0), (0.5, 1.0)]) == 4.5


def test_phase_timer_counts_one_linear_solve_per_newton_iteration_and_restores_the_solver():
    mesh = structured_box((0.03, 0.03, 0.03), (3, 3, 3), name="cube")
    grasps = sample_antipodal_grasps(mesh, num_grasps=1, seed=0)
    solver = make_squeeze_solver(mesh, grasps, fem.Material(1e6, 0.3, 1000.0), 0.7, device="cpu")
    with PhaseTimer(solver) as phases:
        eqs = squeeze_ramp(solver, 6.0, 2)
    assert all(eq.converged.all() for eq in eqs)
    newton = sum(int(eq.newton_iterations[0]) for eq in eqs)
    assert phases.calls["linear_solve"] == newton > 0
    assert phases.calls["commit"] >= 2  # at least one converged increment per step
    assert not any(name in solver.__dict__ for name in PHASES.values())  # the class's methods again
    summary = phases.summary()
    assert summary["wall_seconds"] >= summary["linear_solve"]["seconds"] > 0


def test_benchmark_fem_solves_a_chosen_subset_of_the_sampled_grasps_as_in_the_whole_batch(tmp_path):
    """grasp_indices: the second of two sampled grasps alone takes the Newton iterations it took beside the
    first (on the CPU a problem's path does not depend on its batch), as it does with a barrier between the
    force steps, where the batch makes more Newton passes; an index out of range is named."""
    common = (
        "object.size=[0.03,0.03,0.03]",
        "object.divisions=[3,3,3]",
        "num_grasps=2",
        "steps=2",
        "youngs_modulus=1e6",
        "linear_solver=dense",
    )
    records = []
    for i, extra in enumerate(((), ("grasp_indices=[1]",), ("barrier=true",))):
        out = tmp_path / f"fem{i}.json"
        run = _run(tmp_path, *common, *extra, f"out={out}")
        assert run.returncode == 0, run.stderr[-2000:]
        records.append(json.loads(out.read_text()))
    both, alone, barrier = records
    assert both["grasps"] == 2 and alone["grasps"] == 1
    assert not both["barrier"] and barrier["barrier"]
    assert barrier["newton_iterations_per_problem"] == both["newton_iterations_per_problem"]
    assert barrier["status_per_problem"] == both["status_per_problem"]
    assert barrier["newton_passes"] > both["newton_passes"] >= both["newton_iterations_total"]
    assert alone["newton_iterations_per_problem"] == both["newton_iterations_per_problem"][1:]
    assert alone["status_per_problem"] == both["status_per_problem"][1:]
    run = _run(tmp_path, *common, "grasp_indices=[2]")
    assert run.returncode != 0 and "grasp_indices" in run.stderr


def test_benchmark_fem_names_a_misspelled_key(tmp_path):
    run = _run(tmp_path, "num_grasp=2")
    assert run.returncode != 0
    assert "num_grasp" in run.stderr
    run = _run(tmp_path, "+solver.friction_stick_slipp=0.01")  # a SolverOptions field, misspelled
    assert run.returncode != 0
    assert "friction_stick_slipp" in run.stderr


def test_the_newton_pass_log_counts_the_passes_of_a_benchmark(tmp_path):
    """scripts/newton_pass_log.py around a tiny benchmark: at least the passes the benchmark counts; the
    problem-passes lie between the passes and the slot-passes; the buckets add up."""
    log = tmp_path / "passes.json"
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "newton_pass_log.py"),
        str(log),
        str(SCRIPT),
        "progress=false",
        f"out={tmp_path / 'fem.json'}",
        *TINY,
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    passes, record = json.loads(log.read_text()), json.loads((tmp_path / "fem.json").read_text())
    # the benchmark times a warm-up ramp and the measured one; its own counter covers the measured one
    assert passes["passes"] >= record["newton_passes"] > 0
    assert passes["passes"] <= passes["problem_passes"] <= passes["slot_passes"] == 2 * passes["passes"]
    assert passes["passes_working_le_1"] <= passes["passes_working_le_2"] == passes["passes"]
    assert 0 < passes["seconds_working_le_32"] == passes["pass_seconds"]
    assert "benchmark_fem.py" in passes["command"]
