"""Solver behaviour: batching, linear solvers, devices, reference FEM, bad input."""

from pathlib import Path

import numpy as np
import pytest
from fem_helpers import box_pad, symmetric_pattern_matrices
from scipy.spatial.transform import Rotation

from defgraspnets import fem

L = 0.02


def _grasp_problem(batch, device="cpu", linear_solver="auto", model="corotated", select=None, **options):
    """A box squeezed by two finger pads (shared force dof) with friction, rotated per problem; ``select``
    keeps only those problems of the batch (same materials and poses); ``options``: more SolverOptions."""
    mesh = fem.TetMesh.box(
        size=(L, 0.75 * L, 1.25 * L), divisions=(4, 4, 4), origin=(-L / 2, -0.375 * L, -0.625 * L)
    )
    v, f = box_pad((0.012, 0.008, 0.012))
    left = fem.RigidBody(
        "left", fem.TriangleMesh(v, f), control=fem.Control.force((0, -1, 0), dof="grip"), friction=0.7
    )
    right = fem.RigidBody(
        "right", fem.TriangleMesh(v, f), control=fem.Control.force((0, 1, 0), dof="grip"), friction=0.7
    )
    mats = [fem.Material(E, 0.3, 1000.0, model=model) for E in np.geomspace(2e4, 2e6, batch)]
    select = list(range(batch)) if select is None else list(select)
    solver = fem.QuasiStaticSolver(
        mesh,
        [left, right],
        [mats[b] for b in select],
        batch_size=len(select),
        device=device,
        options=fem.SolverOptions(linear_solver=linear_solver, **options),
    )
    poses_l, poses_r = [], []
    for b in range(batch):
        angle = 0.3 * b
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # grasp rotated about the closing axis
        offset = np.array([0.001 * b, 0, -0.001 * b])
        for sign, out in ((1, poses_l), (-1, poses_r)):
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = offset + [0, sign * (0.375 * L + 0.004), 0]
            out.append(T)
    solver.set_body_pose("left", np.array(poses_l)[select])
    solver.set_body_pose("right", np.array(poses_r)[select])
    return mesh, solver


def _ramp(solver, forces, steps=3):
    return solver.ramp(steps, targets={"grip": forces})[-1]


def test_batched_solves_equal_single_solves():
    forces = np.array([0.5, 1.0, 2.0])
    mesh, batched = _grasp_problem(3)
    eq = _ramp(batched, forces)
    eq.require_converged()
    for b in range(3):
        _, single = _grasp_problem(3)
        # same problem alone: restrict the batch to one entry by giving the others zero load
        eq1 = _ramp(single, np.where(np.arange(3) == b, forces, 0.0))
        # equal to within the Newton tolerance (relative residual 1e-7)
        np.testing.assert_allclose(
            eq.displacement[b], eq1.displacement[b], atol=1e-5 * np.abs(eq1.displacement[b]).max()
        )
        np.testing.assert_allclose(
            eq.von_mises[b], eq1.von_mises[b], rtol=1e-5, atol=1e-5 * eq.von_mises[b].max()
        )
    # the two fingers share the grasp force; the object is in equilibrium
    for b in range(3):
        np.testing.assert_allclose(
            eq.body_force["left"][b] + eq.body_force["right"][b], 0, atol=1e-7 * forces[b]
        )
        assert eq.dof_force["grip"][b] == pytest.approx(forces[b], rel=1e-6)
    # stiffer material deforms less under a larger force here
    assert eq.deformation()[0].max() > eq.deformation()[2].max()


@pytest.mark.parametrize("model", fem.MATERIAL_MODELS)
@pytest.mark.parametrize("linear_solver", ["direct", "dense", "dense-batched", "banded"])
def test_exact_linear_solvers_make_a_problem_independent_of_its_batch(linear_solver, model, monkeypatch):
    """With a factorization per problem, a problem solved in a batch gives bit for bit what it gives alone:
    nothing of one problem (sparse fill-reducing ordering, pivots, tolerances) depends on another, so a
    resumed or re-sharded dataset equals an uninterrupted one. (A single SuperLU factorization of the whole
    block-diagonal matrix broke this: its minimum-degree ordering is a global choice.)"""
    if linear_solver == "dense-batched":  # one batched Cholesky for any number of problems
        monkeypatch.setattr(fem.system, "DENSE_LOOP_MAX_PROBLEMS", 0)
        linear_solver = "dense"
    forces = np.array([0.5, 1.0, 2.0])
    _, batched = _grasp_problem(3, linear_solver=linear_solver, model=model)
    eq = _ramp(batched, forces)
    eq.require_converged()
    for b in (0, 2):
        _, single = _grasp_problem(3, linear_solver=linear_solver, model=model, select=[b])
        eq1 = _ramp(single, forces[b : b + 1])
        np.testing.assert_array_equal(eq.displacement[b], eq1.displacement[0])
        np.testing.assert_array_equal(eq.von_mises[b], eq1.von_mises[0])
        np.testing.assert_array_equal(eq.travel["grip"][b], eq1.travel["grip"][0])


