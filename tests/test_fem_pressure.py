"""Gas pressure as a conservative follower load: derivatives, Lame's thick sphere, closed isothermal gas."""

import numpy as np
import pytest
import trimesh
import warp as wp
from fem_helpers import thick_shell_octant_mesh

from defgraspnets import fem
from defgraspnets.fem import pressure as pk

A, B_OUT = 0.01, 0.02  # inner / outer radius of the thick sphere [m]
E, NU = 1e5, 0.3


def _pressure_terms(x, faces, p, c):
    """Pi = -p V, its gradient (lumped follower load) and its Hessian (dense), from the Warp kernels."""
    n = len(x)
    args = dict(device="cpu")
    pos = wp.array(x, dtype=wp.vec3d, **args)
    fa = wp.array(faces.astype(np.int32), dtype=wp.int32, **args)
    vol = wp.zeros(1, dtype=wp.float64, **args)
    # volume change from a "rest" state with every vertex at c (zero volume): V itself
    at_c = wp.array(np.tile(c, (n, 1)), dtype=wp.vec3d, **args)
    wp.launch(pk.cavity_volume_change_kernel, (1, len(faces)), [pos, at_c, fa, wp.vec3d(*c), n, vol], **args)
    dv = wp.zeros(n, dtype=wp.vec3d, **args)
    wp.launch(pk.volume_gradient_kernel, (1, len(faces)), [pos, fa, n, n, dv], **args)
    grad = wp.zeros(n, dtype=wp.vec3d, **args)
    scale = wp.zeros(1, dtype=wp.float64, **args)
    pa = wp.array([p], dtype=wp.float64, **args)
    act = wp.array([1], dtype=wp.int32, **args)
    wp.launch(pk.pressure_gradient_kernel, (1, n), [dv, pa, n, act, grad, scale], **args)
    blocks = np.stack([faces[:, i] * n + faces[:, j] for i in range(3) for j in range(3)], axis=1)
    H = wp.zeros(n * n, dtype=wp.mat33d, **args)
    wp.launch(
        pk.pressure_hessian_kernel,
        (1, len(faces)),
        [
            pos,
            fa,
            wp.vec3d(*c),
            pa,
            wp.array(blocks.astype(np.int32), dtype=wp.int32, **args),
            n,
            n * n,
            act,
            H,
        ],
        **args,
    )
    Hd = H.numpy().reshape(n, n, 3, 3).transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    return -p * vol.numpy()[0], grad.numpy().ravel(), Hd, vol.numpy()[0], scale.numpy()[0]


def _blob(seed=0):
    """A closed, perturbed icosphere (outward faces) and its inward (gas-facing) orientation."""
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.02)
    rng = np.random.default_rng(seed)
    x = np.asarray(m.vertices) * (1 + 0.1 * rng.random((len(m.vertices), 1))) + 0.003 * rng.normal(size=3)
    # a solid *around* the gas cavity has its outward normals pointing into the cavity: flip the faces
    return x, np.asarray(m.faces)[:, ::-1].copy()


def test_volume_gradient_and_hessian_match_finite_differences():
    x, faces = _blob()
    p, c = 750.0, np.array([0.001, -0.002, 0.0005])
    e, g, H, V, _ = _pressure_terms(x, faces, p, c)
    assert V == pytest.approx(trimesh.Trimesh(x, faces[:, ::-1]).volume, rel=1e-12)
    h = 1e-7
    g_fd, H_fd = np.zeros_like(g), np.zeros_like(H)
    for i in range(g.size):
        xp, xm = x.ravel().copy(), x.ravel().copy()
        xp[i] += h
        xm[i] -= h
        ep, gp, *_ = _pressure_terms(xp.reshape(-1, 3), faces, p, c)
        em, gm, *_ = _pressure_terms(xm.reshape(-1, 3), faces, p, c)
        g_fd[i] = (ep - em) / (2 * h)
        H_fd[:, i] = (gp - gm) / (2 * h)
    assert np.abs(g - g_fd).max() < 1e-7 * np.abs(g).max()
    assert np.abs(H - H_fd).max() < 1e-6 * np.abs(H).max()
    assert np.array_equal(H, H.T)  # exactly symmetric, as the Hessian of the potential -p V
    # a closed cavity: neither V nor its derivatives depend on the reference point
    e2, g2, H2, _, _ = _pressure_terms(x, faces, p, c + [0.05, 0.01, -0.02])
    assert e2 == pytest.approx(e, rel=1e-12)
    np.testing.assert_allclose(H2, H, atol=1e-9 * np.abs(H).max())
    # force on each vertex = -p A n / 3 summed over its faces; the resultant of a closed cavity is zero
    f = -g.reshape(-1, 3)
    area_normals = 0.5 * np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    lumped = np.zeros_like(x)
    for k in range(3):
        np.add.at(lumped, faces[:, k], -p * area_normals / 3)
    np.testing.assert_allclose(f, lumped, rtol=0, atol=1e-12 * np.abs(f).max())
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * np.abs(f).max() * len(x)


