"""The Armijo line search evaluates several step lengths per energy pass (SolverOptions.line_search_trials):
it must accept exactly the step that one-at-a-time backtracking accepts, so every answer is the same."""

import numpy as np
import pytest

from defgraspnets import fem


def _squeeze(line_search_trials: int, stabilization: float = 0.0):
    """Two Franka-like pads squeeze a box, one grasp centred and one off-centre, with friction
    (force-controlled travel, so the external work has a dof term) under gravity (nodal dead loads): the
    object turns while it is gripped."""
    from fem_helpers import pad_squeeze_solver

    solver = pad_squeeze_solver(
        [0.0, 0.002],
        linear_solver="dense",
        line_search_trials=line_search_trials,
        stabilization=stabilization,
    )
    gravity = fem.BodyLoad(gravity=(0.0, 0.0, -9.81))
    return solver.ramp(4, targets={"grip": np.array([1.0, 2.0])}, body_load=gravity)


@pytest.mark.parametrize("stabilization", [0.0, 1e-3])
def test_batched_trial_steps_reach_the_same_states_with_the_same_iterations(stabilization, monkeypatch):
    cuts = []  # accepted / first step length of every line search
    search = fem.QuasiStaticSolver._line_search

    def recorded(self, working, max_step):
        result, first_trial, alpha = search(self, working, max_step)
        cuts.extend(alpha[working] / first_trial[working])
        return result, first_trial, alpha

    monkeypatch.setattr(fem.QuasiStaticSolver, "_line_search", recorded)
    one_at_a_time = _squeeze(1, stabilization)
    # the ramp backtracks past one pass of 8 trials (else the passes after the first go untested)
    assert 0 < min(cuts) < 0.5**8
    for trials in (2, 8):
        batched = _squeeze(trials, stabilization)
        for a, b in zip(one_at_a_time, batched, strict=True):
            a.require_converged()
            np.testing.assert_array_equal(b.newton_iterations, a.newton_iterations)
            np.testing.assert_array_equal(b.displacement, a.displacement)
            np.testing.assert_array_equal(b.travel["grip"], a.travel["grip"])
    assert np.abs(one_at_a_time[-1].displacement).max() > 1e-4  # m: the pads moved the object


def test_sealed_membrane_poke_with_batched_trial_steps_equals_one_at_a_time():
    """The closed gas cavity's work enters every trial's energy (the cavity volume per trial state)."""
    from fem_helpers import sealed_pole_poke

    readings = {}
    for trials in (1, 3):
        _, readings[trials] = sealed_pole_poke(6, 0.006, linear_solver="direct", line_search_trials=trials)
        assert readings[trials].converged
    a, b = readings[1], readings[3]
    assert a.contact_force[2] > 0.1  # N: a real poke
    np.testing.assert_array_equal(b.contact_force, a.contact_force)
    assert b.gauge_pressure == a.gauge_pressure


@pytest.mark.parametrize(
    "field, bad",
    [("line_search_trials", b) for b in (0, -1, True, 2.5, "8")]
    + [("max_factor_reuse", b) for b in (-1, False, 1.0, "2")],
)
def test_optional_integer_options_reject_other_values(field, bad):
    with pytest.raises(ValueError, match=f"{field} must be None or an integer"):
        fem.SolverOptions(**{field: bad})
    fem.SolverOptions(**{field: None})


def test_line_search_trials_default_by_device():
    mesh = fem.TetMesh.box(size=(0.01, 0.01, 0.01), divisions=(1, 1, 1))
    solver = fem.QuasiStaticSolver(mesh, [], fem.Material(1e5, 0.3, 1000.0), device="cpu")
    assert solver._line_search_trials == 1
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        fem.Material(1e5, 0.3, 1000.0),
        device="cpu",
        options=fem.SolverOptions(line_search_trials=4),
    )
    assert solver._line_search_trials == 4
