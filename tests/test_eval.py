"""Evaluation metrics: Kendall tau vs scipy, grouped tau, field errors in physical units, Chamfer distance."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import kendalltau

from defgraspnets.eval.chamfer import chamfer_distance, nearest_training_object, surface_samples
from defgraspnets.eval.metrics import (
    FieldMetrics,
    grouped_kendall_tau,
    grouped_spread_and_relative_error,
    kendall_tau,
    kendall_tau_interval,
)
from defgraspnets.eval.report import markdown_table, write_json
from defgraspnets.fem.mesh import TetMesh
from defgraspnets.models.graph import NODE_FINGER, NODE_SURFACE, GraspGraph


@pytest.mark.parametrize("seed", range(6))
def test_kendall_tau_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 60))
    x = rng.normal(size=n)
    y = x * rng.uniform(-1, 1) + rng.normal(size=n)
    if seed % 2:  # ties in both sequences
        x, y = np.round(x), np.round(y * 2) / 2
    want = kendalltau(x, y).statistic
    got = kendall_tau(x, y)
    assert (np.isnan(want) and np.isnan(got)) or got == pytest.approx(want, abs=1e-12)


def test_kendall_tau_edge_cases():
    assert kendall_tau([1, 2, 3], [1, 2, 3]) == pytest.approx(1.0)
    assert kendall_tau([1, 2, 3], [3, 2, 1]) == pytest.approx(-1.0)
    assert np.isnan(kendall_tau([1, 1, 1], [1, 2, 3])) and np.isnan(kendall_tau([1], [2]))
    with pytest.raises(ValueError, match="equal lengths"):
        kendall_tau([1, 2], [1, 2, 3])


def test_grouped_spread_and_relative_error_leave_out_offsets_common_to_a_group():
    """Spread: the mean within-group standard deviation of the true values; relative error: that of the
    errors, so a prediction off by a constant per group (whose ranking is exact) has none."""
    groups = np.array([0, 0, 0, 1, 1, 2])  # group 2 has one row: left out
    true = np.array([1.0, 2.0, 3.0, 10.0, 14.0, 99.0])
    offset = np.array([5.0, 5.0, 5.0, -3.0, -3.0, 7.0])
    spread, error = grouped_spread_and_relative_error(groups[:, None], true + offset, true)
    assert spread == pytest.approx((np.std([1.0, 2.0, 3.0]) + np.std([10.0, 14.0])) / 2)
    assert error == pytest.approx(0.0, abs=1e-12)
    assert grouped_kendall_tau(groups[:, None], true + offset, true)[0] == pytest.approx(1.0)
    # noise within group 1 only: half of its standard deviation in the group mean
    noise = np.array([0.0, 0.0, 0.0, 1.0, -1.0, 0.0])
    _, error = grouped_spread_and_relative_error(groups[:, None], true + offset + noise, true)
    assert error == pytest.approx(1.0 / 2)
    assert np.isnan(grouped_spread_and_relative_error(np.arange(3)[:, None], true[:3], true[:3])[0])


def test_min_relative_spread_leaves_groups_of_alike_grasps_out_of_tau():
    """Object 0's four grasps differ by ~10 % and are ranked right; object 1's differ by 0.1 % (a sphere's
    facets) and are ranked backwards. Over all groups tau is 0; with min_relative_spread 0.05 only object 0
    counts, for stress and deformation alike; a negative fraction is refused."""
    true0, true1 = np.array([1.0, 1.1, 1.2, 1.3]), np.array([2.0, 2.001, 2.002, 2.003])
    true = np.concatenate([true0, true1])
    pred = np.concatenate([true0, true1[::-1]])
    n = len(true)
    a = {
        "sample": np.stack([np.zeros(n), np.zeros(n), np.r_[0:4, 0:4], np.zeros(n)], axis=1),
        "object_id": np.repeat([0, 1], 4),
        "youngs_modulus": np.full(n, 1e6),
        "force": np.full(n, 5.0),
        "nodes": np.full(n, 10.0),
        "stress_abs_err": np.zeros(n),
        "deform_abs_err": np.zeros(n),
        "disp_abs_err": np.zeros(n),
        "mean_stress_pred": pred * 1e3,
        "mean_stress_true": true * 1e3,
        "max_stress_pred": pred,
        "max_stress_true": true,
        "mean_deform_pred": pred * 1e-4,
        "mean_deform_true": true * 1e-4,
    }
    everything = FieldMetrics.summarize(a)
    assert everything["tau_s"] == pytest.approx(0.0) and everything["tau_groups"] == 2
    spread = FieldMetrics.summarize(a, min_relative_spread=0.05)
    assert spread["tau_s"] == pytest.approx(1.0) and spread["tau_d"] == pytest.approx(1.0)
    assert spread["tau_groups"] == spread["tau_d_groups"] == 1
    assert spread["mae_stress_pa"] == everything["mae_stress_pa"]  # only tau is restricted
    sphere = FieldMetrics.summarize({k: v[4:] for k, v in a.items()}, min_relative_spread=0.05)
    assert np.isnan(sphere["tau_s"]) and sphere["tau_groups"] == 0  # no group left to rank
    with pytest.raises(ValueError, match="min_relative_spread"):
        FieldMetrics(min_relative_spread=-0.1)


def test_grouped_kendall_tau_averages_groups():
    groups = np.array([0, 0, 0, 1, 1, 1, 2])  # group 2 has a single sample: no tau
    pred = np.array([1, 2, 3, 1, 2, 3, 5.0])
    true = np.array([1, 2, 3, 3, 2, 1, 5.0])
    tau, n = grouped_kendall_tau(groups[:, None], pred, true)
    assert n == 2 and tau == pytest.approx(0.0)


def _clustered_rankings(objects: int, groups_per_object: int = 4):
    """Rows of 3-grasp groups; even objects ranked right (tau 1), odd ones reversed (tau -1)."""
    groups, clusters, pred, true = [], [], [], []
    for o in range(objects):
        for g in range(groups_per_object):
            for i in range(3):
                groups.append((o, g))
                clusters.append(o)
                true.append(float(i))
                pred.append(float(i if o % 2 == 0 else 2 - i))
    return np.array(groups), np.array(clusters), np.array(pred), np.array(true)


def test_kendall_tau_interval_resamples_objects_not_groups():
    groups, clusters, pred, true = _clustered_rankings(32)
    tau, n = grouped_kendall_tau(groups, pred, true)
    assert n == 128 and tau == pytest.approx(0.0)
    low, high = kendall_tau_interval(groups, clusters, pred, true)
    # object means are +-1 (variance 1): the mean over 32 objects has standard error 1/sqrt(32); resampling
    # the 128 groups as if independent would give half that
    assert low < tau < high
    assert high - low == pytest.approx(2 * 1.96 / np.sqrt(32), rel=0.15)
    # four times the objects: half the width
    low4, high4 = kendall_tau_interval(*_clustered_rankings(128))
    assert (high - low) / (high4 - low4) == pytest.approx(2.0, rel=0.2)


def test_kendall_tau_interval_edge_cases():
    groups, clusters, pred, true = _clustered_rankings(6)
    agree = np.array(true)  # every object ranked right: no spread to resample
    assert kendall_tau_interval(groups, clusters, agree, true) == pytest.approx((1.0, 1.0))
    one = clusters == 0
    assert np.all(np.isnan(kendall_tau_interval(groups[one], clusters[one], pred[one], true[one])))
    assert kendall_tau_interval(groups, clusters, pred, true, seed=3) == kendall_tau_interval(
        groups, clusters, pred, true, seed=3
    )
    with pytest.raises(ValueError, match="level must lie in"):
        kendall_tau_interval(groups, clusters, pred, true, level=95)


def _batch(stress, disp, obj_nodes=3):
    """Two graphs of obj_nodes object nodes + 1 finger node each."""
    n = obj_nodes + 1
    node_type = torch.tensor(([NODE_SURFACE] * obj_nodes + [NODE_FINGER]) * 2)
    g = GraspGraph(
        pos=torch.zeros(2 * n, 3),
        node_type=node_type,
        stress=stress,
        displacement=disp,
        force=torch.tensor([1.0, 2.0]),
        youngs_modulus=torch.tensor([1e5, 1e5]),
        sample=torch.tensor([[0, 0, 0, 0], [0, 0, 1, 0]]),
        object_id=torch.tensor([0, 0]),
        num_nodes=2 * n,
    )
    g.batch = torch.arange(2).repeat_interleave(n)
    return g


def test_field_metrics_in_physical_units():
    true_s = torch.tensor([1e3, 2e3, 3e3, 0.0, 4e3, 5e3, 6e3, 0.0], dtype=torch.float64)
    true_d = torch.zeros(8, 3, dtype=torch.float64)
    true_d[:, 0] = torch.tensor([1, 2, 3, 0, 4, 5, 6, 0]) * 1e-3
    pred_s = true_s + torch.tensor([100.0, -100, 100, 9e9, 100, -100, 100, 9e9])  # finger nodes ignored
    pred_d = true_d.clone()
    pred_d[:, 1] += 1e-3  # |d| error sqrt(x^2 + 1e-6) - x, vector error 1 mm
    m = FieldMetrics()
    m.update(pred_s, pred_d, _batch(true_s, true_d))
    out = m.compute()
    assert out["samples"] == 2 and out["nodes"] == 6 and out["mae_stress_pa"] == pytest.approx(100.0)
    assert out["mae_stress_kpa"] == pytest.approx(0.1)
    assert out["mae_displacement_mm"] == pytest.approx(1.0)
    x = np.array([1, 2, 3, 4, 5, 6]) * 1e-3
    assert out["mae_deformation_mm"] == pytest.approx(np.mean(np.sqrt(x**2 + 1e-6) - x) * 1e3)
    assert (
        out["tau_s"] == pytest.approx(1.0) and out["tau_d"] == pytest.approx(1.0) and out["tau_groups"] == 1
    )
    a = m.arrays()
    np.testing.assert_allclose(a["mean_stress_true"], [2e3, 5e3])
    np.testing.assert_allclose(a["max_stress_pred"], [3.1e3, 6.1e3])
    assert list(m.compute_per_object()) == [0]


def test_chamfer_distance():
    a = np.random.default_rng(0).normal(size=(200, 3))
    assert chamfer_distance(a, a) == 0.0
    assert chamfer_distance(a, a + [0.01, 0, 0]) == pytest.approx(0.01, rel=1e-9)
    box = TetMesh.box((0.04, 0.04, 0.04), (2, 2, 2))
    big = TetMesh.box((0.05, 0.04, 0.04), (2, 2, 2), origin=(1.0, 0, 0))  # translation is removed
    s_box = surface_samples(box.points, box.surface_faces, 3000, seed=1)
    s_box2 = surface_samples(box.points, box.surface_faces, 3000, seed=2)
    s_big = surface_samples(big.points, big.surface_faces, 3000)
    assert np.abs(s_box.mean(0)).max() < 1e-3
    assert chamfer_distance(s_box, s_box2) < 1.5e-3 < chamfer_distance(s_box, s_big) < 5e-3
    name, d = nearest_training_object(s_box, {"big": s_big, "same": s_box2})
    assert name == "same" and d == pytest.approx(chamfer_distance(s_box, s_box2))


def test_report_writers(tmp_path):
    rows = [
        {
            "split": "unseen_E",
            "displacement_target": "total",
            "samples": 3,
            "tau_s": 0.5,
            "tau_d": float("nan"),
            "tau_s_ci_low": 0.25,
            "tau_s_ci_high": 0.75,
            "tau_d_ci_low": float("nan"),
            "tau_d_ci_high": float("nan"),
            "mae_stress_kpa": 1.0,
            "mae_deformation_mm": 0.25,
            "relative_error_mean_stress_kpa": 0.5,
            "spread_mean_stress_kpa": 2.0,
        }
    ]
    text = markdown_table(rows)
    assert (
        text.splitlines()[2]
        == "| unseen_E | total | 3 | 0.50 | n/a | [0.25, 0.75] | n/a | 1 | 0.25 | 0.5 / 2 |"
    )
    write_json(tmp_path / "r.json", {"rows": rows})
    assert '"tau_d": null' in (tmp_path / "r.json").read_text()