def _dome(radius, rings, sectors):
    """Upper hemisphere: pole + rings of ``sectors`` vertices (the last one on z = 0), outward faces."""
    theta = 0.5 * np.pi * np.arange(1, rings + 1) / rings
    phi = 2 * np.pi * np.arange(sectors) / sectors
    rho, z = radius * np.sin(theta), radius * np.cos(theta)
    z[-1] = 0.0
    x = np.vstack(
        [[0.0, 0.0, radius]]
        + [np.stack([r * np.cos(phi), r * np.sin(phi), np.full(sectors, h)], axis=1) for r, h in zip(rho, z)]
    )
    ring = [1 + k * sectors + np.arange(sectors) for k in range(rings)]
    faces = [np.stack([np.zeros(sectors, int), ring[0], np.roll(ring[0], -1)], axis=1)]
    for a, b in zip(ring[:-1], ring[1:]):
        faces += [
            np.stack([a, b, np.roll(b, -1)], axis=1),
            np.stack([a, np.roll(b, -1), np.roll(a, -1)], axis=1),
        ]
    faces = np.concatenate(faces)
    n = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    flip = np.einsum("ij,ij->i", n, x[faces].mean(axis=1)) < 0  # orient outward
    faces[flip] = faces[flip][:, ::-1]
    return x, faces


def test_open_cavity_closed_by_a_plane_through_the_reference_point():
    """The upper half of a cavity closed by the plane z = 0: V, grad V at the free vertices and the
    pressure resultant p * (disk area) e_z."""
    x, outward = _dome(0.02, rings=4, sectors=12)
    top = outward[:, ::-1].copy()  # the solid around the gas: normals into the gas
    p, c = 300.0, np.zeros(3)
    e, g, _, V, _ = _pressure_terms(x, top, p, c)
    # reference: close the dome with a fan of triangles on z = 0 and take trimesh's volume
    ring_ids = np.nonzero(np.abs(x[:, 2]) < 1e-12)[0]
    fan = np.stack([np.full(len(ring_ids), len(x)), np.roll(ring_ids, -1), ring_ids], axis=1)
    closed = trimesh.Trimesh(np.vstack([x, [0, 0, 0]]), np.vstack([outward, fan]), process=False)
    assert closed.is_watertight and closed.volume > 0
    assert V == pytest.approx(closed.volume, rel=1e-12)
    lower = x[:, 2] < -1e-9
    rim = np.abs(x[:, 2]) < 1e-12
    used = np.unique(top)
    inside = np.setdiff1d(used, np.nonzero(rim | lower)[0])
    # energy gradient at the free (non-rim) vertices by central differences
    h = 1e-7
    for v in inside[:6]:
        for k in range(3):
            xp, xm = x.copy(), x.copy()
            xp[v, k] += h
            xm[v, k] -= h
            fd = (_pressure_terms(xp, top, p, c)[0] - _pressure_terms(xm, top, p, c)[0]) / (2 * h)
            assert fd == pytest.approx(g[3 * v + k], rel=1e-6, abs=1e-9 * np.abs(g).max())
    # gas force on the dome: p times the vector area of the closing polygon (here ~ pi r^2 e_z)
    ring = x[rim]
    order = np.argsort(np.arctan2(ring[:, 1], ring[:, 0]))
    ring = ring[order]
    disk = 0.5 * np.cross(ring, np.roll(ring, -1, axis=0)).sum(axis=0)
    np.testing.assert_allclose(-g.reshape(-1, 3).sum(axis=0), p * disk, rtol=1e-9, atol=1e-12)


