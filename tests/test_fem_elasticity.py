"""Hyperelastic elements (fixed co-rotated, Neo-Hookean): derivatives, patch tests, rigid motions."""

import numpy as np
import pytest
import warp as wp
from fem_helpers import corotated_cauchy_stress, linear_elastic_stress, neohookean_cauchy_stress
from scipy.spatial.transform import Rotation

from defgraspnets import fem
from defgraspnets.fem import elasticity as ek

E, NU = 2e5, 0.3
MAT = fem.Material(E, NU, 1000.0)


MODELS = fem.MATERIAL_MODELS


def _element(x, rest, mu, lam, exact=False, model="corotated"):
    """Energy, gradient (12,) and Hessian (12, 12, projected or exact) of one tet from the Warp kernels."""
    m = fem.TetMesh(rest, [[0, 1, 2, 3]])
    args = dict(device="cpu")
    tets = wp.array(m.tets.astype(np.int32), dtype=wp.int32, **args)
    binv = wp.array(m.rest_shape_inverse, dtype=wp.mat33d, **args)
    vol = wp.array(m.volumes, dtype=wp.float64, **args)
    mu_a, lam_a = wp.array([mu], dtype=wp.float64, **args), wp.array([lam], dtype=wp.float64, **args)
    act = wp.array([1], dtype=wp.int32, **args)
    code = wp.array([MODELS.index(model)], dtype=wp.int32, **args)
    pos = wp.array(x, dtype=wp.vec3d, **args)
    e = wp.zeros(1, dtype=wp.float64, **args)
    wp.launch(ek.elastic_energy_kernel, (1, 1), [pos, tets, binv, vol, mu_a, lam_a, code, 4, act, e], **args)
    g = wp.zeros(4, dtype=wp.vec3d, **args)
    H = wp.zeros(16, dtype=wp.mat33d, **args)
    fs = wp.zeros(1, dtype=wp.float64, **args)
    blocks = wp.array(np.arange(16, dtype=np.int32).reshape(1, 16), dtype=wp.int32, **args)
    wp.launch(
        ek.elastic_gradient_hessian_kernel,
        (1, 1),
        [
            pos,
            tets,
            binv,
            vol,
            mu_a,
            lam_a,
            code,
            blocks,
            4,
            4,
            16,
            act,
            wp.array([int(exact)], dtype=wp.int32),
            g,
            fs,
            H,
        ],
        **args,
    )
    return (
        e.numpy()[0],
        g.numpy().ravel(),
        H.numpy().reshape(4, 4, 3, 3).transpose(0, 2, 1, 3).reshape(12, 12),
    )


REST = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 0.01


