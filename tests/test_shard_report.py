"""Grasp data report: status counts by cause, field magnitudes, ranking agreement across moduli."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_data_synthetic import make_shards

from defgraspnets.data.grasp_schema import GraspShard
from defgraspnets.data.shard_report import settings_note, shard_summary, status_name
from defgraspnets.eval.metrics import ranking_agreement_across_moduli
from defgraspnets.fem.results import SolveStatus
from defgraspnets.grasp.datagen import STATUS_INVERTED

ROOT = Path(__file__).resolve().parents[1]


def test_ranking_agreement_across_moduli():
    grasp_value = np.array([3.0, 1.0, 4.0, 1.5, 9.0])
    same = np.broadcast_to(grasp_value[None, :, None], (2, 5, 3))
    ok = np.ones((2, 5), bool)
    assert ranking_agreement_across_moduli(same, ok) == (pytest.approx(1.0), 3)
    # modulus 1 ranks the grasps backwards, modulus 2 like modulus 0: pairs -1, +1, -1
    three = np.stack([grasp_value, 1.0 / grasp_value, 2.0 * grasp_value])[:, :, None]
    assert ranking_agreement_across_moduli(three, np.ones((3, 5), bool)) == (pytest.approx(-1 / 3), 3)
    # a pair needs min_grasps grasps converged at both moduli
    ok[1, 2:] = False
    assert np.isnan(ranking_agreement_across_moduli(same, ok)[0])
    with pytest.raises(ValueError, match="values \\(K, G, S\\) and converged \\(K, G\\) expected"):
        ranking_agreement_across_moduli(same[0], ok)


def test_status_names():
    assert status_name(0) == "CONVERGED" and status_name(SolveStatus.PINCHED) == "PINCHED"
    assert status_name(STATUS_INVERTED) == "INVERTED" and status_name(99) == "code 99"


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return make_shards(tmp_path_factory.mktemp("report"), grasps=4, num_steps=3, with_real=False)


def test_shard_summary_counts_and_magnitudes(shards):
    shard = GraspShard(shards / "cuboid_a__shard0of2.h5")  # ramp (1, 2) failed with NaN fields
    row = shard_summary(shard)
    assert row["ramps"] == shard.status.size and row["converged"] == row["ramps"] - 1
    assert row["status"] == {"CONVERGED": row["ramps"] - 1, "NONFINITE": 1}
    last = [
        np.mean(shard.fields(k, g, -1)[0])
        for k in range(shard.num_moduli)
        for g in range(shard.num_grasps)
        if shard.status[k, g] == 0
    ]
    assert row["mean_stress_kpa"] == pytest.approx(np.median(last) / 1e3, rel=1e-6)
    # the synthetic stress does not depend on E and the displacement scales as 1/E: the same rankings
    assert row["stress_ranking_agreement"] == pytest.approx(1.0)
    assert row["deformation_ranking_agreement"] == pytest.approx(1.0)


def test_shard_summary_sees_rankings_that_change_with_modulus(shards, tmp_path):
    path = tmp_path / "cuboid_b__shard0of1.h5"
    path.write_bytes((shards / "cuboid_b__shard0of1.h5").read_bytes())
    with h5py.File(path, "r+") as f:
        vm = f["ramp/von_mises"]
        first = vm[0]  # (G, S, N)
        # modulus 1: a uniform stress that ranks the grasps backwards
        vm[1] = np.broadcast_to((1e6 / first.mean(axis=-1))[..., None], first.shape).astype(np.float32)
    row = shard_summary(GraspShard(path))
    assert row["stress_ranking_agreement"] == pytest.approx(-1 / 3)
    assert row["deformation_ranking_agreement"] == pytest.approx(1.0)


def test_grasp_data_report_script(shards, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    script = str(ROOT / "scripts/grasp_data_report.py")
    cmd = [sys.executable, script, f"data_dir={shards}", f"out_dir={tmp_path}"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = json.loads((tmp_path / "grasp_data_report.json").read_text())["shards"]
    assert len(rows) == len(list(shards.glob("*.h5")))
    text = (tmp_path / "grasp_data_report.md").read_text()
    total = sum(row["ramps"] for row in rows)
    assert f"| **all** | – | {total - 1} | {total} | NONFINITE 1 |" in text
    assert f"Solver settings: not recorded in the {len(rows)} shard(s)" in text  # synthetic shards
    missing = subprocess.run(
        [*cmd[:2], f"data_dir={tmp_path / 'nowhere'}", f"out_dir={tmp_path}"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert missing.returncode != 0 and "nowhere" in missing.stderr


def test_settings_note_names_the_shards_made_with_other_solver_settings():
    """A data directory whose shards were simulated with different solver settings (a default changed
    between runs) is flagged, naming the odd shards and what differs from the most common setting."""
    early = {"squeeze": {"rtol": 1e-5, "friction_lag_check": 1000.0}}
    late = {"squeeze": {"rtol": 1e-5, "friction_lag_check": 1.0}}
    rows = [{"object": n, "solver_settings": early} for n in ("x", "y")]
    assert settings_note(rows) == "Solver settings: the same in all 2 shard(s)."
    note = settings_note([*rows, {"object": "z", "solver_settings": late}])
    assert note.startswith("**Solver settings differ between shards**: 2 share the most common setting")
    assert "z (squeeze.friction_lag_check: 1000.0 -> 1.0)" in note
    assert "w (none recorded)" in settings_note([*rows, {"object": "w", "solver_settings": {}}])
    assert "not recorded in the 1 shard(s)" in settings_note([{"object": "w", "solver_settings": {}}])
