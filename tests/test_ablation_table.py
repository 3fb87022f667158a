"""The ablation table (thesis §7.8, Table 7.2): variants labelled by the design condition in which they differ
from the baseline, with the thesis's values of that condition; models of different test sets refused."""

import pytest

from defgraspnets.eval.ablation import BASELINE, THESIS_TABLE_7_2, ablation_rows, model_conditions


def _level(tau_d, tau_s, split="unseen_grasps", **conditions):
    return {
        "split": split,
        "samples": 40,
        "tau_d": tau_d,
        "tau_s": tau_s,
        "conditions": {**BASELINE, **conditions},
    }


def test_variants_are_named_by_their_one_differing_condition_and_ordered_as_table_7_2():
    levels = [
        _level(0.5, 0.6, force_on="nodes"),
        _level(0.3, 0.4, prediction="multi_step"),
        _level(0.7, 0.8),
        _level(0.1, 0.2, outputs="separate", force_feature="total"),
        _level(0.6, 0.7, outputs="separate"),
    ]
    rows = ablation_rows(levels)
    assert [r["variant"] for r in rows] == [
        "baseline",
        "V1 number of outputs",
        "V2 prediction type",
        "V4 assignment of F_g",
        "V1 number of outputs + V3 force on a contact edge",
    ]
    base, v1, v2, v4, mixed = rows
    assert (base["tau_d"], base["tau_s"]) == (0.7, 0.8)  # the measured values stay with their model
    assert (base["thesis_tau_d"], base["thesis_tau_s"]) == THESIS_TABLE_7_2["baseline"] == (0.61, 0.82)
    assert (v2["thesis_tau_d"], v2["thesis_tau_s"]) == (0.37, 0.70) and v2["condition"] == "multi-step"
    assert (v1["thesis_tau_d"], v1["thesis_tau_s"]) == (0.57, 0.84) and v1["differs_in"] == ["outputs"]
    assert (v4["thesis_tau_d"], v4["thesis_tau_s"]) == (0.58, 0.74)
    # two conditions at once: no single thesis row applies
    assert mixed["thesis_tau_d"] is None and mixed["differs_in"] == ["outputs", "force_feature"]
    assert "conditions" not in base and levels[0]["conditions"]["force_on"] == "nodes"  # input untouched


def test_models_of_different_test_sets_and_unknown_conditions_are_refused():
    with pytest.raises(ValueError, match="different splits: unseen_E, unseen_grasps"):
        ablation_rows([_level(0.7, 0.8), _level(0.6, 0.7, split="unseen_E", outputs="separate")])
    with pytest.raises(ValueError, match=r"model.force_on='vertices' is none of the conditions"):
        model_conditions({"force_on": "vertices"})
    # hyperparameters of checkpoints saved before a variable existed: the baseline's condition
    assert model_conditions({"latent": 64}) == BASELINE
