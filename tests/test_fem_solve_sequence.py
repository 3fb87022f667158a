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


def test_the_first_load_step_since_the_rest_state_has_its_own_newton_budget():
    """``max_newton_first_step``: a problem's first load step since its rest state gets its own Newton budget,
    later steps keep ``max_newton_per_solve``; problems that need no more than the smaller budget are the
    same bit for bit; ``reset`` and a copied rest state start the count again, a copied gripped problem does
    not. (Squeeze ramps, streamed and lockstep: ``test_grasp_squeeze.py``.)"""
    from fem_helpers import pad_squeeze_solver

    gravity = fem.BodyLoad(gravity=(0.0, 0.0, -9.81))

    def build(offsets, **options):
        return pad_squeeze_solver(
            offsets, linear_solver="dense", max_newton_iterations=20, max_newton_per_solve=20, **options
        )

    offsets, forces = OFFSETS[1:], 0.1 * FORCES[1:]  # gripped at 0.2-0.3 N under gravity, first step
    a = build(offsets).solve(targets={"grip": forces}, body_load=gravity)
    first = build(offsets, max_newton_first_step=80)
    b = first.solve(targets={"grip": forces}, body_load=gravity)
    # the grasp at 4 mm needs several increments, 61 Newton iterations: beyond 20, within 80
    assert a.status.tolist() == [0, fem.SolveStatus.NOT_CONVERGED, 0, 0] and a.newton_iterations[1] >= 20
    b.require_converged()
    assert 20 < b.newton_iterations[1] <= 80
    for g in (0, 2, 3):  # (gripped within 20 either way)
        assert a.newton_iterations[g] == b.newton_iterations[g]
        np.testing.assert_array_equal(a.displacement[g], b.displacement[g])
        np.testing.assert_array_equal(a.travel["grip"][g], b.travel["grip"][g])
    # back to the rest state: a first step again, the same equilibrium
    first.reset()
    again = first.solve(targets={"grip": forces}, body_load=gravity)
    np.testing.assert_array_equal(again.displacement, b.displacement)
    np.testing.assert_array_equal(again.newton_iterations, b.newton_iterations)
    # a later step keeps the budget of 20: the centred grasp, gripped at 0.1 N without gravity first, needs
    # several increments (127 Newton iterations without a budget) once gravity is on
    centred = {"grip": 0.1 * FORCES[:1]}
    later = build(OFFSETS[:1], max_newton_first_step=80)
    later.solve(targets=centred).require_converged()
    eq = later.solve(targets=centred, body_load=gravity)
    assert eq.status[0] == fem.SolveStatus.NOT_CONVERGED and eq.newton_iterations[0] <= 40
    # copied states carry their count: problem 0 from a rest state (a first step: 80), problem 1 from the
    # gripped centred problem (a later step: 20)
    rest = build(OFFSETS[2:3], max_newton_first_step=80)
    gripped = build(OFFSETS[:1], max_newton_first_step=80)
    gripped.solve(targets=centred).require_converged()
    copy = build(OFFSETS[:2], max_newton_first_step=80)
    copy.copy_state_from(rest, rows=[0], into=[0])
    copy.copy_state_from(gripped, rows=[0], into=[1])
    eq = copy.solve(targets={"grip": [forces[1], centred["grip"][0]]}, body_load=gravity)
    assert eq.status.tolist() == [fem.SolveStatus.CONVERGED, fem.SolveStatus.NOT_CONVERGED]
    assert eq.newton_iterations[0] == b.newton_iterations[1]


def test_the_first_step_budget_is_checked():
    for bad in (-1, 1.5, True, "400"):
        with pytest.raises(ValueError, match="max_newton_first_step"):
            fem.SolverOptions(max_newton_first_step=bad)
    assert fem.SolverOptions().max_newton_first_step is None  # the engine: max_newton_per_solve
    assert fem.SolverOptions(max_newton_first_step=0).max_newton_first_step == 0  # no budget
