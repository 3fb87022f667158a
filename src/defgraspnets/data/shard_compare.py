"""Agreement of two data sets of the same grasps: two solver settings, two devices, two code versions.

Both folders must hold the same shards (file names) of the same objects, moduli, grasps and force ramps; per
object it counts the ramps each solved and, where both did, compares the states at one ramp step: the mean
von Mises stress and the stress field, the deformation with each state's rigid motion removed (what the
models learn), and the angle between the two rigid motions (a grasp that settled at another equilibrium of
the frictional path: the object rolled or slid to another pose). It also gives the Kendall tau between the
two data sets' rankings of the grasps by mean stress (per modulus): what a change of solver does to the
labels a model is trained to rank.

    rows = compare_grasp_data("data/plain", "data/stabilized")
    print(comparison_markdown(rows))
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from defgraspnets.eval.metrics import kendall_tau
from defgraspnets.eval.report import markdown_table
from defgraspnets.grasp.metrics import best_rigid_transform, undo_rigid_motion

from .dataset import discover_shards
from .grasp_schema import GraspShard

__all__ = ["RAMP_METRICS", "compare_grasp_data", "compare_shards", "comparison_markdown", "pooled_summary"]

# per ramp solved in both data sets, at the compared step
RAMP_METRICS = ("mean_stress_rel", "stress_field_rel", "deformation_rel", "rotation_deg")


def _rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the relative rotation Ra^T Rb [deg] (scipy's rotation magnitude: accurate near 0)."""
    return float(np.degrees(Rotation.from_matrix(Ra.T @ Rb).magnitude()))


def _check_same_grasps(a: GraspShard, b: GraspShard, atol: float) -> None:
    """Raise ValueError naming what differs between the two shards' objects, moduli, grasps or ramps."""
    where = f"{a.path.name} ({a.path.parent} vs {b.path.parent})"
    oa, ob = a.object, b.object
    if oa.name != ob.name:
        raise ValueError(f"{where}: objects differ ({oa.name!r} vs {ob.name!r})")
    if oa.points.shape != ob.points.shape or not np.allclose(oa.points, ob.points, rtol=0, atol=atol):
        raise ValueError(f"{where}: the rest meshes of {oa.name} differ (vertices)")
    if not np.array_equal(oa.tets, ob.tets):
        raise ValueError(f"{where}: the rest meshes of {oa.name} differ (tets)")
    if not np.allclose(oa.youngs_modulus, ob.youngs_modulus, rtol=1e-12, atol=0):
        raise ValueError(f"{where}: Young's moduli differ ({oa.youngs_modulus} vs {ob.youngs_modulus} Pa)")
    if a.grasp_pose.shape != b.grasp_pose.shape or not np.allclose(
        a.grasp_pose, b.grasp_pose, rtol=0, atol=atol
    ):
        raise ValueError(f"{where}: grasp poses differ (another sampler seed or grasp count?)")
    # the reached total grasp force per step (the solver meets the prescribed ramp to its tolerance)
    both = (a.status == 0) & (b.status == 0) if a.status.shape == b.status.shape else None
    if (
        a.force.shape != b.force.shape
        or both is None
        or not np.allclose(a.force[both], b.force[both], rtol=1e-3, atol=1e-6)
    ):
        raise ValueError(f"{where}: force ramps differ (steps or max_force)")


