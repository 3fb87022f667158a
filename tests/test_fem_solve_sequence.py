"""QuasiStaticSolver.solve_sequence: each problem runs through the levels on its own (no barrier between
levels), and reaches the same equilibria as one solve() call per level."""

import numpy as np
import pytest

from defgraspnets import fem

OFFSETS = np.array([0.0, 0.002, 0.004, 0.001, 0.003])  # m: where the pads grip along x
FORCES = np.array([1.0, 2.0, 3.0, 1.5, 2.5])  # N: grip force at the last level


def _solver(linear_solver: str, **options) -> fem.QuasiStaticSolver:
    """Two Franka-like pads squeeze a box off-centre with friction under gravity, five grasps at once:
    the off-centre grasps turn the object and take more Newton iterations per level than the centred one."""
    from fem_helpers import pad_squeeze_solver

    solver = pad_squeeze_solver(OFFSETS, linear_solver=linear_solver, **options)
    # gripped first (under gravity the object would fall from the open pads)
    solver.solve(targets={"grip": 0.2 * FORCES}, body_load=fem.BodyLoad(gravity=(0.0, 0.0, -9.81)))
    return solver


def _levels(steps: int) -> list[dict]:
    return [{"grip": FORCES * (0.2 + 0.8 * (k + 1) / steps)} for k in range(steps)]


def _assert_same(a: fem.Equilibrium, b: fem.Equilibrium) -> None:
    from fem_helpers import assert_same_squeeze

    assert_same_squeeze(a, b)


@pytest.mark.parametrize(
    "linear_solver, options",
    [("direct", {}), ("dense", {}), ("dense", {"stabilization": 1e-3, "stabilization_release": True})],
)
def test_levels_without_barrier_reach_the_same_equilibria_as_one_solve_per_level(linear_solver, options):
    """Chord Newton (the CPU default) and the stabilized increments released to exact equilibria too."""
    steps = 4
    sequential = _solver(linear_solver, **options)
    expected = [sequential.solve(targets=level) for level in _levels(steps)]
    # the grasps need different Newton iterations per level, so without a barrier they drift apart
    iterations = np.array([eq.newton_iterations for eq in expected])
    assert (iterations.max(axis=1) > iterations.min(axis=1)).any()
    assert np.all(expected[-1].converged)

    solver = _solver(linear_solver, **options)
    seen = []
    got = solver.solve_sequence(_levels(steps), on_level=lambda k, eq: seen.append((k, eq)))
    assert [k for k, _ in seen] == list(range(steps))
    assert all(eq is got[k] for k, eq in seen)
    for a, b in zip(expected, got, strict=True):
        _assert_same(a, b)
    # the solver goes on from the same state and targets: one more level alike
    more = {"grip": 1.2 * FORCES}
    _assert_same(sequential.solve(targets=more), solver.solve(targets=more))


def test_flagged_problems_are_reported_at_every_later_level_as_solve_reports_them():
    """A problem flagged before the call and one that runs out of its Newton budget at a level: the later
    levels report them at their last converged state, with no load fraction or iterations."""

    def build():
        solver = _solver("dense", max_newton_iterations=20, max_newton_per_solve=22)
        solver.status[4] = fem.SolveStatus.ESCAPED
        return solver

    steps = 3
    sequential = build()
    expected = [sequential.solve(targets=level) for level in _levels(steps)]
    got = build().solve_sequence(_levels(steps))
    # grasp 3 spends its budget half-way through the first level; the others converge
    np.testing.assert_array_equal(expected[-1].converged, [True, True, True, False, False])
    assert expected[0].load_fraction[3] == 0.5 and expected[0].newton_iterations[3] > 0
    for a, b in zip(expected, got, strict=True):
        _assert_same(a, b)


def test_level_targets_are_checked():
    solver = _solver("dense")
    with pytest.raises(KeyError, match="unknown dof 'grasp'"):
        solver.solve_sequence([{"grasp": 1.0}])
    with pytest.raises(ValueError, match="target 'grip' of level 1 must be finite"):
        solver.solve_sequence([{"grip": 1.0}, {"grip": np.nan}])
    with pytest.raises(ValueError, match="at least one level"):
        solver.solve_sequence([])
    with pytest.raises(TypeError, match="level 0 must be a dict"):
        solver.solve_sequence([1.0])


def test_rows_are_put_only_from_equilibria_of_as_many_problems_with_the_same_fields():
    solver = _solver("dense")
    eq = solver.solve(targets={"grip": FORCES})
    copy = eq.take(np.arange(eq.batch_size))
    copy.put([3, 0], eq.take([0, 3]))
    np.testing.assert_array_equal(copy.displacement[[0, 3]], eq.displacement[[3, 0]])
    np.testing.assert_array_equal(copy.contact_normal_force["left"][3], eq.contact_normal_force["left"][0])
    with pytest.raises(ValueError, match="2 problems cannot fill rows"):
        copy.put([1], eq.take([0, 3]))
    copy.tet_stress = np.zeros((eq.batch_size, eq.mesh.num_tets, 3, 3))
    with pytest.raises(ValueError, match="'tet_stress' is recorded in only one"):
        copy.put([0], eq.take([0]))


def test_a_check_flags_problems_where_they_reach_a_level_as_setting_the_status_between_solves_does():
    """``check`` sees each problem as it reaches a level and may stop it there (the tactile sensor flags an
    indenter that lost contact): the same as flagging it between two solve() calls."""
    limit = 1.6  # N: grasps pressing harder than this at a level are stopped there

    def too_hard(force):
        return np.where(force > limit, fem.SolveStatus.ESCAPED, fem.SolveStatus.CONVERGED)

    steps = 3
    sequential = _solver("dense")
    expected = []
    for level in _levels(steps):
        eq = sequential.solve(targets=level)
        codes = np.where(eq.converged, too_hard(eq.dof_force["grip"]), eq.status)
        eq.status[:] = codes
        sequential.status[:] = codes
        expected.append(eq)
    seen = []

    def check(levels, part, rows):
        seen.append(levels.copy())
        assert np.all(part.converged) and len(rows) == len(levels) == part.batch_size
        return too_hard(part.dof_force["grip"])

    got = _solver("dense").solve_sequence(_levels(steps), check=check)
    assert sorted(set(np.concatenate(seen).tolist())) == list(range(steps))  # every level was checked
    flagged = expected[-1].status == fem.SolveStatus.ESCAPED
    assert flagged.any() and not flagged.all()  # some grasps stopped on the way, the gentle ones went on
    for a, b in zip(expected, got, strict=True):
        _assert_same(a, b)
    with pytest.raises(ValueError, match="check must return"):
        _solver("dense").solve_sequence(_levels(1), check=lambda levels, part, rows: np.zeros(1))
