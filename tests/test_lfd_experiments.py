"""Edge-following LfD in simulation: teacher demonstrations, 2-state HMM, GMRa rollout on a curved pipe."""

import json

import numpy as np
import pytest

from defgraspnets.tactile.contour import ContourParameters
from defgraspnets.tactile.contour_sim import build_fast_simulation
from defgraspnets.tactile.lfd.experiments import edge_following_experiment
from defgraspnets.tactile.loop_plots import edge_following_figure, save_figure

TEACHER = ContourParameters(tracking_step=0.01, force_gain=7.0e-4, alignment_gain=0.25, desired_force=3.0)


@pytest.fixture(scope="module")
def sim():
    return build_fast_simulation(cap_divisions=12, camera_scale=0.5)


def test_edge_following_policy_follows_an_unseen_curved_pipe_at_the_teachers_pace(sim, tmp_path):
    result = edge_following_experiment(sim, TEACHER, steps=20, rollout_steps=40)
    rep = result["report"]
    assert rep["n_demonstrations"] == 6 and rep["hmm_states"] == 2
    assert min(rep["demonstration_contact_fraction"]) == 1.0
    # the policy lowers itself onto the pipe (no contact at the start), then keeps contact
    ro = result["rollout"]
    assert not ro.in_contact[0]
    assert rep["rollout_first_contact_step"] is not None and rep["rollout_first_contact_step"] < 10
    assert rep["rollout_contact_fraction"] >= 0.9
    assert rep["rollout_housing_contact_steps"] == 0
    # the two HMM states separate pre-contact from contact readings (lambda = 0 vs > 0)
    w = ro.weights
    assert np.argmax(w[0]) != np.argmax(w[-1])
    # progress: the traversal state moves at >= 80 % of the teacher's K_v (a zig-zagging teacher gives
    # ~30 %), and the rollout advances along the curved pipe (arc length of the membrane pole) by >= 70 %
    # of K_v per contact step, i.e. it follows the bend rather than crawling or leaving it
    traversal = int(np.argmax(w[-1]))
    assert rep["hmm_state_mean_speed_m_per_step"][traversal] >= 0.8 * TEACHER.tracking_step
    contact_steps = rep["rollout_steps"] - 1 - rep["rollout_first_contact_step"]
    assert rep["rollout_distance_along_pipe_m"] >= 0.7 * TEACHER.tracking_step * contact_steps
    assert rep["rollout_pipe_progress_per_contact_step_m"] >= 0.7 * TEACHER.tracking_step
    # the script's outputs: the report is JSON-ready, the figure shows every rollout step and the weights
    assert json.loads(json.dumps(rep))["rollout_steps"] == rep["rollout_steps"]
    fig = edge_following_figure(result)
    rollout_panel, weights_panel = fig.axes[1], fig.axes[2]
    assert len(rollout_panel.collections[0].get_offsets()) == rep["rollout_steps"]
    np.testing.assert_array_equal(weights_panel.lines[0].get_ydata(), w[:, 0])
    assert len(fig.axes[0].lines) == rep["n_demonstrations"]
    assert save_figure(fig, tmp_path / "lfd_edge_following.png").stat().st_size > 10_000
