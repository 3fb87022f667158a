"""Paired comparison of two evaluations (defgraspnets.eval.compare, scripts/compare_evaluations.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from defgraspnets.eval.compare import compare_evaluations, paired_difference
from defgraspnets.eval.metrics import _cluster_bootstrap_interval

ROOT = Path(__file__).resolve().parents[1]


def _results(group_taus: list[np.ndarray], mae=None, nodes=None, split="unseen_grasps") -> dict:
    """A results.json with one per-object row per entry of ``group_taus`` (that object's group taus)."""
    rows = []
    for k, taus in enumerate(group_taus):
        row = {"split": split, "object": f"obj{k:02d}", "samples": 10 + k, "tau_groups": len(taus)}
        row.update(tau_s=float(np.mean(taus)), tau_d=float(np.mean(taus)))
        row.update(mae_stress_kpa=1.0 if mae is None else mae[k], mae_deformation_mm=0.1)
        if nodes is not None:
            row["nodes"] = nodes[k]
        rows.append(row)
    return {"levels": [], "objects": rows}


def _group_taus(num_objects: int, seed: int, shift: float = 0.0, noise: float = 0.0):
    """Per object 3-8 group taus around an object effect; B's are A's + shift (+ noise)."""
    rng = np.random.default_rng(seed)
    a, b = [], []
    for _ in range(num_objects):
        m = int(rng.integers(3, 9))
        taus = np.clip(rng.uniform(-0.5, 0.9) + 0.1 * rng.standard_normal(m), -1, 1)
        a.append(taus)
        b.append(taus + shift + noise * rng.standard_normal(m))
    return a, b


def test_paired_interval_is_the_cluster_bootstrap_of_the_group_differences():
    a, b = _group_taus(12, seed=1, shift=0.05, noise=0.05)
    rows = compare_evaluations(_results(a), _results(b), metrics=["tau_s"])
    (row,) = rows
    groups_a, groups_b = np.concatenate(a), np.concatenate(b)
    clusters = np.concatenate([np.full(len(t), k) for k, t in enumerate(a)])
    # the level's tau is the mean over groups; the per-object rows (mean + count) carry it exactly
    assert row["a"] == pytest.approx(groups_a.mean(), abs=1e-12)
    assert row["b"] == pytest.approx(groups_b.mean(), abs=1e-12)
    assert row["difference"] == pytest.approx((groups_b - groups_a).mean(), abs=1e-12)
    # and the same resampled objects as the group-level cluster bootstrap of the differences
    low, high = _cluster_bootstrap_interval(groups_b - groups_a, clusters)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx((low, high), abs=1e-12)
    assert row["objects"] == 12 and row["weights"] == "tau_groups"


def test_pairing_cancels_the_spread_between_objects():
    # objects differ a lot in how well they rank (-0.5 ... 0.9); B is better by 0.05 on every group
    a, b = _group_taus(18, seed=2, shift=0.05, noise=0.02)
    (row,) = compare_evaluations(_results(a), _results(b), metrics=["tau_d"])
    clusters = np.concatenate([np.full(len(t), k) for k, t in enumerate(b)])
    own_low, own_high = _cluster_bootstrap_interval(np.concatenate(b), clusters)
    assert row["ci_low"] > 0.0 and row["b_better_fraction"] == 1.0
    assert row["ci_high"] - row["ci_low"] < 0.1 * (own_high - own_low)
    # no difference: an interval around 0, B better in about half the resamples
    a2, b2 = _group_taus(18, seed=3, shift=0.0, noise=0.05)
    (row2,) = compare_evaluations(_results(a2), _results(b2), metrics=["tau_d"])
    assert row2["ci_low"] < 0.0 < row2["ci_high"] and 0.1 < row2["b_better_fraction"] < 0.9


def test_identical_and_shifted_evaluations():
    a, _ = _group_taus(5, seed=4)
    (same,) = compare_evaluations(_results(a), _results(a), metrics=["tau_s"])
    assert same["difference"] == 0.0 and (same["ci_low"], same["ci_high"]) == (0.0, 0.0)
    assert same["b_better_fraction"] == 0.0
    (shifted,) = compare_evaluations(_results(a), _results([t + 0.1 for t in a]), metrics=["tau_s"])
    assert shifted["difference"] == pytest.approx(0.1)
    assert (shifted["ci_low"], shifted["ci_high"]) == pytest.approx((0.1, 0.1))


def test_errors_are_better_when_lower_and_weighted_by_nodes():
    a, _ = _group_taus(4, seed=5)
    nodes = [100, 300, 100, 500]
    res_a = _results(a, mae=[1.0, 2.0, 3.0, 4.0], nodes=nodes)
    res_b = _results(a, mae=[0.5, 1.5, 2.5, 3.5], nodes=nodes)
    (row,) = compare_evaluations(res_a, res_b, metrics=["mae_stress_kpa"])
    assert row["weights"] == "nodes" and row["difference"] == pytest.approx(-0.5)
    assert row["a"] == pytest.approx(np.dot(nodes, [1, 2, 3, 4]) / sum(nodes))
    assert row["b_better_fraction"] == 1.0
    # older evaluations without node counts: weighted by samples, and the row says so
    (old,) = compare_evaluations(_results(a, mae=[1.0, 2.0, 3.0, 4.0]), res_b, metrics=["mae_stress_kpa"])
    assert old["weights"] == "samples"
    assert old["a"] == pytest.approx(np.dot([10, 11, 12, 13], [1, 2, 3, 4]) / 46)


def test_bad_comparisons_are_named():
    a, b = _group_taus(4, seed=6)
    res_a, res_b = _results(a), _results(b)
    res_b["objects"][2]["object"] = "lemon"
    with pytest.raises(ValueError, match=r"objects \['lemon', 'obj02'\] are in only one"):
        compare_evaluations(res_a, res_b)
    res_c = _results([np.append(b[0], 0.5), *b[1:]])
    with pytest.raises(ValueError, match="obj00: .* tau groups: the two evaluations did not see the same"):
        compare_evaluations(res_a, res_c)
    with pytest.raises(ValueError, match="different levels"):
        compare_evaluations(res_a, _results(b, split="unseen_E"))
    with pytest.raises(ValueError, match="unknown metrics"):
        compare_evaluations(res_a, _results(b), metrics=["accuracy"])
    with pytest.raises(ValueError, match="no per-object rows"):
        compare_evaluations({"levels": []}, res_a)
    with pytest.raises(ValueError, match="weights must be positive"):
        paired_difference([0.1, 0.2], [0.2, 0.3], [1, 0])
    with pytest.raises(ValueError, match="level must lie in"):
        paired_difference([0.1, 0.2], [0.2, 0.3], [1, 1], level=95)
    single = paired_difference([0.1], [0.3], [2])
    assert single["difference"] == pytest.approx(0.2) and np.isnan(single["ci_low"])


def test_compare_script_writes_markdown_and_json(tmp_path):
    a, b = _group_taus(6, seed=7, shift=0.1, noise=0.02)
    (tmp_path / "a.json").write_text(json.dumps(_results(a)))
    (tmp_path / "b.json").write_text(json.dumps(_results(b)))
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "compare_evaluations.py"),
        "a=a.json",
        "b=b.json",
        "out_dir=out",
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads((tmp_path / "out" / "comparison.json").read_text())
    assert [r["metric"] for r in out["rows"]] == ["tau_s", "tau_d", "mae_stress_kpa", "mae_deformation_mm"]
    assert out["rows"][0]["difference"] == pytest.approx(np.concatenate(b).mean() - np.concatenate(a).mean())
    assert "| unseen_grasps | tau_s | 6 | tau_groups |" in (tmp_path / "out" / "comparison.md").read_text()
    missing = subprocess.run(
        [*cmd[:2], "a=a.json", "b=nowhere.json"], capture_output=True, text=True, cwd=tmp_path, env=env
    )
    assert missing.returncode != 0 and "evaluation results not found: nowhere.json" in missing.stderr
