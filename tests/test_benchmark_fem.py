"""scripts/benchmark_fem.py on CPU: a tiny squeeze benchmark writes a complete JSON (per-step timings,
per-grasp Newton iterations and status), and a misspelled key is named."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "benchmark_fem.py"


def _run(tmp_path, *overrides):
    cmd = [sys.executable, str(SCRIPT), "progress=false", f"out={tmp_path / 'fem.json'}", *overrides]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)


def test_benchmark_fem_writes_per_step_and_per_grasp_records(tmp_path):
    run = _run(
        tmp_path,
        "object.size=[0.03,0.03,0.03]",
        "object.divisions=[3,3,3]",
        "num_grasps=2",
        "steps=3",
        "youngs_modulus=1e6",
        "linear_solver=dense",
    )
    assert run.returncode == 0, run.stderr[-2000:]
    record = json.loads((tmp_path / "fem.json").read_text())
    assert record["linear_solver"] == "dense"
    assert record["completed_steps"] == 3 and len(record["step_seconds"]) == 3
    assert record["object"]["vertices"] == 64 and record["grasps"] == 2
    per_grasp = np.array(record["newton_iterations_per_problem"])
    assert per_grasp.shape == (2,) and np.all(per_grasp > 0)
    assert record["newton_iterations_total"] == per_grasp.max()
    assert len(record["newton_iterations_step_max"]) == 3
    assert sum(record["status_counts"].values()) == 2 == len(record["status_per_problem"])
    assert record["converged"] == 2  # a stiff cube squeezed by two pads: both ramps reach 15 N
    assert abs(record["grasp_force_reached_n"] - 15.0) < 1e-4
    assert record["machine"]["device"] == "cpu" and record["seconds"] > 0


def test_benchmark_fem_names_a_misspelled_key(tmp_path):
    run = _run(tmp_path, "num_grasp=2")
    assert run.returncode != 0
    assert "num_grasp" in run.stderr
