"""The ablation table of DefGraspNets (thesis §7.8, Table 7.2): models that differ from the baseline by one
design condition, compared on one test set by Kendall tau of the grasp rankings by mean deformation and mean
stress.

The four design variables are model hyperparameters stored in every checkpoint (``DefGraspNetsModule``):

=============  =======================================  ===========================================
variable       baseline (the thesis's choice)           ablation
=============  =======================================  ===========================================
V1 outputs     ``joint``: one network, both fields      ``separate``: a deformation-only and a
                                                        stress-only network
V2 prediction  ``one_step``: the final state at once    ``multi_step``: the ramp in increments
V3 force       ``distributed``: F_g / |E^C| per         ``total``: F_g on every contact edge
   feature     contact edge
V4 force on    ``contact_edges``                        ``nodes``: the force on every node
=============  =======================================  ===========================================

:func:`ablation_rows` labels each evaluated checkpoint by the variables in which it differs from the baseline
and sets the thesis's Table 7.2 values of that condition beside it.
"""

from __future__ import annotations

from collections.abc import Sequence

from .report import LEVEL_COLUMNS

__all__ = [
    "ABLATION_COLUMNS",
    "BASELINE",
    "THESIS_TABLE_7_2",
    "VARIABLES",
    "ablation_rows",
    "model_conditions",
]

#: the thesis's conditions (bold in Table 7.2)
BASELINE = {
    "outputs": "joint",
    "prediction": "one_step",
    "force_feature": "distributed",
    "force_on": "contact_edges",
}
#: variable -> (Table 7.2 row label, {condition: description})
VARIABLES = {
    "outputs": ("V1 number of outputs", {"joint": "deformation and stress", "separate": "two networks"}),
    "prediction": ("V2 prediction type", {"one_step": "one-step", "multi_step": "multi-step"}),
    "force_feature": (
        "V3 force on a contact edge",
        {"distributed": "distributed F_g / |E^C|", "total": "non-distributed F_g"},
    ),
    "force_on": ("V4 assignment of F_g", {"contact_edges": "on contact edges", "nodes": "on all nodes"}),
}
#: Table 7.2 of the thesis (its data and test set): (variable, condition) or "baseline" -> (tau_d, tau_s).
#: V1's two networks: tau_d of the deformation-only one, tau_s of the stress-only one.
THESIS_TABLE_7_2 = {
    "baseline": (0.61, 0.82),
    ("outputs", "separate"): (0.57, 0.84),
    ("prediction", "multi_step"): (0.37, 0.70),
    ("force_feature", "total"): (0.33, 0.51),
    ("force_on", "nodes"): (0.58, 0.74),
}

_LEVEL_COLUMN = {column[0]: column for column in LEVEL_COLUMNS}
#: the level table's columns (:data:`~defgraspnets.eval.report.LEVEL_COLUMNS`) in Table 7.2's order
#: (deformation before stress), after the variant and before the thesis's values
ABLATION_COLUMNS = (
    ("variant", "Variant", "{}"),
    ("model", "Model", "{}"),
    ("condition", "Condition", "{}"),
    *(
        _LEVEL_COLUMN[key]
        for key in (
            "displacement_target",
            "samples",
            "tau_d",
            "tau_s",
            ("tau_d_ci_low", "tau_d_ci_high"),
            ("tau_s_ci_low", "tau_s_ci_high"),
            "mae_deformation_mm",
            "mae_stress_kpa",
        )
    ),
    ("thesis_tau_d", "thesis τ_d", "{:.2f}"),
    ("thesis_tau_s", "thesis τ_s", "{:.2f}"),
)


def model_conditions(hparams) -> dict:
    """The four design conditions of a DefGraspNets model from its hyperparameters (a mapping; a missing
    key is the module's default, the baseline's condition)."""
    conditions = {key: str(hparams.get(key, default)) for key, default in BASELINE.items()}
    for key, value in conditions.items():
        if value not in VARIABLES[key][1]:
            raise ValueError(f"model.{key}={value!r} is none of the conditions {sorted(VARIABLES[key][1])}")
    return conditions


def ablation_rows(levels: Sequence[dict]) -> list[dict]:
    """Table 7.2 rows of evaluated checkpoints: ``levels`` are ``scripts/evaluate.py``'s level rows, each with
    the model's ``conditions`` (:func:`model_conditions`). A row's variant is "baseline", the one variable
    ("V2 prediction type") in which it differs from the baseline, or "V1 + V3 ..." for several (then no
    thesis value applies). Rows are ordered baseline first, then V1 to V4; the models must have been
    evaluated on one test set (one ``split``), or the comparison says nothing: a ValueError names them."""
    splits = sorted({row["split"] for row in levels})
    if len(splits) > 1:
        raise ValueError(
            "an ablation table compares models on one test set; these checkpoints were evaluated on "
            f"different splits: {', '.join(splits)}"
        )
    order = list(BASELINE)
    rows, ranks = [], []
    for level in levels:
        conditions = level["conditions"]
        differ = [key for key in order if conditions[key] != BASELINE[key]]
        if not differ:
            variant, condition, thesis = "baseline", "the thesis's conditions", THESIS_TABLE_7_2["baseline"]
        else:
            variant = " + ".join(VARIABLES[key][0] for key in differ)
            condition = ", ".join(VARIABLES[key][1][conditions[key]] for key in differ)
            key = (differ[0], conditions[differ[0]])
            thesis = THESIS_TABLE_7_2.get(key, (None, None)) if len(differ) == 1 else (None, None)
        # baseline 0, V1-V4 by their variable, variants of several variables last
        first = min((order.index(variable) + 1 for variable in differ), default=0)
        ranks.append(first + (len(differ) > 1) * len(order))
        rows.append(
            {
                **{k: v for k, v in level.items() if k != "conditions"},
                "variant": variant,
                "condition": condition,
                "differs_in": differ,
                "thesis_tau_d": thesis[0],
                "thesis_tau_s": thesis[1],
            }
        )
    return [row for _, row in sorted(zip(ranks, rows), key=lambda pair: pair[0])]
