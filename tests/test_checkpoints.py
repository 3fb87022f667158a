"""Checkpoint loading: a missing, unreadable or wrong-model file is an error naming the path and problem."""

from __future__ import annotations

from pathlib import Path

import pytest

from defgraspnets.models.checkpoints import CheckpointError, read_checkpoint
from defgraspnets.models.predictor import DefGraspNetsPredictor
from defgraspnets.models.wrench_module import WrenchRegressionModule

ROOT = Path(__file__).resolve().parents[1]
GRASP_CKPT = ROOT / "checkpoints" / "defgraspnets_box30.ckpt"
WRENCH_CKPT = ROOT / "checkpoints" / "wrench_poke.ckpt"


@pytest.fixture()
def broken(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_text("garbage\n")
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(GRASP_CKPT.read_bytes()[:4096])
    return garbage, truncated


def test_shipped_checkpoints_are_read_as_their_model():
    assert "state_dict" in read_checkpoint(GRASP_CKPT, "DefGraspNetsModule")
    assert "net_config" in read_checkpoint(WRENCH_CKPT, "WrenchRegressionModule")


def test_grasp_predictor_names_a_broken_or_wrong_checkpoint(broken, tmp_path):
    garbage, truncated = broken
    for path in (garbage, truncated):  # were an unpickling error suggesting weights_only=False, or int()
        with pytest.raises(CheckpointError, match=f"{path.name}: not a readable PyTorch checkpoint"):
            DefGraspNetsPredictor.from_checkpoint(path)
    # was a state_dict key mismatch of DefGraspNetsModule
    with pytest.raises(CheckpointError, match="wrench_poke.ckpt: not a DefGraspNetsModule checkpoint "
                       r"\(it holds a WrenchRegressionModule\)"):  # fmt: skip
        DefGraspNetsPredictor.from_checkpoint(WRENCH_CKPT)
    with pytest.raises(CheckpointError, match="not a file"):
        DefGraspNetsPredictor.from_checkpoint(tmp_path)
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        DefGraspNetsPredictor.from_checkpoint(tmp_path / "missing.ckpt")


def test_wrench_module_names_a_broken_or_wrong_checkpoint(broken):
    garbage, _ = broken
    with pytest.raises(CheckpointError, match="garbage.ckpt: not a readable PyTorch checkpoint"):
        WrenchRegressionModule.from_checkpoint(garbage)
    # was "stores no net_config (saved before it existed)"
    wrong = (
        r"defgraspnets_box30.ckpt: not a WrenchRegressionModule checkpoint \(it holds a DefGraspNetsModule\)"
    )
    with pytest.raises(CheckpointError, match=wrong):
        WrenchRegressionModule.from_checkpoint(GRASP_CKPT)


def test_train_checks_the_checkpoint_against_its_model_class(broken):
    """``python train.py ckpt_path=...`` (check_checkpoint_for): was Lightning's unpickling error at fit."""
    from defgraspnets.models.checkpoints import check_checkpoint_for

    garbage, truncated = broken
    grasp_target = "defgraspnets.models.defgraspnets_module.DefGraspNetsModule"
    check_checkpoint_for(GRASP_CKPT, grasp_target)
    check_checkpoint_for(WRENCH_CKPT, "defgraspnets.models.wrench_module.WrenchRegressionModule")
    with pytest.raises(CheckpointError, match="truncated.ckpt: not a readable PyTorch checkpoint"):
        check_checkpoint_for(truncated, grasp_target)
    with pytest.raises(CheckpointError, match="not a DefGraspNetsModule checkpoint"):
        check_checkpoint_for(WRENCH_CKPT, grasp_target)
    check_checkpoint_for(garbage, "some.other.Module")  # other classes: existence only
    with pytest.raises(FileNotFoundError):
        check_checkpoint_for(garbage.with_name("missing.ckpt"), "some.other.Module")