def test_linear_solvers_agree():
    forces = np.array([1.0, 1.5])
    results = {}
    for linear in ("amg", "direct", "cg", "dense"):
        _, solver = _grasp_problem(2, linear_solver=linear)
        eq = _ramp(solver, forces, steps=2)
        eq.require_converged()
        results[linear] = eq
    for other in ("direct", "cg", "dense"):
        np.testing.assert_allclose(
            results[other].displacement,
            results["amg"].displacement,
            atol=1e-5 * np.abs(results["amg"].displacement).max(),
        )


def test_squeeze_is_mirror_symmetric_and_grows_with_force():
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(4, 4, 4), origin=(-L / 2, -L / 2, -L / 2))
    v, f = box_pad((0.012, 0.008, 0.012))
    left = fem.RigidBody(
        "left", fem.TriangleMesh(v, f), control=fem.Control.force((0, -1, 0), dof="grip"), friction=0.7
    )
    right = fem.RigidBody(
        "right", fem.TriangleMesh(v, f), control=fem.Control.force((0, 1, 0), dof="grip"), friction=0.7
    )
    solver = fem.QuasiStaticSolver(mesh, [left, right], fem.Material(5e4, 0.3, 1000.0), device="cpu")
    for name, y in (("left", L / 2 + 0.004), ("right", -L / 2 - 0.004)):
        T = np.eye(4)
        T[1, 3] = y
        solver.set_body_pose(name, T)
    steps = solver.ramp(4, targets={"grip": 4.0})
    for eq in steps:
        eq.require_converged()
    peak = [eq.von_mises[0].max() for eq in steps]
    squeeze = [eq.travel["grip"][0] for eq in steps]
    assert np.all(np.diff(peak) > 0) and np.all(np.diff(squeeze) > 0)
    # mirror y -> -y maps the field onto itself
    eq = steps[-1]
    p = mesh.points
    mirror = np.array([np.argmin(np.linalg.norm(p - q * [1, -1, 1], axis=1)) for q in p])
    np.testing.assert_allclose(eq.von_mises[0][mirror], eq.von_mises[0], rtol=1e-5, atol=1e-6 * max(peak))
    np.testing.assert_allclose(
        eq.displacement[0][mirror], eq.displacement[0] * [1, -1, 1], atol=1e-6 * squeeze[-1]
    )


def test_agrees_with_scikit_fem_linear_elasticity():
    """Cantilever under its own weight (small strain): same mesh, P1 elements, L2 difference < 1 %."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    E, nu, rho, g = 1e6, 0.3, 1000.0, 2.0
    mesh = fem.TetMesh.box(size=(0.08, 0.02, 0.02), divisions=(12, 3, 3))
    clamped = np.nonzero(mesh.points[:, 0] < 1e-12)[0]
    solver = fem.QuasiStaticSolver(mesh, [], fem.Material(E, nu, rho), fixed=clamped, device="cpu")
    eq = solver.solve(body_load=fem.BodyLoad(gravity=(0, 0, -g)))
    eq.require_converged()

    m = skfem.MeshTet(mesh.points.T.copy(), mesh.tets.T.copy())
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
    K = skfem.asm(linear_elasticity(*lame_parameters(E, nu)), basis)

    @skfem.LinearForm
    def weight(v, w):
        return -rho * g * v[2]

    f = skfem.asm(weight, basis)
    dofs = basis.get_dofs(lambda x: x[0] < 1e-12)
    u = skfem.solve(*skfem.condense(K, f, D=dofs))[basis.nodal_dofs.T]  # (N, 3)
    ours = eq.displacement[0]
    rel = np.linalg.norm(ours - u) / np.linalg.norm(u)
    assert rel < 0.01
    assert -ours[:, 2].min() > 1e-6  # the load did something measurable


# ------------------------------------------------------------------ bad input
def test_bad_material_and_options():
    with pytest.raises(fem.MaterialError, match="poisson_ratio"):
        fem.Material(1e5, 0.5)
    with pytest.raises(fem.MaterialError, match="youngs_modulus"):
        fem.Material(float("nan"))
    with pytest.raises(fem.MaterialError, match="density"):
        fem.Material(1e5, 0.3, -1.0)
    with pytest.raises(ValueError, match="linear_solver"):
        fem.SolverOptions(linear_solver="magic")
    # a number given as a string names the field (was numpy's "ufunc 'isfinite' not supported")
    with pytest.raises(fem.MaterialError, match="youngs_modulus must be a finite number, got '1e6'"):
        fem.Material("1e6")
    with pytest.raises(fem.MaterialError, match="poisson_ratio must be a finite number, got 'abc'"):
        fem.Material(1e6, "abc")


def test_bad_solver_set_up_names_the_argument():
    """Wrong types at QuasiStaticSolver's boundary (were "not iterable" or AttributeError deep inside)."""
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(1, 1, 1))
    floor = fem.RigidBody("floor", fem.Plane())
    with pytest.raises(
        TypeError, match=r"bodies must be a list of RigidBody instances, got RigidBody \(wrap"
    ):
        fem.QuasiStaticSolver(mesh, floor, device="cpu")
    with pytest.raises(TypeError, match="bodies must be RigidBody instances, got str 'floor'"):
        fem.QuasiStaticSolver(mesh, ["floor"], device="cpu")
    with pytest.raises(TypeError, match="material must be a Material or a list of 1 Materials, got float"):
        fem.QuasiStaticSolver(mesh, [floor], 1e5, device="cpu")
    solver = fem.QuasiStaticSolver(mesh, (b for b in [floor]), device="cpu")  # any iterable of bodies
    assert [b.name for b in solver.bodies] == ["floor"]
    # a plane without a direction (was accepted, NaN frames later)
    with pytest.raises(fem.BodyError, match="Plane normal must be a non-zero vector"):
        fem.Plane(normal=(0, 0, 0))
    with pytest.raises(fem.BodyError, match="Plane point must be 3 finite numbers"):
        fem.Plane(point=(float("nan"), 0, 0))


