r"""Prediction metrics of thesis §7.6: Kendall's tau of grasp rankings and mean absolute errors.

Kendall's tau-b of paired rankings ``x, y`` (n,) (ties handled as in ``scipy.stats.kendalltau``):

    tau_b = sum_{i<j} sgn(x_i - x_j) sgn(y_i - y_j)
            / sqrt( sum_{i<j} sgn(x_i - x_j)^2  sum_{i<j} sgn(y_i - y_j)^2 )

``tau_s`` ranks grasps by mean von Mises stress over the object's vertices, ``tau_d`` by mean deformation
``|d|`` (thesis §7.4: the distance between rest and deformed vertex positions). Rankings compare grasps of
the same object, modulus and ramp step (the same commanded force level); tau is averaged over such groups.
How far the mean tau can be trusted is the 95 % interval of a cluster bootstrap over objects
(:func:`kendall_tau_interval`): the groups of one object share its few test grasps, so they are not
independent, and resampling groups would understate the spread; resampling whole objects does not.
Errors are node-weighted over all object vertices: stress MAE [Pa] (also reported in kPa), deformation MAE
``| |d_pred| - |d_true| |`` [mm] and displacement-vector MAE ``|d_pred - d_true|`` [mm].
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "FieldMetrics",
    "PerSampleSums",
    "grouped_kendall_tau",
    "grouped_spread_and_relative_error",
    "kendall_tau",
    "kendall_tau_interval",
    "ranking_agreement_across_moduli",
]


def kendall_tau(x, y) -> float:
    """Kendall's tau-b of two (n,) sequences; NaN if either is constant or n < 2. O(n^2), vectorized."""
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"kendall_tau needs equal lengths, got {x.shape} and {y.shape}")
    if len(x) < 2 or not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        return float("nan")
    i, j = np.triu_indices(len(x), k=1)
    sx, sy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
    denom = np.sqrt(np.sum(sx * sx) * np.sum(sy * sy))
    return float(np.sum(sx * sy) / denom) if denom > 0 else float("nan")