def compare_shards(a: GraspShard, b: GraspShard, step: int = -1, atol: float = 1e-9) -> dict:
    """Agreement of two shards of the same grasps at ramp step ``step`` (default: the last).

    Per ramp solved in both (``ramps`` list, one dict each with ``k``, ``g``, ``youngs_modulus`` [Pa] and
    :data:`RAMP_METRICS`):

    - ``mean_stress_rel``: |mean vM_b - mean vM_a| / mean vM_a;
    - ``stress_field_rel``: max_i |vM_b,i - vM_a,i| / max_i vM_a,i;
    - ``deformation_rel``: mean_i |d_b,i - d_a,i| / mean_i |d_a,i|, d = the displacement with the state's
      best rigid motion removed, in the rest frame (:func:`~defgraspnets.grasp.metrics.best_rigid_transform`);
    - ``rotation_deg``: the angle between the two states' best rotations [deg].

    Also per object: counts (``ramps``, ``solved_a``, ``solved_b``, ``solved_both``) and
    ``stress_ranking_tau``, the mean over moduli of the Kendall tau between the two data sets' per-grasp
    mean stresses (moduli with at least 3 grasps solved in both; NaN if none).

    Raises:
        ValueError: the shards are not of the same object, moduli, grasps and force ramp (``atol`` [m] on
            vertices and poses), or ``step`` is outside the ramp.
    """
    _check_same_grasps(a, b, atol)
    if not -a.num_steps <= step < a.num_steps:
        raise ValueError(f"step={step} is outside the {a.num_steps}-step ramp")
    rest = a.object.points.astype(np.float64)
    both = (a.status == 0) & (b.status == 0)
    ramps = []
    taus = []
    for k in range(a.num_moduli):
        grasps = np.flatnonzero(both[k])
        mean_a, mean_b = [], []
        for g in grasps:
            vm_a, u_a = (np.asarray(x, dtype=np.float64) for x in a.fields(k, int(g), step))
            vm_b, u_b = (np.asarray(x, dtype=np.float64) for x in b.fields(k, int(g), step))
            Ra, ta = best_rigid_transform(rest, rest + u_a)
            Rb, tb = best_rigid_transform(rest, rest + u_b)
            d_a = undo_rigid_motion(rest + u_a, Ra, ta) - rest
            d_b = undo_rigid_motion(rest + u_b, Rb, tb) - rest
            mean_a.append(vm_a.mean())
            mean_b.append(vm_b.mean())
            ramps.append(
                {
                    "k": int(k),
                    "g": int(g),
                    "youngs_modulus": float(a.object.youngs_modulus[k]),
                    "mean_stress_rel": float(abs(vm_b.mean() - vm_a.mean()) / vm_a.mean()),
                    "stress_field_rel": float(np.abs(vm_b - vm_a).max() / vm_a.max()),
                    "deformation_rel": float(
                        np.linalg.norm(d_b - d_a, axis=1).mean() / np.linalg.norm(d_a, axis=1).mean()
                    ),
                    "rotation_deg": _rotation_angle_deg(Ra, Rb),
                }
            )
        if len(grasps) >= 3:
            taus.append(kendall_tau(mean_a, mean_b))
    taus = [t for t in taus if np.isfinite(t)]
    return {
        "object": a.object.name,
        "shard": a.path.name,
        "ramps_total": int(a.status.size),
        "solved_a": int((a.status == 0).sum()),
        "solved_b": int((b.status == 0).sum()),
        "solved_both": int(both.sum()),
        "stress_ranking_tau": float(np.mean(taus)) if taus else float("nan"),
        "ramps": ramps,
    }


def compare_grasp_data(
    dir_a: str | Path, dir_b: str | Path, step: int = -1, progress: bool = False
) -> list[dict]:
    """:func:`compare_shards` of every shard of ``dir_a`` with the shard of the same file name in ``dir_b``.

    Raises:
        FileNotFoundError: a folder is missing or holds no finished shard.
        ValueError: the folders do not hold the same shard files (names listed), or two shards differ in
            object, moduli, grasps or ramp.
    """
    paths_a = {p.name: p for p in discover_shards(dir_a)}
    paths_b = {p.name: p for p in discover_shards(dir_b)}
    only_a, only_b = sorted(set(paths_a) - set(paths_b)), sorted(set(paths_b) - set(paths_a))
    if only_a or only_b:
        raise ValueError(
            f"the folders hold different shards: only in {dir_a}: {only_a}; only in {dir_b}: {only_b}"
        )
    rows = []
    for name in tqdm(sorted(paths_a), desc="shards", disable=not progress):
        a, b = GraspShard(paths_a[name]), GraspShard(paths_b[name])
        try:
            rows.append(compare_shards(a, b, step))
        finally:
            a.close()
            b.close()
    return rows


def _quantiles(values: np.ndarray) -> dict:
    if not len(values):
        return {q: float("nan") for q in ("median", "p90", "p99", "max")}
    return {
        "median": float(np.median(values)),
        "p90": float(np.quantile(values, 0.9)),
        "p99": float(np.quantile(values, 0.99)),
        "max": float(values.max()),
    }