def test_bad_bodies_and_targets():
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 2))
    v, f = box_pad()
    with pytest.raises(fem.BodyError, match="closed"):
        fem.TriangleMesh(v, f[:-1])
    with pytest.raises(fem.BodyError, match="outward"):
        fem.TriangleMesh(v, f[:, ::-1])
    with pytest.raises(fem.BodyError, match="radius"):
        fem.Sphere(radius=-1.0)
    with pytest.raises(fem.BodyError, match="mode"):
        fem.Control("pull")
    with pytest.raises(fem.BodyError, match="friction"):
        fem.RigidBody("p", fem.Plane(), friction=-0.1)
    top = fem.RigidBody(
        "top", fem.Plane(point=(0, 0, L), normal=(0, 0, -1)), control=fem.Control.force((0, 0, -1))
    )
    with pytest.raises(fem.BodyError, match="unique"):
        fem.QuasiStaticSolver(mesh, [top, top], device="cpu")
    solver = fem.QuasiStaticSolver(mesh, [top], device="cpu")
    with pytest.raises(KeyError, match="unknown dof 'grip'"):
        solver.solve(targets={"grip": 1.0})
    with pytest.raises(ValueError, match="finite"):
        solver.solve(targets={"top": float("nan")})
    with pytest.raises(ValueError, match="target 'top' must be a number or 1 numbers, got 'abc'"):
        solver.solve(targets={"top": "abc"})
    with pytest.raises(KeyError, match="no rigid body named"):
        solver.set_body_pose("finger", np.eye(4))
    bad_pose = np.eye(4)
    bad_pose[0, 0] = 2.0
    with pytest.raises(fem.BodyError, match="rotation"):
        solver.set_body_pose("top", bad_pose)
    with pytest.raises(ValueError, match="BodyLoad.gravity"):
        solver.solve(body_load=fem.BodyLoad(gravity=(0, 0, float("inf"))))
    with pytest.raises(ValueError, match="fixed mask"):
        fem.QuasiStaticSolver(mesh, [], fixed=np.zeros((3, 3), bool), device="cpu")
    with pytest.raises(TypeError, match="TetMesh"):
        fem.QuasiStaticSolver(mesh.points, [], device="cpu")


REFERENCE = Path(__file__).parent / "data" / "fem_cpu_reference.npz"
REFERENCE_FORCES = np.array([0.5, 1.5])


def _reference_solve(device):
    _, solver = _grasp_problem(2, device=device)
    eq = _ramp(solver, REFERENCE_FORCES)
    eq.require_converged()
    return eq


def write_cpu_reference():
    """Regenerate tests/data/fem_cpu_reference.npz (python tests/test_fem_solver.py)."""
    eq = _reference_solve("cpu")
    REFERENCE.parent.mkdir(exist_ok=True)
    np.savez_compressed(REFERENCE, displacement=eq.displacement, von_mises=eq.von_mises)