def _group_taus(groups, pred, true) -> tuple[np.ndarray, np.ndarray]:
    """(first row index of each group with a defined tau, its tau) for rows of ``groups`` (n, k)."""
    groups = np.asarray(groups).reshape(len(pred), -1)
    pred, true = np.asarray(pred), np.asarray(true)
    _, first, inverse = np.unique(groups, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    taus = np.array([kendall_tau(pred[inverse == u], true[inverse == u]) for u in range(len(first))])
    keep = np.isfinite(taus)
    return first[keep], taus[keep]


def _group_index(groups) -> tuple[np.ndarray, np.ndarray]:
    """(n,) group of each row of ``groups`` (n, k) (rows with equal keys share one) and (m,) group sizes."""
    _, inverse, counts = np.unique(groups, axis=0, return_inverse=True, return_counts=True)
    return inverse.ravel(), counts


def _group_mean_and_std(inverse, counts, values) -> tuple[np.ndarray, np.ndarray]:
    """(m,) mean and (population) standard deviation of ``values`` (n,) within each group."""
    mean = np.bincount(inverse, weights=values, minlength=len(counts)) / counts
    var = np.bincount(inverse, weights=(values - mean[inverse]) ** 2, minlength=len(counts)) / counts
    return mean, np.sqrt(var)


def grouped_spread_and_relative_error(groups, pred, true) -> tuple[float, float]:
    """What a ranking within groups has to resolve, and how well the prediction resolves it.

    Over the groups (rows of ``groups`` (n, k) with equal keys) of two or more rows: the mean of the
    standard deviation of ``true`` within each group (the grasp-to-grasp spread that tau ranks), and the mean
    of the standard deviation of the errors ``pred - true`` within each group (the error that can reorder
    grasps: an offset common to a whole group changes no rank, so it is left out). Where the second is as
    large as the first, a group's ranking is mostly noise. Returns (spread, relative error); (NaN, NaN)
    without a group of two rows."""
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    inverse, counts = _group_index(np.asarray(groups).reshape(len(pred), -1))
    ranked = counts >= 2
    if not ranked.any():
        return float("nan"), float("nan")
    spread = _group_mean_and_std(inverse, counts, true)[1]
    error = _group_mean_and_std(inverse, counts, pred - true)[1]
    return float(np.mean(spread[ranked])), float(np.mean(error[ranked]))


def _groups_spread_at_least(groups, true, fraction: float) -> np.ndarray:
    """(n,) rows whose group (equal rows of ``groups``) has a standard deviation of ``true`` of at least
    ``fraction`` of the magnitude of its mean (every row for fraction 0)."""
    true = np.asarray(true, dtype=np.float64)
    if fraction <= 0:
        return np.ones(len(true), dtype=bool)
    inverse, counts = _group_index(groups)
    mean, std = _group_mean_and_std(inverse, counts, true)
    return (std >= fraction * np.abs(mean))[inverse]


def grouped_kendall_tau(groups, pred, true) -> tuple[float, int]:
    """Mean tau-b over groups (rows of ``groups`` (n, k) with equal keys) with a defined tau.

    Returns:
        (mean tau, number of groups it averages); (NaN, 0) if no group has a defined tau.
    """
    _, taus = _group_taus(groups, pred, true)
    return (float(np.mean(taus)), len(taus)) if len(taus) else (float("nan"), 0)


def kendall_tau_interval(
    groups, clusters, pred, true, level: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile interval of the mean group tau (:func:`grouped_kendall_tau`) by a cluster bootstrap.

    Every group lies in one cluster (``clusters`` (n,), e.g. the object id of each row; rows of one group
    must share it). A resample draws as many clusters as there are, with replacement, and averages the taus
    of all their groups. Returns (low, high); (NaN, NaN) with fewer than two clusters that have a tau.
    """
    first, taus = _group_taus(groups, pred, true)
    return _cluster_bootstrap_interval(taus, np.asarray(clusters).ravel()[first], level, resamples, seed)


def _cluster_bootstrap_interval(
    taus: np.ndarray, clusters: np.ndarray, level: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """:func:`kendall_tau_interval` of group taus ``taus`` (m,) in clusters ``clusters`` (m,)."""
    check_level(level)
    if not len(taus):
        return float("nan"), float("nan")
    _, cluster_of_group = np.unique(clusters, return_inverse=True)
    cluster_of_group = cluster_of_group.ravel()
    num_clusters = int(cluster_of_group.max()) + 1
    if num_clusters < 2:
        return float("nan"), float("nan")
    tau_sum = np.bincount(cluster_of_group, weights=taus, minlength=num_clusters)
    count = np.bincount(cluster_of_group, minlength=num_clusters).astype(np.float64)
    return percentile_interval(cluster_bootstrap_means(tau_sum, count, resamples, seed), level)


def check_level(level: float) -> None:
    """Raise ValueError unless ``level`` (a confidence level) lies in (0, 1)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")


def percentile_interval(samples: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """(low, high): the central ``level`` percentile interval of bootstrap ``samples``."""
    check_level(level)
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(samples, [alpha, 1.0 - alpha])
    return float(low), float(high)


def cluster_bootstrap_means(sums, counts, resamples: int = 2000, seed: int = 0) -> np.ndarray:
    """(resamples,) weighted means of a cluster bootstrap: each resample draws as many clusters as there are,
    with replacement, and returns ``sum(sums[drawn]) / sum(counts[drawn])``.

    ``sums`` (K,): each cluster's total (e.g. the sum of its group taus); ``counts`` (K,): its weight (e.g.
    its number of groups). The same seed draws the same clusters for any two inputs of one size, which is
    what a paired comparison of two models on the same clusters needs."""
    sums = np.asarray(sums, dtype=np.float64).ravel()
    counts = np.asarray(counts, dtype=np.float64).ravel()
    if sums.shape != counts.shape:
        raise ValueError(f"sums and counts differ in shape: {sums.shape} vs {counts.shape}")
    draws = np.random.default_rng(seed).integers(0, len(sums), size=(resamples, len(sums)))
    return sums[draws].sum(axis=1) / counts[draws].sum(axis=1)


def ranking_agreement_across_moduli(values, converged, min_grasps: int = 3) -> tuple[float, int]:
    """Mean Kendall tau between the grasp rankings of every two moduli of one object at the same ramp step.

    The ground truth's own answer to "how much of a grasp's rank is set by where it grasps": in linear
    elasticity at a given force, the stress field hardly depends on E, so the rankings of the same grasps at
    two moduli agree unless contact (which vertices touch, slip, friction) changes them. It bounds what
    the unseen-modulus level can reach with rankings carried over from the training moduli.

    Args:
        values: (K, G, S) per-grasp summaries (e.g. mean von Mises stress) at K moduli, G grasps, S steps.
        converged: (K, G) bool, the ramps that may be used.
        min_grasps: a pair of moduli counts at a step only if this many grasps converged at both.

    Returns:
        (mean tau over modulus pairs and steps, number of (pair, step) rankings it averages); (NaN, 0) if
        there is none.
    """
    values = np.asarray(values, dtype=np.float64)
    converged = np.asarray(converged, dtype=bool)
    if values.ndim != 3 or converged.shape != values.shape[:2]:
        raise ValueError(
            f"values (K, G, S) and converged (K, G) expected, got {values.shape}, {converged.shape}"
        )
    taus = []
    for a in range(values.shape[0]):
        for b in range(a + 1, values.shape[0]):
            both = converged[a] & converged[b]
            if both.sum() < min_grasps:
                continue
            for s in range(values.shape[2]):
                taus.append(kendall_tau(values[a, both, s], values[b, both, s]))
    taus = [t for t in taus if np.isfinite(t)]
    return (float(np.mean(taus)), len(taus)) if taus else (float("nan"), 0)


class PerSampleSums:
    """Per-sample summaries of an evaluation split (one row per graph, keyed by its ``sample`` id (shard,
    k, g, s)), kept on the CPU and mergeable over DDP ranks. Subclasses name their columns in ``_KEYS`` (the
    first being ``sample``) and append a batch's rows with :meth:`_append`."""

    _KEYS: tuple[str, ...] = ("sample",)

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self._parts: dict[str, list[np.ndarray]] = defaultdict(list)

    def __len__(self) -> int:
        return int(sum(len(p) for p in self._parts["sample"]))

    def _append(self, values: dict[str, Tensor]) -> None:
        for k in self._KEYS:
            self._parts[k].append(values[k].detach().cpu().numpy())

    def arrays(self) -> dict[str, np.ndarray]:
        """Per-sample summaries, concatenated."""
        if not len(self):
            return {k: np.zeros((0, 4) if k == "sample" else (0,)) for k in self._KEYS}
        return {k: np.concatenate(self._parts[k]) for k in self._KEYS}

    def gather(self) -> None:
        """Merge the summaries of all DDP ranks (no-op without torch.distributed).

        Samples seen by several ranks (a DistributedSampler pads the last batch with repeats) count once.
        """
        import torch.distributed as dist

        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return
        everyone: list = [None] * dist.get_world_size()
        dist.all_gather_object(everyone, self.arrays())
        merged = {k: np.concatenate([part[k] for part in everyone]) for k in self._KEYS}
        _, first = np.unique(merged["sample"], axis=0, return_index=True)
        self.reset()
        for k in self._KEYS:
            self._parts[k].append(merged[k][np.sort(first)])


class FieldMetrics(PerSampleSums):
    """Accumulates per-sample summaries of predicted vs true fields; :meth:`compute` gives the metrics.

    Per sample (graph) it keeps: ``sample`` (shard, k, g, s), ``object_id``, ``E`` [Pa], ``force`` [N], mean
    and max stress [Pa] (pred/true), mean deformation [m] (pred/true) and error sums over object nodes.
    Works on any device; summaries are moved to the CPU.

    ``min_relative_spread``: tau (and its interval) averages only the groups whose true values spread by at
    least this fraction of their mean (standard deviation / mean), separately for stress and deformation.
    The grasps of a sphere are all alike up to the mesh's facets (a spread of 1-2 %): their order is the
    discretization's, not the object's. 0 (default): every group.
    """

    def __init__(self, min_relative_spread: float = 0.0):
        if not (np.isfinite(min_relative_spread) and min_relative_spread >= 0):
            raise ValueError(f"min_relative_spread must be a fraction >= 0, got {min_relative_spread!r}")
        self.min_relative_spread = float(min_relative_spread)
        super().__init__()

    _KEYS = (
        "sample",
        "object_id",
        "youngs_modulus",
        "force",
        "nodes",
        "stress_abs_err",
        "deform_abs_err",
        "disp_abs_err",
        "mean_stress_pred",
        "mean_stress_true",
        "max_stress_pred",
        "max_stress_true",
        "mean_deform_pred",
        "mean_deform_true",
    )

    @torch.no_grad()
    def update(self, stress_pred: Tensor, displacement_pred: Tensor, batch) -> None:
        """Add a batch: predictions (n,) [Pa], (n, 3) [m] vs ``batch.stress`` / ``batch.displacement``.

        ``batch`` is a :class:`~defgraspnets.models.graph.GraspGraph` (single or batched) with ``sample`` and
        ``object_id``; only object nodes count.
        """
        obj = batch.object_mask
        gidx = batch.node_graph()[obj]
        b = batch.graph_count

        def per_graph(v: Tensor, reduce: str = "sum") -> Tensor:
            v = v.double()
            if reduce == "sum":
                return torch.zeros(b, dtype=v.dtype, device=v.device).index_add_(0, gidx, v)
            return torch.full((b,), -torch.inf, dtype=v.dtype, device=v.device).scatter_reduce(
                0, gidx, v, "amax"
            )

        sp, st = stress_pred[obj], batch.stress[obj]
        dp, dt = displacement_pred[obj], batch.displacement[obj]
        np_, nt = dp.norm(dim=1), dt.norm(dim=1)
        nodes = per_graph(torch.ones_like(sp))
        values = {
            "sample": batch.sample.reshape(b, -1),
            "object_id": batch.object_id.reshape(b),
            "youngs_modulus": batch.youngs_modulus.double(),
            "force": batch.force.double(),
            "nodes": nodes,
            "stress_abs_err": per_graph((sp - st).abs()),
            "deform_abs_err": per_graph((np_ - nt).abs()),
            "disp_abs_err": per_graph((dp - dt).norm(dim=1)),
            "mean_stress_pred": per_graph(sp) / nodes,
            "mean_stress_true": per_graph(st) / nodes,
            "max_stress_pred": per_graph(sp, "max"),
            "max_stress_true": per_graph(st, "max"),
            "mean_deform_pred": per_graph(np_) / nodes,
            "mean_deform_true": per_graph(nt) / nodes,
        }
        self._append(values)

    @staticmethod
    def summarize(a: dict[str, np.ndarray], min_relative_spread: float = 0.0) -> dict[str, float]:
        """Metrics of a dict of per-sample arrays (see :meth:`arrays`); ``min_relative_spread`` as in the
        class."""
        n = a["nodes"].sum()
        if not len(a["nodes"]):
            return {"samples": 0}
        groups = np.stack(
            [a["object_id"], np.round(np.log10(a["youngs_modulus"]), 6), a["sample"][:, 3]], axis=1
        )

        def tau_and_interval(pred, true) -> tuple[float, int, tuple[float, float]]:
            # group taus once; their mean and its cluster-bootstrap interval over objects
            keep = _groups_spread_at_least(groups, true, min_relative_spread)
            if not keep.any():
                return float("nan"), 0, (float("nan"), float("nan"))
            first, taus = _group_taus(groups[keep], pred[keep], true[keep])
            mean = float(np.mean(taus)) if len(taus) else float("nan")
            return mean, len(taus), _cluster_bootstrap_interval(taus, a["object_id"][keep][first])

        tau_s, groups_s, tau_s_ci = tau_and_interval(a["mean_stress_pred"], a["mean_stress_true"])
        tau_d, groups_d, tau_d_ci = tau_and_interval(a["mean_deform_pred"], a["mean_deform_true"])
        mae_pa = float(a["stress_abs_err"].sum() / n)
        spread_s, rel_err_s = grouped_spread_and_relative_error(
            groups, a["mean_stress_pred"], a["mean_stress_true"]
        )
        spread_d, rel_err_d = grouped_spread_and_relative_error(
            groups, a["mean_deform_pred"], a["mean_deform_true"]
        )
        return {
            "samples": int(len(a["nodes"])),
            "nodes": int(n),  # object nodes over all samples: the weight of the MAEs
            "tau_groups": int(groups_s),
            "tau_d_groups": int(groups_d),
            "tau_s": tau_s,
            "tau_d": tau_d,
            # 95 % cluster-bootstrap interval over objects (NaN for a single object)
            "tau_s_ci_low": tau_s_ci[0],
            "tau_s_ci_high": tau_s_ci[1],
            "tau_d_ci_low": tau_d_ci[0],
            "tau_d_ci_high": tau_d_ci[1],
            "mae_stress_pa": mae_pa,
            "mae_stress_kpa": mae_pa / 1e3,
            "mae_deformation_mm": float(a["deform_abs_err"].sum() / n * 1e3),
            "mae_displacement_mm": float(a["disp_abs_err"].sum() / n * 1e3),
            "mean_stress_true_kpa": float(np.mean(a["mean_stress_true"]) / 1e3),
            "mean_deformation_true_mm": float(np.mean(a["mean_deform_true"]) * 1e3),
            # what tau ranks within a group (grasp-to-grasp standard deviation of the mean value) and the
            # prediction error that can reorder it (its standard deviation within the group), group means
            "spread_mean_stress_kpa": spread_s / 1e3,
            "relative_error_mean_stress_kpa": rel_err_s / 1e3,
            "spread_mean_deformation_mm": spread_d * 1e3,
            "relative_error_mean_deformation_mm": rel_err_d * 1e3,
        }

    def compute(self) -> dict[str, float]:
        """Metrics over everything accumulated (tau averaged over (object, E, step) groups)."""
        return self.summarize(self.arrays(), self.min_relative_spread)

    def compute_per_object(self) -> dict[int, dict[str, float]]:
        """Metrics of each object id."""
        a = self.arrays()
        return {
            int(o): self.summarize(
                {k: v[a["object_id"] == o] for k, v in a.items()}, self.min_relative_spread
            )
            for o in np.unique(a["object_id"])
        }