def _lame_solver(size, options=None, batch_size=1, **kwargs):
    mesh = thick_shell_octant_mesh(A, B_OUT, size)
    P = mesh.points
    faces = mesh.surface_faces
    inner = faces[np.all(np.abs(np.linalg.norm(P[faces], axis=2) - A) < 1e-7, axis=1)]
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        fem.Material(E, NU, 1000.0),
        batch_size=batch_size,
        fixed=np.abs(P) < 1e-9,  # symmetry planes x = 0, y = 0, z = 0
        pressure_surface=fem.PressureSurface(inner, reference_point=(0.0, 0.0, 0.0), **kwargs),
        options=options,
    )
    return mesh, solver


def _lame_radial(r, p):
    """Lame: u(r) = p a^3 / (E (b^3 - a^3)) [(1 - 2 nu) r + (1 + nu) b^3 / (2 r^2)]."""
    return p * A**3 / (E * (B_OUT**3 - A**3)) * ((1 - 2 * NU) * r + (1 + NU) * B_OUT**3 / (2 * r**2))


def _lame_errors(mesh, eq):
    P = mesh.points
    r = np.linalg.norm(P, axis=1)
    radial = P / r[:, None]
    u = eq.displacement[0]
    ur = np.einsum("ij,ij->i", u, radial)
    exact = _lame_radial(r, float(eq.gauge_pressure[0]))
    tangential = np.linalg.norm(u - ur[:, None] * radial, axis=1)
    out = {}
    for name, sel in (("inner", np.abs(r - A) < 1e-7), ("outer", np.abs(r - B_OUT) < 1e-7)):
        out[name] = (ur[sel].mean() / exact[sel].mean() - 1, np.abs(ur[sel] / exact[sel] - 1).max())
    return out, tangential.max() / ur.max()


def test_lame_thick_sphere_under_internal_pressure():
    p = 1e-3 * E  # linear regime
    errors = []
    for size in (0.0025, 0.0015):
        mesh, solver = _lame_solver(size)
        eq = solver.solve(pressure=fem.PressureLoad.fixed(p))
        eq.require_converged()
        assert eq.gauge_pressure[0] == p
        err, tangential = _lame_errors(mesh, eq)
        errors.append(abs(err["inner"][0]))
        assert tangential < 0.05
        # Clapeyron: strain energy = (1/2) p dV in the linear regime
        dv = eq.cavity_volume[0] - solver.rest_cavity_volume
        assert eq.strain_energy[0] == pytest.approx(0.5 * p * dv, rel=2e-3)
        # the symmetry planes carry the gas force: reactions + pressure forces balance
        total = eq.reaction_force[0].sum(axis=0) + eq.pressure_force[0].sum(axis=0)
        assert np.abs(total).max() < 1e-6 * np.abs(eq.pressure_force[0]).sum()
    assert errors[1] < errors[0]  # converges with refinement
    # the finer mesh (6-7 elements through the wall) is within 4 % of Lame's solution on both surfaces
    assert abs(err["inner"][0]) < 0.04 and abs(err["outer"][0]) < 0.04
    assert err["inner"][1] < 0.07 and err["outer"][1] < 0.07


def test_closed_isothermal_gas_reaches_boyles_law_equilibrium():
    """A closed cavity (plus an external rigid volume) filled with gas: p (V + V_h) = PV - P_atm (V + V_h)
    at equilibrium, the same state as a fixed-pressure solve at that p, and Newton (with the rank-one
    gas stiffness by Sherman-Morrison) converges in a few iterations."""
    vh = 2e-6  # m^3: stiff gas (dp/dV ~ P / V_total comparable to the shell's own pressure stiffness)
    mesh, solver = _lame_solver(0.0025, external_volume=vh)
    v0 = solver.rest_cavity_volume
    atm = fem.STANDARD_ATMOSPHERE
    pv = (atm + 300.0) * (v0 + vh)  # 300 Pa gauge at the rest volume
    eq = solver.solve(pressure=fem.PressureLoad.isothermal(pv))
    eq.require_converged()
    p, V = eq.gauge_pressure[0], eq.cavity_volume[0]
    assert p == pytest.approx(pv / (V + vh) - atm, rel=1e-12)
    assert 0 < p < 300.0  # the gas expanded and lost pressure
    assert eq.newton_iterations[0] <= 6
    _, fixed = _lame_solver(0.0025)
    eq_fixed = fixed.solve(pressure=fem.PressureLoad.fixed(p))
    eq_fixed.require_converged()
    np.testing.assert_allclose(
        eq.displacement, eq_fixed.displacement, atol=1e-6 * np.abs(eq.displacement).max()
    )
    # energy consistency: the linear shell stores (1/2) p dV, the gas did work int p dV > (1/2) p dV
    dv = V - v0
    gas_work = pv * np.log((V + vh) / (v0 + vh)) - atm * dv
    assert eq.strain_energy[0] == pytest.approx(0.5 * p * dv, rel=5e-3)
    assert gas_work == pytest.approx(0.5 * (300.0 + p) * dv, rel=1e-3)  # trapezoid: p linear in V