def _assert_matches_reference(eq):
    ref = np.load(REFERENCE)
    np.testing.assert_allclose(eq.displacement, ref["displacement"], atol=1e-7 * L)
    vm = ref["von_mises"]
    np.testing.assert_allclose(eq.von_mises, vm, rtol=1e-4, atol=1e-6 * vm.max())


def test_cpu_matches_stored_reference():
    """The stored CPU answer that the CUDA test compares with is the current CPU solver's answer.
    (The GPU machines have no CPU code generator for Warp, so both cannot run in one process there.)"""
    _assert_matches_reference(_reference_solve("cpu"))


@pytest.mark.gpu
def test_cuda_matches_cpu():
    _assert_matches_reference(_reference_solve("cuda"))


def test_dalembert_loads_per_problem():
    """Per-problem frame accelerations: the support reaction balances m (g - a) and the moment of alpha."""
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 2), origin=(-L / 2, -L / 2, -L / 2))
    clamped = np.nonzero(mesh.points[:, 2] < -L / 2 + 1e-12)[0]
    mats = [fem.Material(1e6, 0.3, rho) for rho in (500.0, 1000.0, 2000.0)]
    solver = fem.QuasiStaticSolver(mesh, [], mats, batch_size=3, fixed=clamped, device="cpu")
    g = np.array([0.0, 0.0, -9.81])
    acc = np.array([[3.0, 0.0, 0.0], [0.0, -5.0, 2.0], [1.0, 1.0, 1.0]])
    alpha = np.array([[0.0, 0.0, 100.0], [0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    eq = solver.solve(body_load=fem.BodyLoad(gravity=g, linear_acceleration=acc, angular_acceleration=alpha))
    eq.require_converged()
    for b, rho in enumerate((500.0, 1000.0, 2000.0)):
        m = mesh.mass(rho)
        # the support carries the whole inertial + gravity load (the centroid is the rotation centre)
        np.testing.assert_allclose(
            eq.reaction_force[b].sum(axis=0), -m * (g - acc[b]), rtol=1e-6, atol=1e-7 * m * 9.81
        )
        # moment balance in the deformed configuration (elastic forces carry no net moment): exact
        x = mesh.points + eq.displacement[b]
        f = fem.BodyLoad(gravity=g, linear_acceleration=acc[b], angular_acceleration=alpha[b]).nodal_forces(
            mesh.points, mesh.vertex_masses(rho), 1
        )[0]
        scale = m * 9.81 * L
        np.testing.assert_allclose(np.cross(x, eq.reaction_force[b] + f).sum(axis=0), 0.0, atol=1e-7 * scale)
        # and to first order the support supplies I alpha about the centroid
        r = mesh.points - mesh.center_of_mass()
        masses = mesh.vertex_masses(rho)
        inertia = sum(mi * (ri @ ri * np.eye(3) - np.outer(ri, ri)) for mi, ri in zip(masses, r))
        moment = np.cross(r, eq.reaction_force[b]).sum(axis=0)
        np.testing.assert_allclose(moment, inertia @ alpha[b], atol=1e-3 * scale)


if __name__ == "__main__":
    write_cpu_reference()


# the factorizing solvers on the CPU and on CUDA (there the banded solver factors all its problems in one
# batch, and a breakdown is read from the batch's flags)
SOLVE_DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


@pytest.mark.parametrize("device", SOLVE_DEVICES)
@pytest.mark.parametrize(
    "method, factor, fallback", [("dense", "cholesky", "lu"), ("banded", "banded", "banded")]
)
def test_factorizing_solvers_match_numpy_with_lu_fallback_and_factor_reuse(method, factor, fallback, device):
    """solve_dense and solve_banded: SPD problems by Cholesky (dense or block-tridiagonal with the travel
    rows as border), an indefinite one by LU (dense, or block LU), zero right-hand sides skipped, and a
    second right-hand side on the same matrix solved with the kept factors."""
    import warp as wp

    from defgraspnets.fem.system import BatchedSystem, BlockPattern

    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 4))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    B, n = 3, 3 * pattern.rows_per_problem
    system = BatchedSystem(pattern, B, device)
    rng = np.random.default_rng(0)
    # problems 0, 1 positive definite; problem 2 indefinite (eigenvalues of both signs)
    dense, values = symmetric_pattern_matrices(pattern, B, [True, True, False], rng)
    system.values.assign(wp.array(values, dtype=wp.mat33d, device=device))
    for _ in range(2):
        rhs = rng.normal(size=(B, n))
        rhs[1] = 0.0  # a converged problem: skipped, increment zero
        system.rhs.assign(rhs.reshape(-1, 3))
        iterations, residual = getattr(system, f"solve_{method}")()
        assert iterations == 1 and residual < 1e-10
        x = system.increment.numpy().reshape(B, n)
        for b in (0, 2):
            np.testing.assert_allclose(x[b], np.linalg.solve(dense[b], rhs[b]), rtol=1e-8, atol=1e-12)
        np.testing.assert_array_equal(x[1], 0.0)
        assert sorted(system._dense_factors) == [0, 2]  # factors kept for the next right-hand side
        assert system._dense_factors[0][0] == factor and system._dense_factors[2][0] == fallback
    np.testing.assert_array_equal(system.factorizations, [1, 0, 1])  # the second solve reused them
    system.zero()
    assert not system._dense_factors


@pytest.mark.parametrize("device", SOLVE_DEVICES)
@pytest.mark.parametrize("method", ["dense", "banded", "dense_banded"])
def test_factorizing_solvers_report_indefinite_problems_instead_of_lu(method, device):
    """``report_indefinite``: a marked problem whose matrix is not positive definite gets no factor and a zero
    increment and is flagged in ``indefinite`` (the Newton loop damps it instead of taking an LU step); an
    unmarked one still falls back to LU, and positive definite ones are solved whatever the mark. A factor
    kept from an earlier solve of a reported problem is dropped."""
    import warp as wp

    from defgraspnets.fem.system import BatchedSystem, BlockPattern

    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 4))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    B, n = 4, 3 * pattern.rows_per_problem
    rng = np.random.default_rng(2)
    dense, values = symmetric_pattern_matrices(pattern, B, [True, False, False, True], rng)
    system = BatchedSystem(pattern, B, device)
    system.keep_factors = True
    system.values.assign(wp.array(values, dtype=wp.mat33d, device=device))
    solve = getattr(system, f"solve_{method}")
    kwargs = {"banded_from": 1} if method == "dense_banded" else {}
    rhs = rng.normal(size=(B, n))
    system.rhs.assign(rhs.reshape(-1, 3))
    solve(**kwargs)  # nothing marked: both indefinite problems by LU
    assert not system.indefinite.any() and sorted(system._dense_factors) == [0, 1, 2, 3]
    system.report_indefinite = np.array([True, True, False, False])
    solve(refactor=np.ones(B, dtype=bool), **kwargs)
    np.testing.assert_array_equal(system.indefinite, [False, True, False, False])
    x = system.increment.numpy().reshape(B, n)
    np.testing.assert_array_equal(x[1], 0.0)
    for b in (0, 2, 3):
        np.testing.assert_allclose(x[b], np.linalg.solve(dense[b], rhs[b]), rtol=1e-8, atol=1e-12)
    assert sorted(system._dense_factors) == [0, 2, 3]  # problem 1's kept LU factor dropped
    np.testing.assert_array_equal(system.fresh_factor, True)
    np.testing.assert_array_equal(system.factorizations, [2, 2, 2, 2])
    # every problem marked, problem 2 keeps its LU factor (not refactored): it is solved with it; problem 1
    # has no stored factor, so it is factored again and reported again
    system.report_indefinite = np.ones(B, dtype=bool)
    rhs = rng.normal(size=(B, n))
    system.rhs.assign(rhs.reshape(-1, 3))
    solve(refactor=np.array([True, False, False, True]), **kwargs)
    np.testing.assert_array_equal(system.indefinite, [False, True, False, False])
    x = system.increment.numpy().reshape(B, n)
    np.testing.assert_array_equal(x[1], 0.0)
    for b in (0, 2, 3):
        np.testing.assert_allclose(x[b], np.linalg.solve(dense[b], rhs[b]), rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(system.factorizations, [3, 3, 2, 3])
    assert sorted(system._dense_factors) == [0, 2, 3]


def test_dense_banded_solver_factors_few_problems_densely_and_many_banded():
    """solve_dense_banded: below ``banded_from`` problems to factor the dense Cholesky, from it on the
    banded one; either way the solutions are numpy's, and kept factors of both kinds serve a second
    right-hand side."""
    import warp as wp

    from defgraspnets.fem.system import BatchedSystem, BlockPattern

    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 4))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    B, n = 3, 3 * pattern.rows_per_problem
    rng = np.random.default_rng(1)
    dense, values = symmetric_pattern_matrices(pattern, B, [True, True, True], rng)
    for banded_from, kind in ((3, "cholesky"), (2, "banded"), (1, "banded")):
        system = BatchedSystem(pattern, B, "cpu")
        system.values.assign(wp.array(values, dtype=wp.mat33d, device="cpu"))
        rhs = rng.normal(size=(B, n))
        rhs[1] = 0.0  # two problems to factor
        system.rhs.assign(rhs.reshape(-1, 3))
        system.solve_dense_banded(banded_from=banded_from)
        x = system.increment.numpy().reshape(B, n)
        for b in (0, 2):
            np.testing.assert_allclose(x[b], np.linalg.solve(dense[b], rhs[b]), rtol=1e-8, atol=1e-12)
        assert {p: f[0] for p, f in system._dense_factors.items()} == {0: kind, 2: kind}
        # a second right-hand side with problem 1 too: problems 0 and 2 reuse their factors, 1 is factored
        # alone, densely below banded_from = 2 and banded at 1
        rhs = rng.normal(size=(B, n))
        system.rhs.assign(rhs.reshape(-1, 3))
        system.solve_dense_banded(banded_from=banded_from)
        x = system.increment.numpy().reshape(B, n)
        for b in range(B):
            np.testing.assert_allclose(x[b], np.linalg.solve(dense[b], rhs[b]), rtol=1e-8, atol=1e-12)
        assert system._dense_factors[1][0] == ("banded" if banded_from == 1 else "cholesky")
        np.testing.assert_array_equal(system.factorizations, [1, 1, 1])
    with pytest.raises(ValueError, match="banded_from"):
        system.solve_dense_banded(banded_from=0)
    for bad in (0, 2.5, None):
        with pytest.raises(ValueError, match="banded_min_problems"):
            fem.SolverOptions(banded_min_problems=bad)
    for bad in (0, 1.5, None, True):
        with pytest.raises(ValueError, match="factor_streams"):
            fem.SolverOptions(factor_streams=bad)


