"""What a directory of grasp shards holds: ramps solved and failed by cause, field magnitudes, and how
consistently the ground truth ranks the grasps (a reference for the Kendall tau a model can reach).

    rows = [shard_summary(GraspShard(p)) for p in discover_shards("data/grasps")]
"""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
from tqdm.auto import tqdm

from defgraspnets.eval.metrics import ranking_agreement_across_moduli
from defgraspnets.eval.report import markdown_table
from defgraspnets.fem.results import SolveStatus
from defgraspnets.grasp.datagen import STATUS_INVERTED, STATUS_SELF_INTERSECTING
from defgraspnets.grasp.metrics import rigid_removed_deformation

from .grasp_schema import GraspShard, settings_difference

__all__ = ["report_markdown", "settings_note", "shard_summary", "status_name"]

# codes of /ramp/status besides the solver's
_EXTRA_STATUS = {STATUS_INVERTED: "INVERTED", STATUS_SELF_INTERSECTING: "SELF_INTERSECTING"}


def status_name(code: int) -> str:
    """Name of a /ramp/status code (``SolveStatus`` or the generator's own)."""
    try:
        return SolveStatus(int(code)).name
    except ValueError:
        return _EXTRA_STATUS.get(int(code), f"code {int(code)}")


def shard_summary(shard: GraspShard, progress: bool = False) -> dict:
    """Counts, field magnitudes and ground-truth ranking agreement of one shard.

    Returns a dict with ``object``, ``category``, ``vertices``, ``moduli`` [Pa], ``grasps``, ``steps``,
    ``ramps``, ``converged``, ``status`` ({name: count}), the medians over converged ramps of the mean von
    Mises stress [kPa] and mean rigid-removed deformation [mm] at the last step, and
    ``stress_ranking_agreement`` / ``deformation_ranking_agreement``
    (:func:`~defgraspnets.eval.metrics.ranking_agreement_across_moduli` of those per-grasp means).
    """
    k_count, g_count, s_count = shard.num_moduli, shard.num_grasps, shard.num_steps
    solved = shard.status == 0
    mean_stress = np.full((k_count, g_count, s_count), np.nan)
    mean_deform = np.full((k_count, g_count, s_count), np.nan)
    rest = shard.object.points
    entries = [(k, g) for k in range(k_count) for g in range(g_count) if solved[k, g]]
    for k, g in tqdm(entries, desc=shard.object.name, leave=False, disable=not progress):
        stress, disp = shard.fields(k, g, slice(None))  # the whole ramp in one read: (S, N), (S, N, 3)
        mean_stress[k, g] = stress.mean(axis=1)
        mean_deform[k, g] = rigid_removed_deformation(rest, rest + disp).mean(axis=1)
    codes, counts = np.unique(shard.status, return_counts=True)
    tau_s, pairs = ranking_agreement_across_moduli(mean_stress, solved)
    tau_d, _ = ranking_agreement_across_moduli(mean_deform, solved)
    nan = float("nan")
    return {
        "object": shard.object.name,
        "category": shard.object.category,
        "vertices": int(len(rest)),
        "moduli": [float(e) for e in shard.object.youngs_modulus],
        "grasps": int(g_count),
        "steps": int(s_count),
        "ramps": int(k_count * g_count),
        "converged": int(solved.sum()),
        "status": {status_name(c): int(n) for c, n in zip(codes, counts)},
        "mean_stress_kpa": float(np.median(mean_stress[solved, -1]) / 1e3) if solved.any() else nan,
        "mean_deformation_mm": float(np.median(mean_deform[solved, -1]) * 1e3) if solved.any() else nan,
        "stress_ranking_agreement": tau_s,
        "deformation_ranking_agreement": tau_d,
        "ranking_pairs": int(pairs),
        "solver_settings": shard.solver_settings,
    }


_COLUMNS = (
    ("object", "Object", "{}"),
    ("vertices", "Vertices", "{:d}"),
    ("converged", "Converged", "{:d}"),
    ("ramps", "Ramps", "{:d}"),
    ("failures", "Failed ramps by cause", "{}"),
    ("mean_stress_kpa", "Mean stress, last step [kPa]", "{:.3g}"),
    ("mean_deformation_mm", "Mean deformation, last step [mm]", "{:.3g}"),
    ("stress_ranking_agreement", "τ_s across moduli", "{:.2f}"),
    ("deformation_ranking_agreement", "τ_d across moduli", "{:.2f}"),
)


def settings_note(rows: list[dict]) -> str:
    """One line on the solver settings the shards were made with (``GraspShard.solver_settings``): one
    setting, none recorded (shards before session 44), or which shards differ from the most common one and
    how. A data set whose shards were simulated with different settings (a default changed between runs)
    holds two kinds of equilibria; the line makes that visible."""
    groups: dict[str, list[str]] = {}
    for r in rows:
        groups.setdefault(json.dumps(r.get("solver_settings", {}), sort_keys=True), []).append(r["object"])
    if not groups:
        return ""
    if len(groups) == 1:
        ((text, names),) = groups.items()
        if text == "{}":
            return f"Solver settings: not recorded in the {len(names)} shard(s) (made before session 44)."
        return f"Solver settings: the same in all {len(names)} shard(s)."
    common = max(groups, key=lambda t: len(groups[t]))
    parts = []
    for text, names in groups.items():
        if text == common:
            continue
        if text == "{}":
            what = "none recorded"
        elif common == "{}":
            what = "recorded; the others: none"
        else:
            what = settings_difference(json.loads(common), json.loads(text))
        parts.append(f"{', '.join(sorted(set(names)))} ({what})")  # (an object's shards once)
    return (
        f"**Solver settings differ between shards**: {len(groups[common])} share the most common setting; "
        + "; ".join(parts)
        + "."
    )


def report_markdown(rows: list[dict]) -> str:
    """Markdown table of :func:`shard_summary` rows with a total line (agreements: mean over shards) and a
    line on their solver settings (:func:`settings_note`)."""

    def failures(status: dict) -> str:
        failed = {name: n for name, n in status.items() if name != SolveStatus.CONVERGED.name}
        return ", ".join(f"{name} {n}" for name, n in sorted(failed.items())) or "none"

    table = [{**r, "failures": failures(r["status"])} for r in rows]
    if rows:
        total: dict = {"object": "**all**", "vertices": None}
        for key in ("converged", "ramps"):
            total[key] = sum(r[key] for r in rows)
        for key in ("stress_ranking_agreement", "deformation_ranking_agreement"):
            values = [r[key] for r in rows if np.isfinite(r[key])]
            total[key] = float(np.mean(values)) if values else float("nan")
        total["failures"] = failures(sum((Counter(r["status"]) for r in rows), Counter()))
        table.append(total)
    return (
        "## Grasp data\n\nτ across moduli: mean Kendall tau between the rankings of the same grasps (by "
        "mean von Mises stress, by mean rigid-removed deformation) at two Young's moduli and the same ramp "
        "step.\n\n" + markdown_table(table, _COLUMNS) + "\n\n" + settings_note(rows) + "\n"
    )