def pooled_summary(
    rows: list[dict], stress_tolerance: float = 0.01, rotation_tolerance_deg: float = 1.0
) -> dict:
    """Totals over all shards and quantiles (median, p90, p99, max) of each :data:`RAMP_METRICS` over the
    ramps solved in both; ``stress_outside`` / ``rotation_outside``: ramps whose mean stress differs by more
    than ``stress_tolerance`` (relative) / whose rigid motions differ by more than
    ``rotation_tolerance_deg``."""
    ramps = [r for row in rows for r in row["ramps"]]
    values = {m: np.array([r[m] for r in ramps], dtype=np.float64) for m in RAMP_METRICS}
    taus = np.array([row["stress_ranking_tau"] for row in rows], dtype=np.float64)
    return {
        "shards": len(rows),
        "ramps_total": sum(r["ramps_total"] for r in rows),
        "solved_a": sum(r["solved_a"] for r in rows),
        "solved_b": sum(r["solved_b"] for r in rows),
        "solved_both": len(ramps),
        "stress_tolerance": stress_tolerance,
        "stress_outside": int((values["mean_stress_rel"] > stress_tolerance).sum()),
        "rotation_tolerance_deg": rotation_tolerance_deg,
        "rotation_outside": int((values["rotation_deg"] > rotation_tolerance_deg).sum()),
        "stress_ranking_tau_mean": float(np.nanmean(taus)) if np.isfinite(taus).any() else float("nan"),
        **{m: _quantiles(v) for m, v in values.items()},
    }


_ROW_COLUMNS = (
    ("object", "Object", "{}"),
    ("ramps_total", "Ramps", "{}"),
    ("solved_a", "Solved A", "{}"),
    ("solved_b", "Solved B", "{}"),
    ("solved_both", "Both", "{}"),
    ("median_mean_stress_rel", "Mean stress diff., median", "{:.1e}"),
    ("max_mean_stress_rel", "max", "{:.1e}"),
    ("median_deformation_rel", "Deformation diff., median", "{:.1e}"),
    ("max_deformation_rel", "max", "{:.1e}"),
    ("max_rotation_deg", "Rigid rotation diff., max [deg]", "{:.2f}"),
    ("stress_ranking_tau", "τ of stress rankings A vs B", "{:.3f}"),
)


def comparison_markdown(
    rows: list[dict], a: str = "A", b: str = "B", summary: dict | None = None, **tolerances
) -> str:
    """Per-object table and a pooled line of :func:`compare_grasp_data` rows; ``summary``: their
    :func:`pooled_summary` if already computed (else computed here with ``tolerances``)."""
    flat = []
    for row in rows:
        vals = {m: np.array([r[m] for r in row["ramps"]], dtype=np.float64) for m in RAMP_METRICS}
        flat.append(
            {
                **{k: v for k, v in row.items() if k != "ramps"},
                **{f"median_{m}": float(np.median(v)) if len(v) else float("nan") for m, v in vals.items()},
                **{f"max_{m}": float(v.max()) if len(v) else float("nan") for m, v in vals.items()},
            }
        )
    s = summary if summary is not None else pooled_summary(rows, **tolerances)
    lines = [
        f"## Grasp data A = {a} vs B = {b}",
        "Relative differences at the compared ramp step, over ramps solved in both data sets.",
        markdown_table(flat, _ROW_COLUMNS),
        (
            f"**All**: {s['solved_a']} / {s['solved_b']} of {s['ramps_total']} ramps solved (A / B), "
            f"{s['solved_both']} in both. Mean stress differs by more than {s['stress_tolerance']:.0%} in "
            f"{s['stress_outside']} ramps (median {s['mean_stress_rel']['median']:.1e}, p99 "
            f"{s['mean_stress_rel']['p99']:.1e}, max {s['mean_stress_rel']['max']:.1e}); the rigid motions "
            f"differ by more than {s['rotation_tolerance_deg']:g} deg in {s['rotation_outside']} (max "
            f"{s['rotation_deg']['max']:.1f} deg); deformation differs by median "
            f"{s['deformation_rel']['median']:.1e}, p99 {s['deformation_rel']['p99']:.1e}; mean tau of the "
            f"stress rankings A vs B {s['stress_ranking_tau_mean']:.3f}."
        ),
    ]
    return "\n\n".join(lines) + "\n"
