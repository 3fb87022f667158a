"""The squeeze ramp of the grasp simulator: sampled Franka grasps of a box, force-controlled fingers."""

import numpy as np
import pytest

from defgraspnets import fem
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import FINGER_NAMES, make_squeeze_solver, squeeze_ramp, squeeze_solver_options

SIZE = np.array([0.05, 0.04, 0.06])


@pytest.fixture(scope="module")
def ramp():
    mesh = fem.TetMesh.box(size=SIZE, divisions=(4, 3, 5), origin=-SIZE / 2)
    grasps = sample_antipodal_grasps(mesh, num_grasps=3, seed=0)
    solver = make_squeeze_solver(mesh, grasps, fem.Material(2e5, 0.3, 1000.0), friction=0.7, device="cpu")
    calls = []
    results = squeeze_ramp(solver, max_force=10.0, steps=8, on_step=lambda i, f, eq: calls.append((i, f)))
    return mesh, grasps, solver, results, calls


def test_every_grasp_reaches_the_force_in_equilibrium(ramp):
    mesh, grasps, solver, results, calls = ramp
    assert calls == [(i, 10.0 * (i + 1) / 8) for i in range(8)]
    last = results[-1]
    last.require_converged()
    # each finger presses with half the total grasp force, along its closing axis; the object is balanced
    tol = 10 * solver.options.rtol * 10.0  # Newton tolerance: rtol x the largest force component
    np.testing.assert_allclose(last.dof_force["grip"], 10.0, atol=tol)
    left, right = (last.body_force[name] for name in FINGER_NAMES)
    np.testing.assert_allclose(left + right, 0.0, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(left, axis=1), 5.0, rtol=0.05)  # friction may tilt it a little
    # stated penetration bound: ((p / E) / kappa + zeta / 2) h, with p <= E here
    h = mesh.median_surface_edge_length
    o = solver.options
    assert np.all(last.max_penetration <= (1.0 / o.contact_stiffness + o.contact_smoothing / 2) * h)


def test_squeezing_harder_deforms_more(ramp):
    _, _, _, results, _ = ramp
    travel = np.array([eq.travel["grip"] for eq in results])  # (steps, grasps)
    assert np.all(np.diff(travel, axis=0) > 0)
    peak_stress = np.array([eq.von_mises.max(axis=1) for eq in results])
    assert np.all(np.diff(peak_stress, axis=0) > 0)


def test_squeeze_options_and_bad_force():
    assert squeeze_solver_options().contact_smoothing == pytest.approx(1e-3)
    assert squeeze_solver_options().rtol == pytest.approx(1e-5)
    assert squeeze_solver_options(linear_solver="cg").linear_solver == "cg"
    mesh = fem.TetMesh.box(size=SIZE, divisions=(2, 2, 2), origin=-SIZE / 2)
    grasps = sample_antipodal_grasps(mesh, num_grasps=1, seed=0)
    solver = make_squeeze_solver(mesh, grasps, fem.Material(2e5, 0.3, 1000.0), device="cpu")
    with pytest.raises(ValueError, match="max_force"):
        squeeze_ramp(solver, max_force=float("nan"))
    with pytest.raises(ValueError, match="no grasps"):
        make_squeeze_solver(mesh, grasps[:0], fem.Material(2e5, 0.3, 1000.0), device="cpu")


def test_soft_neohookean_object_holds_15_newtons_without_inverting():
    """E = 1e4 Pa (soft tissue) squeezed to 15 N: contact pressure of several E. The Neo-Hookean object
    converges with no inverted tet, deforms by centimetres and balances the fingers; the co-rotated model
    (whose volume resistance is bounded) inverts tets on the way (measured on this grasp: from 6.9 N)."""
    mesh = fem.TetMesh.box(size=SIZE, divisions=(6, 5, 7), origin=-SIZE / 2)
    grasps = sample_antipodal_grasps(mesh, num_grasps=4, seed=0)[[1]]
    options = squeeze_solver_options(linear_solver="direct")
    results = {}
    for model, force, steps in (("neohookean", 15.0, 15), ("corotated", 8.4, 12)):
        material = fem.Material(1e4, 0.3, 1000.0, model=model)
        solver = make_squeeze_solver(mesh, grasps, material, friction=0.7, device="cpu", options=options)
        results[model] = squeeze_ramp(solver, max_force=force, steps=steps)
    soft = results["neohookean"]
    last = soft[-1]
    last.require_converged()
    assert all(eq.inverted_tets[0] == 0 for eq in soft)
    np.testing.assert_allclose(last.dof_force["grip"], 15.0, rtol=1e-4)
    left, right = (last.body_force[name] for name in FINGER_NAMES)
    np.testing.assert_allclose(left + right, 0.0, atol=1e-3)
    assert np.abs(last.displacement).max() > 0.01  # centimetre deformation of a 4-6 cm box
    travel = np.array([eq.travel["grip"][0] for eq in soft])
    step = np.diff(travel)
    assert np.all(step > 0) and step[-1] < 0.3 * step[0]  # it stiffens as it is compressed
    # the co-rotated solution of the same grasp has inverted elements at 8.4 N
    assert results["corotated"][-1].inverted_tets[0] > 0