def _fd_gradient_hessian(x, model):
    h = 1e-8
    g_fd, H_fd = np.zeros(12), np.zeros((12, 12))
    for i in range(12):
        xp, xm = x.ravel().copy(), x.ravel().copy()
        xp[i] += h
        xm[i] -= h
        ep, gp, _ = _element(xp.reshape(4, 3), REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
        em, gm, _ = _element(xm.reshape(4, 3), REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
        g_fd[i] = (ep - em) / (2 * h)
        H_fd[:, i] = (gp - gm) / (2 * h)
    return g_fd, H_fd


@pytest.mark.parametrize("model", MODELS)
def test_element_gradient_and_hessian_match_finite_differences(model):
    rng = np.random.default_rng(3)
    F = 1.2 * np.eye(3) + 0.05 * rng.normal(size=(3, 3))  # stretched: no eigenvalue is clamped
    x = REST @ F.T + 0.002
    _, g, H = _element(x, REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
    g_fd, H_fd = _fd_gradient_hessian(x, model)
    assert np.abs(g - g_fd).max() < 1e-6 * np.abs(g).max()
    assert np.abs(H - H_fd).max() < 1e-6 * np.abs(H).max()


@pytest.mark.parametrize(
    "model, F",
    [
        ("corotated", np.diag([0.7, 0.8, 0.9])),
        # Neo-Hookean: negative twist eigenvalue mu + (lambda log J - mu) / (s_i s_j) needs strong compression
        ("neohookean", np.diag([0.3, 0.35, 0.9])),
        ("neohookean", np.array([[0.4, 0.1, 0.0], [0.05, 0.3, 0.02], [0.0, -0.03, 1.1]])),
    ],
)
def test_exact_element_hessian_of_a_compressed_tet_matches_finite_differences(model, F):
    # compressed: some twist eigenvalues are negative, so the projection changes H
    x = REST @ F.T
    _, g, H = _element(x, REST, MAT.shear_modulus, MAT.lame_lambda, exact=True, model=model)
    _, _, H_psd = _element(x, REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
    g_fd, H_fd = _fd_gradient_hessian(x, model)
    assert np.abs(g - g_fd).max() < 1e-6 * np.abs(g).max()
    assert np.abs(H - H_fd).max() < 1e-6 * np.abs(H).max()
    assert np.linalg.eigvalsh(H).min() < -1e-3 * np.abs(H).max()  # truly indefinite
    assert np.abs(H_psd - H).max() > 1e-2 * np.abs(H).max()  # and the projection differs


@pytest.mark.parametrize("model", MODELS)
def test_element_hessian_is_psd_when_compressed_and_inverted(model):
    states = [np.diag([0.3, 0.4, 1.0]), np.diag([0.05, 2.0, 1.5]), np.diag([0.2, 0.15, 0.5])]
    if model == "corotated":
        states.append(np.diag([1.0, 1.0, -0.2]))  # inverted: finite co-rotated energy
    for F in states:
        _, _, H = _element(REST @ F.T, REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
        assert np.linalg.eigvalsh(H).min() > -1e-9 * np.abs(H).max()


def test_neohookean_energy_is_infinite_for_inverted_and_flat_tets_and_grows_towards_collapse():
    mu, lam = MAT.shear_modulus, MAT.lame_lambda
    for F in (np.diag([1.0, 1.0, -0.2]), np.diag([1.0, 1.0, 0.0])):
        e, _, _ = _element(REST @ F.T, REST, mu, lam, model="neohookean")
        assert e == np.inf
    volume = 1e-6 / 6
    energies = []
    for j in (0.1, 1e-3, 1e-6):
        energies.append(_element(REST @ np.diag([1, 1, j]).T, REST, mu, lam, model="neohookean")[0])
        lj = np.log(j)
        psi = 0.5 * mu * (j * j - 1) - mu * lj + 0.5 * lam * lj * lj
        assert energies[-1] == pytest.approx(volume * psi, rel=1e-9)
    assert energies[0] < energies[1] < energies[2]
    # the co-rotated energy of the same collapse stays bounded: that is what lets soft elements invert
    flat = _element(REST @ np.diag([1, 1, 1e-6]).T, REST, mu, lam)[0]
    assert flat == pytest.approx(volume * (mu + lam / 2) * (1 - 1e-6) ** 2, rel=1e-9)
    assert energies[2] > 20 * flat


@pytest.mark.parametrize("model", MODELS)
def test_element_forces_and_stiffness_at_rest_are_those_of_linear_elasticity(model):
    e, g, H = _element(REST, REST, MAT.shear_modulus, MAT.lame_lambda, model=model)
    assert abs(e) < 1e-15 * MAT.shear_modulus * 1e-6 / 6 and np.abs(g).max() < 1e-12  # round-off of I1 - 3
    # K u for an affine u = G X equals the linear-elastic nodal forces V sigma beta_a
    G = np.array([[1e-3, 2e-4, 0], [0, -5e-4, 3e-4], [1e-4, 0, 2e-4]])
    u = (REST @ G.T).ravel()
    sigma = linear_elastic_stress(G, E, NU)
    binv = np.linalg.inv((REST[1:] - REST[0]).T)
    betas = np.vstack([-binv.sum(axis=0), binv])
    f = np.concatenate([(sigma @ b) / 6e6 for b in betas])
    np.testing.assert_allclose(H @ u, f, rtol=1e-9, atol=1e-9 * np.abs(f).max())
    # six rigid-body zero modes
    assert np.sum(np.abs(np.linalg.eigvalsh(H)) < 1e-9 * np.abs(H).max()) == 6


def _patch_solve(F_affine, translation=(0.0, 0.0, 0.0), material=MAT):
    """Box whose whole boundary follows x = F X + c; returns (solver mesh, equilibrium)."""
    mesh = fem.TetMesh.box(size=(0.02, 0.03, 0.025), divisions=(3, 3, 3))
    target = mesh.points @ F_affine.T + translation - mesh.points
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        material,
        fixed=mesh.surface_vertices,
        device="cpu",
        options=fem.SolverOptions(record_tet_stress=True),
    )
    eq = solver.solve(prescribed_displacement=np.where(mesh.is_surface_vertex[:, None], target, 0.0))
    eq.require_converged()
    return mesh, eq, target


def test_patch_test_small_strain_matches_hookes_law():
    G = np.array([[2e-4, 1e-4, -5e-5], [3e-5, -1e-4, 2e-4], [0.0, 1e-4, 3e-4]])
    mesh, eq, target = _patch_solve(np.eye(3) + G)
    interior = ~mesh.is_surface_vertex
    assert interior.sum() == 8
    np.testing.assert_allclose(eq.displacement[0, interior], target[interior], atol=1e-12)
    expected = linear_elastic_stress(G, E, NU)
    err = np.abs(eq.tet_stress[0] - expected).max() / np.abs(expected).max()
    assert err < 2e-3  # geometric nonlinearity is O(|G|)
    # the volume-weighted vertex stress is the same constant
    assert np.abs(eq.vertex_stress[0] - expected).max() / np.abs(expected).max() < 2e-3


def _corotated_psi(F, m):
    s = np.linalg.svd(F, compute_uv=False)
    return m.shear_modulus * np.sum((s - 1) ** 2) + 0.5 * m.lame_lambda * (np.prod(s) - 1) ** 2


def _neohookean_psi(F, m):
    lj = np.log(np.linalg.det(F))
    return 0.5 * m.shear_modulus * (np.sum(F * F) - 3) - m.shear_modulus * lj + 0.5 * m.lame_lambda * lj**2


@pytest.mark.parametrize(
    "model, F, cauchy, psi",
    [
        (
            "corotated",
            [[1.3, 0.2, 0.0], [-0.1, 0.8, 0.15], [0.05, 0.0, 1.1]],
            corotated_cauchy_stress,
            _corotated_psi,
        ),
        # 60 % volume loss (J = 0.4)
        (
            "neohookean",
            [[0.6, 0.1, 0.0], [-0.05, 0.8, 0.1], [0.02, 0.0, 0.85]],
            neohookean_cauchy_stress,
            _neohookean_psi,
        ),
    ],
)
def test_patch_test_large_strain_gives_constant_exact_stress(model, F, cauchy, psi):
    """The interior follows the affine map and every tet carries the closed-form Cauchy stress and energy
    of the model, computed independently with NumPy."""
    F = np.array(F)
    material = fem.Material(E, NU, 1000.0, model=model)
    mesh, eq, target = _patch_solve(F, material=material)
    interior = ~mesh.is_surface_vertex
    np.testing.assert_allclose(eq.displacement[0, interior], target[interior], atol=1e-11)
    expected = cauchy(F, material.shear_modulus, material.lame_lambda)
    np.testing.assert_allclose(
        eq.tet_stress[0],
        np.broadcast_to(expected, eq.tet_stress[0].shape),
        atol=1e-7 * np.abs(expected).max(),
    )
    assert eq.strain_energy[0] == pytest.approx(mesh.volume * psi(F, material), rel=1e-10)
    assert eq.inverted_tets[0] == 0


def test_rigidly_moved_mesh_has_zero_stress():
    """Every vertex prescribed to R X + c (a 179 degree rotation): stress and energy vanish."""
    R = Rotation.from_rotvec(np.deg2rad(179.0) * np.array([1.0, 2.0, -0.5]) / np.sqrt(5.25)).as_matrix()
    mesh = fem.TetMesh.box(size=(0.02, 0.03, 0.025), divisions=(3, 3, 3))
    target = mesh.points @ R.T + [0.1, -0.2, 0.05] - mesh.points
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        MAT,
        fixed=np.arange(mesh.num_vertices),
        device="cpu",
        options=fem.SolverOptions(record_tet_stress=True),
    )
    eq = solver.solve(prescribed_displacement=target)
    eq.require_converged()
    assert np.abs(eq.tet_stress[0]).max() < 1e-9 * E
    assert eq.strain_energy[0] < 1e-20


def test_large_rotation_of_the_boundary_leaves_the_interior_rigid_and_unstressed():
    """Boundary rotated in 12 increments of 15 degrees (180 in all); free interior vertices follow rigidly."""
    axis = np.array([1.0, 2.0, -0.5]) / np.sqrt(5.25)
    mesh = fem.TetMesh.box(size=(0.02, 0.03, 0.025), divisions=(3, 3, 3))
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        MAT,
        fixed=mesh.surface_vertices,
        device="cpu",
        options=fem.SolverOptions(record_tet_stress=True),
    )
    for step in range(1, 13):
        R = Rotation.from_rotvec(np.deg2rad(15.0 * step) * axis).as_matrix()
        target = mesh.points @ R.T - mesh.points
        eq = solver.solve(prescribed_displacement=np.where(mesh.is_surface_vertex[:, None], target, 0.0))
        eq.require_converged()
    np.testing.assert_allclose(eq.displacement[0], target, atol=1e-10)
    assert np.abs(eq.tet_stress[0]).max() < 1e-6 * E