def _dense_solutions_with_streams(device: str, factor_streams: int):
    """solve_dense of four problems (one indefinite: LU) with ``factor_streams``: (solutions, numpy's,
    factor kinds)."""
    import warp as wp

    from defgraspnets.fem.system import BatchedSystem, BlockPattern

    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(2, 2, 4))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    B, n = 4, 3 * pattern.rows_per_problem
    rng = np.random.default_rng(5)
    dense, values = symmetric_pattern_matrices(pattern, B, [True, False, True, True], rng)
    system = BatchedSystem(pattern, B, device)
    system.factor_streams = factor_streams
    system.values.assign(wp.array(values, dtype=wp.mat33d, device=device))
    rhs = rng.normal(size=(B, n))
    system.rhs.assign(wp.array(rhs.reshape(-1, 3), dtype=wp.vec3d, device=device))
    system.solve_dense()
    expected = np.stack([np.linalg.solve(dense[b], rhs[b]) for b in range(B)])
    kinds = [system._dense_factors[b][0] for b in range(B)]
    return system.increment.numpy().reshape(B, n), expected, kinds


def test_dense_factor_streams_on_the_cpu_factor_one_after_another():
    """factor_streams is a CUDA setting: on the CPU any value gives the one-stream answer, bit for bit."""
    x1, expected, kinds = _dense_solutions_with_streams("cpu", 1)
    x3, _, _ = _dense_solutions_with_streams("cpu", 3)
    np.testing.assert_allclose(x1, expected, rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(x3, x1)
    assert kinds == ["cholesky", "lu", "cholesky", "cholesky"]


@pytest.mark.gpu
def test_cuda_dense_factor_streams_match_one_stream():
    """Three side streams factor four problems (one falls back to LU): numpy's solutions, and the same
    as one stream to round-off."""
    x1, expected, kinds1 = _dense_solutions_with_streams("cuda", 1)
    x3, _, kinds3 = _dense_solutions_with_streams("cuda", 3)
    np.testing.assert_allclose(x3, expected, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(x3, x1, rtol=1e-12, atol=1e-14)
    assert kinds1 == kinds3 == ["cholesky", "lu", "cholesky", "cholesky"]


def test_early_friction_lag_check_saves_relag_cycles_and_keeps_the_equilibrium():
    """Pads tilted about the box's long axis press at an angle that friction must hold, so the frozen
    friction lags are found inconsistent and re-lagged several times per force step. Checking the lags once
    the residual is within 1000x the tolerance (``friction_lag_check``) re-lags before the last iterations
    on a stale potential: fewer Newton iterations (measured 77 -> 66 and 220 -> 179 on one 2-core CPU,
    77 -> 66 and 244 -> 231 on an AVX-512 one: the frictional Newton path, hence its iteration count, turns
    on the factorization's round-off, so only "no problem takes more, the batch takes fewer" is asserted),
    the same converged equilibrium to the friction consistency it asks for (``friction_rtol`` 1e-3: Coulomb
    equilibria depend on the path; measured 1e-8 and 1.9e-4 of the largest displacement)."""
    W = 0.04  # box width [m]
    mesh = fem.TetMesh.box(
        size=(W, 0.75 * W, 1.25 * W), divisions=(4, 4, 4), origin=(-W / 2, -0.375 * W, -0.625 * W)
    )
    v, f = box_pad((0.012, 0.008, 0.012))
    tilts = (0.35, 0.5)
    runs = {}
    for check in (1.0, 1000.0):
        bodies = [
            fem.RigidBody(n, fem.TriangleMesh(v, f), control=fem.Control.force(d, dof="grip"), friction=0.7)
            for n, d in (("left", (0, -1, 0)), ("right", (0, 1, 0)))
        ]
        options = fem.SolverOptions(
            linear_solver="direct", max_factor_reuse=0, rtol=1e-5, friction_rtol=1e-3, contact_smoothing=1e-2,
            max_step_fraction=0.01, friction_lag_check=check,
        )  # fmt: skip
        material = fem.Material(2e5, 0.3, 1000.0, model="neohookean")
        solver = fem.QuasiStaticSolver(
            mesh, bodies, [material] * 2, batch_size=2, device="cpu", options=options
        )
        poses = {"left": [], "right": []}
        for t in tilts:
            R = Rotation.from_rotvec([t, 0.0, 0.0]).as_matrix()
            for name, sign in (("left", 1), ("right", -1)):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, R @ [0.0, sign * (0.375 * W + 0.004), 0.0]
                poses[name].append(T)
        for name, T in poses.items():
            solver.set_body_pose(name, np.array(T))
        path = solver.ramp(10, targets={"grip": np.full(2, 15.0)})
        path[-1].require_converged()
        runs[check] = (sum(eq.newton_iterations for eq in path), path[-1].displacement)
    (plain, u_plain), (early, u_early) = runs[1.0], runs[1000.0]
    assert np.all(early <= plain) and early.sum() < plain.sum()
    scale = np.abs(u_plain).max(axis=(1, 2))
    assert np.all(np.abs(u_early - u_plain).max(axis=(1, 2)) < 1e-3 * scale)
    with pytest.raises(ValueError, match="friction_lag_check"):
        fem.SolverOptions(friction_lag_check=0.5)


def test_newton_budget_flags_a_problem_instead_of_holding_up_the_batch():
    forces = np.array([1.0, 2.0])
    _, solver = _grasp_problem(2)
    free = solver.solve(targets={"grip": forces}, initial_fraction=0.25)
    free.require_converged()
    assert free.newton_iterations.min() > 3
    budget = fem.SolverOptions(max_newton_per_solve=3)
    _, limited = _grasp_problem(2)
    limited.options = budget
    eq = limited.solve(targets={"grip": forces}, initial_fraction=0.25)
    # each problem stops after the increment that spent its budget, at its last converged state
    assert np.all(eq.status == fem.SolveStatus.NOT_CONVERGED)
    assert np.all((eq.load_fraction > 0) & (eq.load_fraction < 1.0))
    assert np.all((eq.newton_iterations >= 3) & (eq.newton_iterations <= 3 + budget.max_newton_iterations))
    with pytest.raises(RuntimeError, match="NOT_CONVERGED"):
        eq.require_converged()
    with pytest.raises(ValueError, match="max_newton_per_solve"):
        fem.SolverOptions(max_newton_per_solve=-1)
    with pytest.raises(ValueError, match="friction_rtol"):
        fem.SolverOptions(friction_rtol=1.0)
    for bad in (-1, 1.5, "yes"):
        with pytest.raises(ValueError, match="relag_friction_on_retry"):
            fem.SolverOptions(relag_friction_on_retry=bad)


def _assert_equilibria_identical(a, b):
    """Every field of two Equilibrium objects equal bit for bit (NaN where NaN)."""
    import dataclasses

    for f in dataclasses.fields(a):
        if f.name in ("mesh", "extras"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, dict):
            assert x.keys() == y.keys(), f.name
            for k in x:
                assert np.array_equal(x[k], y[k], equal_nan=True), f"{f.name}[{k}]"
        elif x is None:
            assert y is None, f.name
        else:
            assert np.array_equal(x, y, equal_nan=True), f.name


@pytest.mark.parametrize("linear_solver", ["direct", "dense"])
def test_copied_state_solves_as_its_source_problem(linear_solver):
    """copy_state_from: replicas of solved problems continue bit for bit as a solver that solved every
    replica itself (friction history, predictor, chord-Newton factorizations included)."""
    forces = np.array([0.5, 1.0, 2.0])
    rows = np.array([1, 0, 1, 1])  # replicas of the source's problems (source problem 1 = problem 2)
    select = np.array([0, 2])[rows]
    _, source = _grasp_problem(3, linear_solver=linear_solver, select=[0, 2])
    _, reference = _grasp_problem(3, linear_solver=linear_solver, select=select)
    _, copy = _grasp_problem(3, linear_solver=linear_solver, select=[0, 0, 0, 0])  # materials copied too
    _ramp(source, forces[[0, 2]], steps=2)
    squeezed = _ramp(reference, forces[select], steps=2)
    copy.copy_state_from(source, rows)
    assert reference.system._direct_factors or reference.system._dense_factors
    gravity = np.array([[0, 0, -9.81], [0, 0, 9.81], [9.81, 0, 0], [0, 9.81, 30.0]])
    for scale in (0.5, 1.0):
        load = fem.BodyLoad(gravity=scale * gravity)
        eq_ref = reference.solve(targets={"grip": 1.2 * forces[select]}, body_load=load)
        eq_copy = copy.solve(targets={"grip": 1.2 * forces[select]}, body_load=load)
        assert np.all(eq_ref.newton_iterations > 0)
        _assert_equilibria_identical(eq_ref, eq_copy)
    np.testing.assert_array_equal(copy.status, reference.status)
    assert not np.array_equal(eq_ref.displacement, squeezed.displacement)


def test_copy_state_rejects_mismatched_solvers():
    _, source = _grasp_problem(3, select=[0, 2])
    _, copy = _grasp_problem(3, select=[0, 1, 2])
    with pytest.raises(ValueError, match="one problem of other per problem"):
        copy.copy_state_from(source, [0, 1])
    with pytest.raises(ValueError, match=r"\[0, 2\)"):
        copy.copy_state_from(source, [0, 1, 2])
    with pytest.raises(ValueError, match="integer"):
        copy.copy_state_from(source, [0.0, 1.0, 1.0])
    with pytest.raises(TypeError, match="QuasiStaticSolver"):
        copy.copy_state_from(object(), [0, 1, 1])
    other_mesh = fem.TetMesh.box(size=(L, L, L), divisions=(3, 3, 3))
    with pytest.raises(ValueError, match="mesh sizes"):
        fem.QuasiStaticSolver(other_mesh, source.bodies, batch_size=3, device="cpu").copy_state_from(
            source, [0, 1, 1]
        )
    with pytest.raises(ValueError, match="bodies"):
        fem.QuasiStaticSolver(source.mesh, source.bodies[:1], batch_size=3, device="cpu").copy_state_from(
            source, [0, 1, 1]
        )
    with pytest.raises(ValueError, match="options"):
        fem.QuasiStaticSolver(
            source.mesh, source.bodies, batch_size=3, device="cpu", options=fem.SolverOptions(rtol=1e-3)
        ).copy_state_from(source, [0, 1, 1])
    with pytest.raises(ValueError, match="fixed"):
        fem.QuasiStaticSolver(
            source.mesh, source.bodies, batch_size=3, device="cpu", fixed=[0], options=source.options
        ).copy_state_from(source, [0, 1, 1])
    copy.copy_state_from(source, [0, 1, 1])  # a valid copy after the refused ones


@pytest.mark.parametrize("linear_solver", ["dense_banded", "banded"])
def test_newton_loop_tells_the_solvers_which_right_hand_sides_are_nonzero(linear_solver, monkeypatch):
    """The Newton loop passes its working problems to the PyTorch solvers as the problems with a nonzero
    right-hand side (so that they need not read the right-hand sides from the device): at every solve of a
    three-grasp ramp, where problems converge at different iterations, they are exactly those the device's
    right-hand sides say; and the answer is the one the solvers find by reading them."""
    from defgraspnets.fem.system import BatchedSystem

    seen = []
    method = "solve_dense_banded" if linear_solver == "dense_banded" else "solve_banded"
    original = getattr(BatchedSystem, method)

    def checked(self, *args, todo=None, **kwargs):
        seen.append((list(todo), self._problems_with_rhs()))
        return original(self, *args, todo=todo, **kwargs)

    forces = np.array([0.5, 1.0, 2.0])
    _, solver = _grasp_problem(3, linear_solver=linear_solver, model="neohookean", max_factor_reuse=0)
    monkeypatch.setattr(BatchedSystem, method, checked)
    told = _ramp(solver, forces)
    told.require_converged()
    assert len(seen) > 10 and any(len(t) < 3 for t, _ in seen)  # some solves without every problem
    for todo, found in seen:
        assert todo == found
    monkeypatch.setattr(BatchedSystem, method, lambda self, *a, todo=None, **k: original(self, *a, **k))
    _, solver = _grasp_problem(3, linear_solver=linear_solver, model="neohookean", max_factor_reuse=0)
    found = _ramp(solver, forces)
    np.testing.assert_array_equal(found.displacement, told.displacement)
