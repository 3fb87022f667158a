"""scripts/benchmark_tactile.py on CPU: one poke path (5 states) through the datagen pipeline writes a
complete JSON with its rate and the whole grid's extrapolated time, and leaves no shard behind; a
misspelled key is named."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "benchmark_tactile.py"


def _run(tmp_path, *overrides):
    cmd = [
        sys.executable,
        str(SCRIPT),
        f"out={tmp_path / 'tactile.json'}",
        f"paths.root_dir={tmp_path}",
        *overrides,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)


def test_benchmark_tactile_times_one_poke_path(tmp_path):
    # the cap-4 membrane with a 40 mm sphere (one path's bookkeeping, not the membrane's resolution)
    run = _run(
        tmp_path,
        "limit=1",
        "batch_size=1",
        "solver.rtol=2e-5",
        "camera_scale=0.25",
        "membrane.cap_divisions=4",
        "indenter.radius=0.02",
    )
    assert run.returncode == 0, run.stderr[-2000:]
    record = json.loads((tmp_path / "tactile.json").read_text())
    assert record["dataset"] == "poke" and record["device"] == "cpu"
    assert record["paths"] == 1 and record["states"] == 5 == record["samples"] + record["failed"]
    assert record["samples"] == 5  # the pole poke, 0.5 to 2.5 cm, converges on the coarsest membrane
    assert record["seconds"] > 0
    # one path of 5 readings from contact onset: at least one Newton pass per load step (the pole poke goes
    # 2.5 cm deep in steps of at most 2 mm), a few per step, inflation not counted
    assert 13 <= record["newton_passes"] <= 40 * 13
    assert record["seconds_per_state"] == pytest.approx(record["seconds"] / 5, rel=1e-3)
    assert record["grid_states"] == 10_000 and record["goal_minutes"] == 10.0
    assert record["extrapolated_grid_minutes"] == pytest.approx(
        record["seconds_per_state"] * 10_000 / 60, rel=1e-3
    )
    assert record["solver"] == {"linear_solver": "banded", "rtol": 2e-5, "contact_smoothing": 0.01}
    assert record["membrane"]["cap_divisions"] == 4  # the overrides are recorded
    assert not list(tmp_path.rglob("*.h5"))  # the timed shard went to a temporary directory


def test_benchmark_tactile_names_a_misspelled_key(tmp_path):
    run = _run(tmp_path, "solver.contact_smothing=0")
    assert run.returncode != 0
    assert "contact_smothing" in run.stderr
