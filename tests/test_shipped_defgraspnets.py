"""The shipped DefGraspNets checkpoint (checkpoints/defgraspnets_box30.ckpt, trained on squeeze ramps of the
30 mm box, see checkpoints/defgraspnets_box30.yaml) against fresh FEM squeezes of grasps it never saw."""

from pathlib import Path

import numpy as np
import pytest
import torch

from defgraspnets import fem
from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp
from defgraspnets.models.predictor import DefGraspNetsPredictor
from defgraspnets.planning.planner import gripper_finger_geometry

CKPT = Path(__file__).resolve().parents[1] / "checkpoints" / "defgraspnets_box30.ckpt"
E = 2.385e6  # [Pa], one of the training moduli


@pytest.fixture(scope="module")
def fem_and_prediction():
    box = structured_box((0.03, 0.03, 0.03), (4, 4, 4))
    grasps = sample_antipodal_grasps(box, num_grasps=16, seed=7)  # the training set used seed 0
    solver = make_squeeze_solver(box, grasps, fem.Material(E, 0.3, 1000.0), 0.7)
    ramp = squeeze_ramp(solver, 15.0, 10)
    predictor = DefGraspNetsPredictor.from_checkpoint(CKPT)
    geometry = gripper_finger_geometry()
    predicted = {
        force: predictor.predict(
            box,
            force,
            E,
            fingers=geometry,
            gripper_pose=grasps.poses,
            closing_distance=grasps.closing_distances,
        )
        for force in (7.5, 15.0)
    }
    return box, ramp, predicted


def test_shipped_checkpoint_predicts_unseen_fem_grasps(fem_and_prediction):
    box, ramp, predicted = fem_and_prediction
    last = ramp[-1]
    ok = last.converged
    assert ok.sum() >= 5
    true_deformation = last.deformation()[ok].mean(axis=1)  # (G,) mean |u| [m]
    true_stress = last.von_mises[ok].mean(axis=1)  # (G,) mean von Mises stress [Pa]
    pred = predicted[15.0]
    pred_deformation = pred.mean_deformation.numpy()[ok]
    # per-grasp mean deformation and stress within 40 % of the FEM (worst of these 16 unseen grasps: 36 %)
    np.testing.assert_allclose(pred_deformation, true_deformation, rtol=0.4)
    pred_stress = pred.mean_stress.numpy()[ok]
    np.testing.assert_allclose(pred_stress, true_stress, rtol=0.4)
    # a larger grasp force deforms and stresses the object more, at every grasp
    assert torch.all(predicted[15.0].mean_deformation > predicted[7.5].mean_deformation)
    assert torch.all(predicted[15.0].mean_stress > predicted[7.5].mean_stress)
    assert torch.all(torch.isfinite(pred.stress)) and torch.all(pred.stress >= 0)
