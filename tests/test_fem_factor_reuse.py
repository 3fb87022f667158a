"""Chord Newton (SolverOptions.max_factor_reuse): factorizations reused across Newton steps and load
increments give the plain Newton answer to the Newton tolerance with fewer factorizations, and keep a
problem independent of its batch."""

import numpy as np
import pytest
from test_fem_solver import L, _grasp_problem, _ramp

from defgraspnets import fem


@pytest.mark.parametrize("linear_solver", ["direct", "dense"])
def test_factor_reuse_matches_plain_newton_with_fewer_factorizations(linear_solver):
    forces = np.array([0.5, 1.0, 2.0])
    runs = {}
    for reuse in (0, 4):
        _, solver = _grasp_problem(3, linear_solver=linear_solver, model="neohookean", max_factor_reuse=reuse)
        eqs = solver.ramp(4, targets={"grip": forces})
        eqs[-1].require_converged()
        runs[reuse] = eqs[-1], solver.system.factorizations.copy(), sum(e.newton_iterations for e in eqs)
    (plain, plain_factors, plain_newton), (chord, chord_factors, _) = runs[0], runs[4]
    # plain Newton factors once per Newton step
    np.testing.assert_array_equal(plain_factors, plain_newton)
    # in all, chord Newton factors far less; one problem may take a few more Newton steps, and factor in
    # each, since its path turns on round-off (dense on an AVX-512 CPU: 5 / 10 / 13 against 10 / 19 / 11)
    assert chord_factors.sum() < 0.8 * plain_factors.sum()
    assert np.all(chord_factors <= 1.5 * plain_factors)
    for b in range(3):
        # the same equilibrium to the Newton tolerance (rtol 1e-7 of the largest force)
        u = np.abs(plain.displacement[b]).max()
        np.testing.assert_allclose(chord.displacement[b], plain.displacement[b], atol=1e-5 * u)
        assert chord.dof_force["grip"][b] == pytest.approx(forces[b], rel=1e-6)


def test_a_barely_changing_hessian_is_factored_once():
    """A clamped cube under gravity ramped in small steps: the Hessian hardly changes, so the first
    factorization serves the whole ramp (max_factor_reuse steps) while every step converges."""
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 2), origin=(-L / 2, -L / 2, -L / 2))
    clamped = np.nonzero(mesh.points[:, 2] < -L / 2 + 1e-12)[0]
    results = {}
    for reuse in (0, 8):
        options = fem.SolverOptions(linear_solver="direct", max_factor_reuse=reuse)
        solver = fem.QuasiStaticSolver(
            mesh, [], fem.Material(1e5, 0.3, 1000.0), fixed=clamped, device="cpu", options=options
        )
        gravity = fem.BodyLoad(gravity=(0.0, 0.0, -9.81))
        eqs = solver.ramp(4, body_load=gravity)
        for eq in eqs:
            eq.require_converged()
        results[reuse] = (
            eqs[-1],
            int(solver.system.factorizations.sum()),
            sum(e.newton_iterations for e in eqs),
        )
    (plain, plain_factors, plain_newton), (chord, chord_factors, _) = results[0], results[8]
    assert plain_factors == plain_newton.sum() > 1
    assert chord_factors == 1
    u = np.abs(plain.displacement).max()
    np.testing.assert_allclose(chord.displacement, plain.displacement, atol=1e-5 * u)


@pytest.mark.parametrize("linear_solver", ["direct", "dense"])
def test_factor_reuse_keeps_a_problem_independent_of_its_batch(linear_solver):
    """Each problem decides from its own residuals when to refactor: alone or in a batch, bit for bit."""
    forces = np.array([0.5, 1.0, 2.0])
    options = {"linear_solver": linear_solver, "model": "neohookean", "max_factor_reuse": 4}
    _, batched = _grasp_problem(3, **options)
    eqs = batched.ramp(3, targets={"grip": forces})
    eq = eqs[-1]
    eq.require_converged()
    newton = sum(e.newton_iterations for e in eqs)
    assert batched.system.factorizations.sum() < newton.sum()  # reuse did happen
    for b in (0, 2):
        _, single = _grasp_problem(3, select=[b], **options)
        eq1 = _ramp(single, forces[b : b + 1])
        np.testing.assert_array_equal(eq.displacement[b], eq1.displacement[0])
        np.testing.assert_array_equal(eq.travel["grip"][b], eq1.travel["grip"][0])
        assert single.system.factorizations[0] == batched.system.factorizations[b]


def test_krylov_solvers_keep_no_factorizations():
    _, solver = _grasp_problem(1, linear_solver="amg", max_factor_reuse=4)
    assert not solver.system.keep_factors
    _, solver = _grasp_problem(1, linear_solver="direct", max_factor_reuse=0)
    assert not solver.system.keep_factors


def test_reuse_by_default_on_the_cpu_only():
    """None: chord Newton on the CPU (factorizations dominate), plain Newton on CUDA (measured not to pay)."""
    from defgraspnets.fem.solver import MAX_FACTOR_REUSE_DEFAULT

    assert fem.SolverOptions().max_factor_reuse is None
    assert MAX_FACTOR_REUSE_DEFAULT == {False: 4, True: 0}
    _, solver = _grasp_problem(1, linear_solver="direct")
    assert solver._max_factor_reuse == 4 and solver.system.keep_factors


@pytest.mark.gpu
def test_no_reuse_by_default_on_cuda():
    _, solver = _grasp_problem(1, linear_solver="dense", device="cuda")
    assert solver._max_factor_reuse == 0 and not solver.system.keep_factors
    _, solver = _grasp_problem(1, linear_solver="dense", device="cuda", max_factor_reuse=4)
    assert solver.system.keep_factors


@pytest.mark.parametrize(
    "bad",
    [
        {"max_factor_reuse": -1},
        {"max_factor_reuse": 1.5},
        {"max_factor_reuse": True},
        {"factor_reuse_contraction": 0.0},
        {"factor_reuse_contraction": 1.0},
    ],
)
def test_invalid_factor_reuse_options(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        fem.SolverOptions(**bad)
