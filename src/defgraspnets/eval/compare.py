"""Paired comparison of two DefGraspNets evaluations on the same test data (``scripts/evaluate.py``'s
``results.json``): is model B better than model A, and by how much?

Each model's own tau interval (a cluster bootstrap over test objects, :func:`~.metrics.kendall_tau_interval`)
is wide when there are few test objects, because objects differ in how hard their grasps are to rank. Both
models meet the same objects, so that spread is shared: the *paired* bootstrap resamples the test objects
once for both models and gives the interval of the difference, which is much narrower. On the 18-object
data (2010 test samples) the 40- and 80-epoch models' own tau_d intervals are [0.34, 0.73] and [0.44, 0.76];
their difference is +0.07 [-0.04, +0.18].

The per-object rows of ``results.json`` are enough: a level's tau is the mean over (object, modulus, step)
groups, i.e. the mean of the per-object taus weighted by their group counts (``tau_groups``), and its MAEs
are node-weighted (``nodes``; evaluations written before the key existed fall back to the sample count,
which is exact for taus and approximate for MAEs, and the row says so).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .metrics import check_level, cluster_bootstrap_means, percentile_interval

__all__ = ["COMPARED_METRICS", "COMPARISON_COLUMNS", "compare_evaluations", "paired_difference"]

# metric -> (weight key of the per-object rows, higher is better)
COMPARED_METRICS = {
    "tau_s": ("tau_groups", True),
    "tau_d": ("tau_groups", True),
    "mae_stress_kpa": ("nodes", False),
    "mae_deformation_mm": ("nodes", False),
}

# columns of the comparison's Markdown table (eval.report.markdown_table)
COMPARISON_COLUMNS = (
    ("split", "Level", "{}"),
    ("metric", "Metric", "{}"),
    ("objects", "Test objects", "{:d}"),
    ("weights", "Objects weighted by", "{}"),
    ("a", "A", "{:.4g}"),
    ("b", "B", "{:.4g}"),
    ("difference", "B - A", "{:+.4g}"),
    (("ci_low", "ci_high"), "95 % CI (paired)", "[{:+.3g}, {:+.3g}]"),
    ("b_better_fraction", "B better in", "{:.0%}"),
)


def paired_difference(
    values_a, values_b, weights, level: float = 0.95, resamples: int = 2000, seed: int = 0
) -> dict[str, float]:
    """Weighted mean of ``values_b - values_a`` over clusters and its paired cluster-bootstrap interval.

    Args:
        values_a, values_b: (K,) one value per cluster (e.g. each test object's tau) of models A and B.
        weights: (K,) each cluster's weight (e.g. its number of tau groups); must be positive.

    Returns ``difference``, ``ci_low``, ``ci_high``, and ``fraction_positive`` and ``fraction_negative``
    (the shares of resamples whose difference is > 0 and < 0). NaN for those with a single cluster.
    """
    check_level(level)
    a = np.asarray(values_a, dtype=np.float64).ravel()
    b = np.asarray(values_b, dtype=np.float64).ravel()
    w = np.asarray(weights, dtype=np.float64).ravel()
    if not (a.shape == b.shape == w.shape) or not len(a):
        raise ValueError(
            f"need one value of A, of B and one weight per cluster, got {a.shape}, {b.shape}, {w.shape}"
        )
    if not np.all(np.isfinite(a) & np.isfinite(b)):
        raise ValueError("values must be finite")
    if not np.all(np.isfinite(w) & (w > 0)):
        raise ValueError("weights must be positive")
    sums = w * (b - a)
    difference = float(sums.sum() / w.sum())
    if len(a) < 2:
        nan = float("nan")
        return {
            "difference": difference,
            "ci_low": nan,
            "ci_high": nan,
            "fraction_positive": nan,
            "fraction_negative": nan,
        }
    means = cluster_bootstrap_means(sums, w, resamples, seed)
    low, high = percentile_interval(means, level)
    return {
        "difference": difference,
        "ci_low": low,
        "ci_high": high,
        "fraction_positive": float(np.mean(means > 0.0)),
        "fraction_negative": float(np.mean(means < 0.0)),
    }


def _objects_by_split(results: dict, name: str) -> dict[str, dict[str, dict]]:
    rows = results.get("objects")
    if not isinstance(rows, list) or not rows:
        raise ValueError(
            f"evaluation {name} has no per-object rows ('objects'): not a scripts/evaluate.py results.json"
        )
    by_split: dict[str, dict[str, dict]] = {}
    for row in rows:
        by_split.setdefault(row["split"], {})[row["object"]] = row
    return by_split


def compare_evaluations(
    results_a: dict,
    results_b: dict,
    metrics: Sequence[str] = tuple(COMPARED_METRICS),
    level: float = 0.95,
    resamples: int = 2000,
    seed: int = 0,
) -> list[dict]:
    """One row per (level, metric): A's and B's values, B - A with its paired interval over test objects,
    and ``b_better_fraction`` (the share of resamples in which B is better: higher tau, lower MAE).

    ``results_a``, ``results_b``: the parsed ``results.json`` of two evaluations of the same split and test
    data. Raises ValueError naming what differs (a level or object only one of them has, or different tau
    group counts, which means different test data).
    """
    unknown = [m for m in metrics if m not in COMPARED_METRICS]
    if unknown:
        raise ValueError(f"unknown metrics {unknown}; known: {', '.join(COMPARED_METRICS)}")
    objects_a, objects_b = _objects_by_split(results_a, "A"), _objects_by_split(results_b, "B")
    if set(objects_a) != set(objects_b):
        raise ValueError(
            f"the evaluations cover different levels: A {sorted(objects_a)}, B {sorted(objects_b)}"
        )
    out = []
    for split in sorted(objects_a):
        rows_a, rows_b = objects_a[split], objects_b[split]
        only = sorted(set(rows_a) ^ set(rows_b))
        if only:
            raise ValueError(f"level {split}: objects {only} are in only one of the two evaluations")
        names = sorted(rows_a)
        for name in names:
            groups_a, groups_b = rows_a[name]["tau_groups"], rows_b[name]["tau_groups"]
            if groups_a != groups_b:
                raise ValueError(
                    f"level {split}, object {name}: {groups_a} vs {groups_b} tau groups: the two evaluations "
                    "did not see the same test data"
                )
        for metric in metrics:
            weight_key, higher_is_better = COMPARED_METRICS[metric]
            if not all(weight_key in rows_a[n] and weight_key in rows_b[n] for n in names):
                weight_key = "samples"
            a = np.array([rows_a[n][metric] for n in names], dtype=np.float64)
            b = np.array([rows_b[n][metric] for n in names], dtype=np.float64)
            keep = np.isfinite(a) & np.isfinite(b)  # a tau is NaN where an object has no rankable group
            w = np.array([rows_a[n][weight_key] for n in names], dtype=np.float64)[keep]
            d = paired_difference(a[keep], b[keep], w, level, resamples, seed)
            out.append(
                {
                    "split": split,
                    "metric": metric,
                    "objects": int(keep.sum()),
                    "weights": weight_key,
                    "a": float(np.sum(w * a[keep]) / np.sum(w)),
                    "b": float(np.sum(w * b[keep]) / np.sum(w)),
                    "difference": d["difference"],
                    "ci_low": d["ci_low"],
                    "ci_high": d["ci_high"],
                    # B is better where its tau is higher, or its error lower
                    "b_better_fraction": d["fraction_positive" if higher_is_better else "fraction_negative"],
                }
            )
    return out
