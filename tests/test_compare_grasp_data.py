"""Comparison of two data sets of the same grasps (defgraspnets.data.shard_compare) on synthetic shards whose
differences are known: a scaled stress field, a rigidly rotated final state, a ramp failed in one set."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_data_synthetic import make_shards

from defgraspnets.data.shard_compare import compare_grasp_data, comparison_markdown, pooled_summary

ROOT = Path(__file__).resolve().parents[1]
SHARD = "cuboid_b__shard0of1.h5"


@pytest.fixture(scope="module")
def data_a(tmp_path_factory) -> Path:
    return make_shards(tmp_path_factory.mktemp("a") / "grasps", with_real=False)


def _copy(data_a: Path, tmp_path: Path) -> Path:
    b = tmp_path / "b"
    shutil.copytree(data_a, b)
    return b


def _ramp(rows, shard, k, g):
    (row,) = [r for r in rows if r["shard"] == shard]
    return row, {(r["k"], r["g"]): r for r in row["ramps"]}[(k, g)]


def test_identical_data_agree_exactly(data_a):
    rows = compare_grasp_data(data_a, data_a)
    assert len(rows) == 6  # cuboid_a in two shards, cuboid_b, cuboid_c, slab_a, slab_b
    s = pooled_summary(rows)
    assert s["solved_both"] == s["solved_a"] == s["solved_b"] == s["ramps_total"] - 1  # one failed ramp
    for metric in ("mean_stress_rel", "stress_field_rel", "deformation_rel", "rotation_deg"):
        assert s[metric]["max"] == pytest.approx(0.0, abs=1e-6), metric
    assert s["stress_outside"] == s["rotation_outside"] == 0
    assert s["stress_ranking_tau_mean"] == pytest.approx(1.0)


def test_known_differences_are_measured(data_a, tmp_path):
    b = _copy(data_a, tmp_path)
    angle = np.radians(10.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    with h5py.File(b / SHARD, "r+") as f:
        rest = f["object/points"][()]
        f["ramp/von_mises"][0, 1, -1] = f["ramp/von_mises"][0, 1, -1] * 1.05  # 5 % more stress everywhere
        # the final state of (0, 3) turned 10 deg about z as a rigid body: same deformation, another pose
        x = rest + f["ramp/displacement"][0, 3, -1]
        f["ramp/displacement"][0, 3, -1] = (x @ R.T + [0.002, 0.0, 0.0]) - rest
        f["ramp/status"][1, 4] = 1  # failed in B only
    rows = compare_grasp_data(data_a, b)
    row, scaled = _ramp(rows, SHARD, 0, 1)
    assert scaled["mean_stress_rel"] == pytest.approx(0.05, rel=1e-5)
    assert scaled["stress_field_rel"] == pytest.approx(0.05, rel=1e-5)
    assert scaled["rotation_deg"] == pytest.approx(0.0, abs=1e-4) and scaled["deformation_rel"] < 1e-5
    _, turned = _ramp(rows, SHARD, 0, 3)
    assert turned["rotation_deg"] == pytest.approx(10.0, abs=1e-3)
    assert turned["deformation_rel"] < 1e-4 and turned["mean_stress_rel"] == 0.0
    assert row["solved_a"] == row["solved_b"] + 1 == row["solved_both"] + 1
    assert (1, 4) not in {(r["k"], r["g"]) for r in row["ramps"]}
    s = pooled_summary(rows, stress_tolerance=0.01, rotation_tolerance_deg=1.0)
    assert s["stress_outside"] == 1 and s["rotation_outside"] == 1
    assert s["rotation_deg"]["max"] == pytest.approx(10.0, abs=1e-3)
    text = comparison_markdown(rows, "plain", "stabilized")
    ramps = row["ramps_total"]
    with h5py.File(data_a / SHARD) as f:
        assert ramps == f["ramp/status"].size
    assert "A = plain vs B = stabilized" in text and f"| cuboid_b | {ramps} | {ramps} | {ramps - 1} |" in text


def test_different_grasps_or_shards_are_refused(data_a, tmp_path):
    b = _copy(data_a, tmp_path)
    with h5py.File(b / SHARD, "r+") as f:
        f["grasps/pose"][2, 0, 3] += 1e-3  # another grasp
    with pytest.raises(ValueError, match="cuboid_b__shard0of1.h5 .*grasp poses differ"):
        compare_grasp_data(data_a, b)
    c = _copy(data_a, tmp_path / "c")
    (c / SHARD).unlink()
    with pytest.raises(ValueError, match=r"only in .*: \['cuboid_b__shard0of1.h5'\]"):
        compare_grasp_data(data_a, c)
    with h5py.File(c / "slab_a__shard0of1.h5", "r+") as f:
        f["material/youngs_modulus"][0] *= 2
    (c / SHARD).symlink_to(data_a / SHARD)
    with pytest.raises(ValueError, match="Young's moduli differ"):
        compare_grasp_data(data_a, c)
    with pytest.raises(FileNotFoundError):
        compare_grasp_data(data_a, tmp_path / "missing")


def test_script_writes_markdown_and_json(data_a, tmp_path):
    b = _copy(data_a, tmp_path)
    with h5py.File(b / SHARD, "r+") as f:
        f["ramp/von_mises"][0, 1, -1] = f["ramp/von_mises"][0, 1, -1] * 1.05
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts/compare_grasp_data.py"),
            f"a={data_a}",
            f"b={b}",
            f"out_dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads((tmp_path / "grasp_data_comparison.json").read_text())
    assert out["all"]["stress_outside"] == 1 and out["all"]["solved_both"] == out["all"]["ramps_total"] - 1
    assert len(out["shards"]) == 6 and "cuboid_b" in (tmp_path / "grasp_data_comparison.md").read_text()
    bad = subprocess.run(
        [sys.executable, str(ROOT / "scripts/compare_grasp_data.py"), f"a={data_a}", f"b={b}", "step=9"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert bad.returncode != 0 and "step=9 is outside the 4-step ramp" in bad.stderr