def _counted(fn, calls: list):
    def wrapped(*args, **kwargs):
        calls.append(1)
        return fn(*args, **kwargs)

    return wrapped


def test_gas_stiffness_solved_with_the_step_equals_a_second_solve():
    """The factorizing solvers (dense, banded) solve the gas stiffness's direction u as a second column of
    the Newton step's substitution; SuperLU ("direct") solves it afterwards with the same factors. Every
    Newton iterate agrees: the same iteration counts and equilibria to round-off, for three sealed
    capsules of different gas amounts in one batch (one of them open: no rank-one term)."""
    vh = 2e-6
    got, solves = {}, {}
    for name in ("direct", "dense", "banded"):
        mesh, solver = _lame_solver(
            0.0025, options=fem.SolverOptions(linear_solver=name), batch_size=3, external_volume=vh
        )
        atm, v0 = fem.STANDARD_ATMOSPHERE, solver.rest_cavity_volume
        # p = p0 + C / (V + V_h): sealed at 300 Pa, open to a regulated 150 Pa, sealed at 600 Pa
        laws = fem.PressureLoad(
            gauge_pressure=[-atm, 150.0, -atm], pv=[(atm + 300.0) * (v0 + vh), 0.0, (atm + 600.0) * (v0 + vh)]
        )
        count = []
        solver._linear_solve = _counted(solver._linear_solve, count)
        eq = solver.solve(pressure=laws)
        eq.require_converged()
        got[name], solves[name] = eq, len(count)
    ref = got["direct"]
    # one substitution per Newton pass with the second column, two with a second solve
    assert solves["dense"] == solves["banded"] and solves["direct"] > 1.5 * solves["dense"]
    for name in ("dense", "banded"):
        np.testing.assert_array_equal(got[name].newton_iterations, ref.newton_iterations, err_msg=name)
        scale = np.abs(ref.displacement).max()
        np.testing.assert_allclose(got[name].displacement, ref.displacement, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(got[name].gauge_pressure, ref.gauge_pressure, rtol=1e-9)
    assert 0 < ref.gauge_pressure[0] < 300.0 and ref.gauge_pressure[1] == 150.0
    assert ref.gauge_pressure[0] < ref.gauge_pressure[2] < 600.0


def test_batched_pressures_and_bad_input():
    mesh, _ = _lame_solver(0.0025)
    P = mesh.points
    faces = mesh.surface_faces
    inner = faces[np.all(np.abs(np.linalg.norm(P[faces], axis=2) - A) < 1e-7, axis=1)]
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        fem.Material(E, NU, 1000.0),
        batch_size=3,
        fixed=np.abs(P) < 1e-9,
        pressure_surface=fem.PressureSurface(inner),
    )
    eq = solver.solve(pressure=fem.PressureLoad.fixed([50.0, 100.0, -100.0]))
    eq.require_converged()
    d = eq.cavity_volume - solver.rest_cavity_volume
    assert d[1] == pytest.approx(2 * d[0], rel=5e-3) and d[2] == pytest.approx(
        -d[1], rel=5e-3
    )  # linear regime
    with pytest.raises(ValueError, match="shape"):
        solver.solve(pressure=fem.PressureLoad.fixed([1.0, 2.0]))
    with pytest.raises(ValueError, match="finite"):
        fem.PressureLoad.fixed(np.nan).arrays(1)
    with pytest.raises(ValueError, match=">= 0"):
        fem.PressureLoad(pv=-1.0).arrays(1)
    with pytest.raises(ValueError, match="pressure_surface"):
        fem.QuasiStaticSolver(mesh).solve(pressure=fem.PressureLoad.fixed(1.0))
    with pytest.raises(ValueError, match="into the gas"):
        fem.QuasiStaticSolver(mesh, pressure_surface=fem.PressureSurface(inner[:, ::-1]))
    with pytest.raises(ValueError, match="triangles of the mesh"):
        fem.QuasiStaticSolver(mesh, pressure_surface=fem.PressureSurface(np.array([[0, 1, 2]])))
    with pytest.raises(ValueError, match="reference_point"):
        fem.PressureSurface(inner, reference_point=(0.0, np.inf, 0.0))
