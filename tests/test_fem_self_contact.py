"""Self-contact of the object's surface (``SolverOptions.self_contact``, ``fem/self_contact.py``)."""

from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp
from fem_helpers import converged_states, two_unit_boxes

from defgraspnets import fem
from defgraspnets.fem import self_contact as sk

E = 1e4  # [Pa]
SIZE = (0.02, 0.02, 0.01)  # [m] each block
GAP = 5e-4  # [m] between the blocks at rest
SHIFT = (0.0013, 0.0007)  # [m] lateral offset of the upper block (no vertex on a vertex)


def two_blocks() -> tuple[fem.TetMesh, int]:
    """Two 20 x 20 x 10 mm blocks of one mesh, the second 0.5 mm above the first (and shifted sideways):
    parts of one object, far apart along its surface, near in space."""
    a = fem.TetMesh.box(size=SIZE, divisions=(4, 4, 2))
    n = a.num_vertices
    upper = a.points + [SHIFT[0], SHIFT[1], SIZE[2] + GAP]
    return fem.TetMesh(np.vstack([a.points, upper]), np.vstack([a.tets, a.tets + n])), n


def blocks_solver(self_contact: float, device: str = "cpu", **options):
    """The two blocks, the lower block's bottom and the upper block's top fixed (prescribed): the solver,
    a function press [m] -> the prescribed displacement moving the top down by it, and the lower block's
    vertex count."""
    mesh, n = two_blocks()
    z = mesh.points[:, 2]
    bottom = np.flatnonzero(z < 1e-9)
    top = np.flatnonzero(z > 2 * SIZE[2] + GAP - 1e-9)
    fixed = np.zeros((mesh.num_vertices, 3), dtype=bool)
    fixed[bottom] = True
    fixed[top] = True
    solver = fem.QuasiStaticSolver(
        mesh,
        [],
        fem.Material(E, 0.3, 1000.0, model="neohookean"),
        fixed=fixed,
        device=device,
        options=fem.SolverOptions(
            **{"linear_solver": "direct", **options}, self_contact=self_contact, contact_smoothing=1e-2
        ),
    )

    def pressed(press: float) -> np.ndarray:
        u = np.zeros((mesh.num_vertices, 3))
        u[top, 2] = -press
        return u

    return solver, pressed, n


def pressed_blocks(self_contact: float, press: float, device: str = "cpu", **options):
    """The upper block's top moved down by ``press`` [m]: the equilibrium, the solver and the lower block's
    vertex count."""
    solver, pressed, n = blocks_solver(self_contact, device, **options)
    eq = solver.solve(prescribed_displacement=pressed(press), initial_fraction=0.25)
    return eq, solver, n


def assert_blocks_balance(eq: fem.Equilibrium, force: np.ndarray, n: int) -> np.ndarray:
    """The pressed blocks' self-contact forces ``force`` (B, N, 3) are internal (sum to zero), carry a real
    load (a strain of a few %) onto the upper block (vertices from ``n``) and are what the lower block's
    support reacts: returns the force on the upper block [N]."""
    pushed = force[0, n:].sum(axis=0)
    assert pushed[2] > 0.1 * E * SIZE[0] * SIZE[1] * 0.01
    np.testing.assert_allclose(force[0].sum(axis=0), 0.0, atol=1e-9 * np.abs(force).max())
    lower_support = eq.reaction_force[0, eq.mesh.points[:, 2] < 1e-9].sum(axis=0)
    np.testing.assert_allclose(lower_support, pushed, rtol=1e-4, atol=1e-6 * pushed[2])
    return pushed


def test_self_contact_option_is_checked():
    for bad in (-1.0, float("nan"), float("inf"), "yes"):
        with pytest.raises(ValueError, match="self_contact"):
            fem.SolverOptions(self_contact=bad)
    assert fem.SolverOptions().self_contact == 0.0
    solver = fem.QuasiStaticSolver(fem.TetMesh.box(divisions=(1, 1, 1)), [], device="cpu")
    with pytest.raises(ValueError, match="self_contact"):
        solver.self_contact_forces()
    # the iterative solvers lack the couplings outside the block pattern: refused; "auto" picks an exact one
    box = fem.TetMesh.box(divisions=(2, 2, 2))
    for name in ("amg", "cg"):
        with pytest.raises(ValueError, match="self_contact needs linear_solver"):
            fem.QuasiStaticSolver(
                box, [], device="cpu", options=fem.SolverOptions(linear_solver=name, self_contact=1)
            )
    big = fem.TetMesh.box(divisions=(8, 8, 8))  # "auto" would pick AMG on the CPU
    assert fem.QuasiStaticSolver(big, [], device="cpu").linear_solver == "amg"
    on = fem.QuasiStaticSolver(big, [], device="cpu", options=fem.SolverOptions(self_contact=1.0))
    assert on.linear_solver == "direct"


def test_exclusion_is_along_the_surface():
    """A vertex never pairs with its own triangles or its 1-ring's, nor those within the exclusion radius
    along the surface; the other block, 0.5 mm away through space, is not excluded."""
    mesh, n = two_blocks()
    h = mesh.median_surface_edge_length
    start, excluded = sk.excluded_triangles(mesh, sk.SELF_CONTACT_EXCLUSION * h)
    faces, surface = mesh.surface_faces, mesh.surface_vertices
    for s in range(0, len(surface), 7):
        row = excluded[start[s] : start[s + 1]]
        assert np.all(np.diff(row) > 0)
        v = surface[s]
        incident = np.flatnonzero(np.any(faces == v, axis=1))
        assert np.all(np.isin(incident, row))
        own_block = faces[row] < n if v < n else faces[row] >= n
        assert np.all(own_block)  # nothing of the other block
        # the block's face farthest away along the surface is not excluded
        assert len(row) < np.sum(np.all(faces < n, axis=1) if v < n else np.all(faces >= n, axis=1))


def _pair_state(seed=0):
    """The blocks at rest, every vertex jiggled by ~20 um (tilted triangles), and one vertex of the upper
    block's bottom face pushed 0.1 mm into the lower block: one penetrating pair."""
    mesh, n = two_blocks()
    rng = np.random.default_rng(seed)
    x = mesh.points + rng.normal(scale=2e-5, size=mesh.points.shape)
    bottom_centre = [SHIFT[0] + 0.01, SHIFT[1] + 0.01, SIZE[2] + GAP]
    v = n + int(np.argmin(np.linalg.norm(mesh.points[n:] - bottom_centre, axis=1)))
    x[v, 2] = SIZE[2] - 1e-4
    return mesh, x, v


def _contact_for(mesh, x, kappa=1000.0, zeta=1e-2):
    from defgraspnets.fem.system import BlockPattern

    pattern = BlockPattern.build(mesh, 0)
    sc = sk.SelfContact(mesh, pattern, 1, mesh.median_surface_edge_length, "cpu")
    pos = wp.array(x, dtype=wp.vec3d, device="cpu")
    sc.update_pairs(pos)
    return sc, pattern


def _energy(sc, x, youngs, kappa, zeta):
    pos = wp.array(x, dtype=wp.vec3d, device="cpu")
    e = wp.zeros(1, dtype=wp.float64, device="cpu")
    sc.add_energy(pos, 1, youngs, kappa, zeta, wp.array([1], dtype=wp.int32, device="cpu"), e)
    return float(e.numpy()[0])


def _assert_fd_gradient(sc, x, g, touched, youngs, kappa, zeta, eps: float = 1e-9) -> None:
    """The self-contact gradient ``g`` at ``x`` matches central differences of the energy at every
    component of the ``touched`` vertices."""
    for u in touched:
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[u, c] += eps
            xm[u, c] -= eps
            fd = (_energy(sc, xp, youngs, kappa, zeta) - _energy(sc, xm, youngs, kappa, zeta)) / (2 * eps)
            assert fd == pytest.approx(g[u, c], rel=1e-5, abs=1e-6 * np.abs(g).max())


def test_gradient_and_hessian_match_finite_differences():
    """The energy's exact gradient (the vertex and the triangle's vertices) against central differences with
    the pair fixed; the Hessian's blocks (in the pattern, and the vertex-triangle couplings outside it) the
    Gauss-Newton k_g c_a c_b n n^T, c = (-1, w): symmetric, PSD together, and their normal parts the finite
    differences of the gradient."""
    mesh, x, v = _pair_state()
    sc, pattern = _contact_for(mesh, x)
    N = mesh.num_vertices
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    kappa, zeta = 1000.0, 1e-2
    active = wp.array([1], dtype=wp.int32, device="cpu")
    free = wp.array(np.ones((N, 3)), dtype=wp.vec3d, device="cpu")

    def assemble(xs):
        grad = wp.zeros(N, dtype=wp.vec3d, device="cpu")
        hess = wp.zeros(pattern.nnz, dtype=wp.mat33d, device="cpu")
        pos = wp.array(xs, dtype=wp.vec3d, device="cpu")
        sc.add_gradient_hessian(pos, youngs, kappa, zeta, N, pattern.nnz, active, free, grad, hess)
        return grad.numpy(), hess.numpy()

    g, H = assemble(x)
    K = sc.arrays.candidates
    s_v = int(np.searchsorted(mesh.surface_vertices, v))
    candidates = sc.arrays.pair.numpy()[s_v * K : (s_v + 1) * K]
    assert np.sum(candidates >= 0) > 1  # the nearest wins among several
    rows, cols, coupling = (a.numpy() for a in sc.coupling)
    f = int(np.flatnonzero(np.all(mesh.surface_faces == cols[3 * s_v : 3 * s_v + 3], axis=1))[0])
    assert f in candidates and np.all(mesh.surface_faces[f] < v)  # a triangle of the lower block
    touched = np.flatnonzero(np.linalg.norm(g, axis=1) > 0)
    np.testing.assert_array_equal(touched, np.sort(np.r_[mesh.surface_faces[f], v]))
    assert _energy(sc, x, youngs, kappa, zeta) > 0
    np.testing.assert_allclose(g.sum(axis=0), 0.0, atol=1e-12 * np.abs(g).max())  # internal forces
    _assert_fd_gradient(sc, x, g, touched, youngs, kappa, zeta)
    eps = 1e-9
    for u in touched:
        blk = H[pattern.vertex_diag[u]]
        assert np.abs(blk).max() > 0
        np.testing.assert_allclose(blk, blk.T, atol=1e-12 * np.abs(blk).max())
        assert np.linalg.eigvalsh(blk).min() > -1e-9 * np.abs(blk).max()
    fd = np.zeros((3, 3))
    for c in range(3):
        xp, xm = x.copy(), x.copy()
        xp[v, c] += eps
        xm[v, c] -= eps
        fd[:, c] = (assemble(xp)[0][v] - assemble(xm)[0][v]) / (2 * eps)
    n = -g[v] / np.linalg.norm(g[v])  # the push-out direction
    assert n[2] > 0.99
    blk = H[pattern.vertex_diag[v]]
    np.testing.assert_allclose(n @ blk @ n, n @ fd @ n, rtol=1e-5)
    np.testing.assert_allclose(blk, (n @ blk @ n) * np.outer(n, n), atol=1e-12 * np.abs(blk).max())
    kg = n @ blk @ n
    # the couplings (v, corner i): -k_g w_i n n^T, the normal part of the corner's gradient's change with x_v
    rows, cols, coupling = (a.numpy() for a in sc.coupling)  # of the last assembly (at x)
    assemble(x)
    rows, cols, coupling = (a.numpy() for a in sc.coupling)
    corners = mesh.surface_faces[f]
    slots = 3 * s_v + np.arange(3)
    np.testing.assert_array_equal(rows[slots], v)
    np.testing.assert_array_equal(cols[slots], corners)
    w = np.array([-(n @ coupling[k] @ n) / kg for k in slots])
    assert np.all(w >= 0) and w.sum() == pytest.approx(1.0)
    for k, u in zip(slots, corners):
        np.testing.assert_allclose(coupling[k], -kg * w[k - slots[0]] * np.outer(n, n), atol=1e-12 * kg)
        fd_u = np.array(
            [(assemble(x + e)[0][u] - assemble(x - e)[0][u]) @ n / (2 * eps) for e in eps_along(v, n, N)]
        )
        assert fd_u[0] == pytest.approx(n @ coupling[k] @ n, rel=1e-5)
    # the whole 12 x 12 Gauss-Newton Hessian of the pair: k_g c c^T (x) n n^T, PSD
    ids = np.r_[v, corners]
    full = np.zeros((12, 12))
    for a, ra in enumerate(ids):
        for b, rb in enumerate(ids):
            if a == 0 and b == 0:
                block = blk
            elif a == 0 or b == 0:
                block = coupling[slots[max(a, b) - 1]]
            else:
                block = H[pattern.block_index(np.array([ra]), np.array([rb]))[0]]
            full[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] = block
    c = np.r_[-1.0, w]
    np.testing.assert_allclose(full, kg * np.kron(np.outer(c, c), np.outer(n, n)), atol=1e-9 * kg)


def eps_along(v, n, N, eps=1e-9):
    """The displacement of vertex v by eps along n, as an (N, 3) array in a one-element list."""
    e = np.zeros((N, 3))
    e[v] = eps * n
    return [e]


def test_off_is_bit_for_bit_the_engine_without_it():
    """self_contact = 0 (default) reproduces a frictional pad squeeze bit for bit."""
    from fem_helpers import assert_same_squeeze, pad_squeeze_solver

    a = pad_squeeze_solver([0.0, 0.003], linear_solver="direct").solve({"grip": 2.0})
    b = pad_squeeze_solver([0.0, 0.003], linear_solver="direct", self_contact=0.0).solve({"grip": 2.0})
    assert_same_squeeze(a, b)


def test_a_pressed_block_passes_through_the_other_without_and_rests_on_it_with_self_contact():
    """The upper block pressed 2 mm down onto the lower one (0.5 mm apart): without self-contact it passes
    into it (its surface vertices inside the lower block's tets); with it the blocks meet, no vertex is
    inside, the penetration stays within the penalty's tolerance, and the force the press needs is what
    the self-contact transmits, which the lower block's support carries."""
    press = 2e-3
    off, _, _ = pressed_blocks(0.0, press)
    assert off.status[0] == fem.SolveStatus.CONVERGED
    mesh = off.mesh
    depth = sk.self_contact_depth(mesh)  # what self-contact holds (a quarter of the 5 mm edges)
    assert len(mesh.surface_vertices_inside(mesh.points + off.displacement[0], depth=depth)) > 10
    assert np.abs(off.reaction_force[0]).max() < 1e-9  # nothing resists a rigid move down

    on, solver, n = pressed_blocks(1.0, press)
    assert on.status[0] == fem.SolveStatus.CONVERGED
    x = mesh.points + on.displacement[0]
    assert mesh.surface_vertices_inside(x).size > 0  # the penalty's penetration, strictly inside
    assert mesh.surface_vertices_inside(x, depth=depth).size == 0
    force, pen = solver.self_contact_forces()
    pushed = assert_blocks_balance(on, force, n)
    upper_support = on.reaction_force[0, mesh.points[:, 2] > 2 * SIZE[2] + GAP - 1e-9].sum(axis=0)
    np.testing.assert_allclose(upper_support, -pushed, rtol=1e-4, atol=1e-6 * pushed[2])
    # penetration tolerance: p h / (kappa E) + zeta h / 2 with the mean pressure p (and a margin for the
    # uneven pressure of the pressed faces)
    h = solver.contact_length
    p = pushed[2] / (SIZE[0] * SIZE[1])
    tolerance = p * h / (1000.0 * E) + 1e-2 * h / 2
    assert 0 < pen.max() < 3 * tolerance
    # the dense solver adds the same couplings (its own scatter): the same equilibrium
    dense, _, _ = pressed_blocks(1.0, press, linear_solver="dense")
    assert dense.status[0] == fem.SolveStatus.CONVERGED
    np.testing.assert_allclose(dense.displacement, on.displacement, atol=1e-9)


def press_path(presses, **options) -> fem.Equilibrium:
    """The blocks pressed by each of ``presses`` [m] in turn (one solve each, every one converged): the
    last equilibrium."""
    solver, pressed, _ = blocks_solver(1.0, **options)
    for press in presses:
        eq = solver.solve(prescribed_displacement=pressed(press))
        eq.require_converged()
    return eq


def test_an_increment_does_not_start_from_a_prediction_that_runs_the_object_through_itself(monkeypatch):
    """The upper block pressed 0.45 mm (0.05 mm short of touching), then 1.35 mm: the predictor would
    extrapolate the first press twice over, 0.85 mm into the lower block, deeper than
    ``PREDICTED_SELF_PENETRATION`` (half) of the 1.25 mm self-contact depth, so the increment starts from the
    last converged state and the press ends where a fine path of 0.1 mm presses ends (to 1e-9 m). Started
    from the extrapolation (the guard off), the same press comes to rest in another state, 0.36 mm away:
    the surface went through itself (measured on the 2-core CPU)."""
    from defgraspnets.fem import solver as solver_module

    assert solver_module.PREDICTED_SELF_PENETRATION == 0.5

    assert blocks_solver(1.0)[0]._self_contact.depth == pytest.approx(1.25e-3)
    fine = press_path(np.linspace(0.45e-3, 1.35e-3, 10))
    guarded = press_path([0.45e-3, 1.35e-3])
    np.testing.assert_allclose(guarded.displacement, fine.displacement, rtol=0, atol=1e-9)
    monkeypatch.setattr(solver_module, "PREDICTED_SELF_PENETRATION", np.inf)
    unguarded = press_path([0.45e-3, 1.35e-3])
    assert np.abs(unguarded.displacement - fine.displacement).max() > 1e-4  # measured 3.6e-4 m


def test_the_data_path_allows_the_penalty_depth_and_still_fails_a_pass_through():
    """With self-contact the data path's self-intersection check (STATUS_SELF_INTERSECTING) allows surface
    vertices within the pairs' depth cap of another part of the surface (held there by the penalty), and
    still fails an object whose parts have passed through each other; without it (depth 0) both fail."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from defgraspnets.grasp import datagen
    from defgraspnets.grasp.squeeze import squeeze_solver_options

    two, n = two_unit_boxes()
    depth = sk.self_contact_depth(two)
    assert depth == pytest.approx(sk.SELF_CONTACT_DEPTH * 0.5)
    shallow, through = np.zeros((2 * n, 3)), np.zeros((2 * n, 3))
    shallow[n:] -= [1.0 + 0.4 * depth, 0.13, 0.07]  # pressed 0.4 of the cap into the first box
    through[n:] -= [1.7, 0.13, 0.07]
    assert two.surface_vertices_inside(two.points + shallow).size > 0
    assert two.surface_vertices_inside(two.points + shallow, depth=depth).size == 0
    assert two.surface_vertices_inside(two.points + through, depth=depth).size > 4

    for options, expected in ((None, 7), (squeeze_solver_options(self_contact=1.0), 0)):
        ramps = SimpleNamespace(mesh=two, options=options)
        out = datagen._empty_ramps(2, 1, 2 * n)
        rows = np.array([0, 1])
        states = converged_states(two, [shallow, through])
        datagen._record_steps(out, rows, np.array([0, 0]), states, True, 0, datagen._contact_depth(ramps))
        assert out["status"].tolist() == [expected, datagen.STATUS_SELF_INTERSECTING]
    # the datagen key: null keeps the squeeze default (off); a bad value names the key
    config = Path(__file__).resolve().parents[1] / "configs/datagen/grasps.yaml"
    assert OmegaConf.load(config).self_contact is None
    assert squeeze_solver_options(self_contact=None).self_contact == 0.0
    with pytest.raises(ValueError, match="self_contact"):
        squeeze_solver_options(self_contact=-1.0)


@pytest.mark.parametrize("name", ["annulus_ro45_ri35_h20_ftetwild.vtu", "cuboid_60x40x20.vtu"])
def test_no_self_contact_at_rest_on_data_path_meshes(name):
    """At rest nothing touches itself: an fTetWild ring (a 10 mm wall) and a slab of the data path have no
    penetrating pair (no false contact of a vertex with its own surface or across a wall)."""
    mesh = fem.TetMesh.load(Path(__file__).parent / "data" / name)
    solver = fem.QuasiStaticSolver(mesh, [], device="cpu", options=fem.SolverOptions(self_contact=1.0))
    force, pen = solver.self_contact_forces()
    assert pen.shape == (1, len(mesh.surface_vertices))
    assert not pen.any() and not force.any()


REFERENCE = Path(__file__).parent / "data" / "self_contact_cpu_reference.npz"
#: the same press with model "barrier"
BARRIER_REFERENCE = Path(__file__).parent / "data" / "self_contact_barrier_cpu_reference.npz"


def _reference_press(device: str, linear_solver: str, model: str = "prism"):
    eq, solver, _ = pressed_blocks(
        1.0, 2e-3, device=device, linear_solver=linear_solver, self_contact_model=model
    )
    eq.require_converged()
    force, _ = solver.self_contact_forces()
    return eq.displacement, force


def write_cpu_reference():
    """Regenerate tests/data/self_contact_cpu_reference.npz and ..._barrier_... (the CPU's "direct"
    answers)."""
    for path, model in ((REFERENCE, "prism"), (BARRIER_REFERENCE, "barrier")):
        displacement, force = _reference_press("cpu", "direct", model)
        np.savez_compressed(path, displacement=displacement, force=force)


def _assert_matches_reference(displacement, force, path=REFERENCE):
    ref = np.load(path)
    np.testing.assert_allclose(displacement, ref["displacement"], atol=1e-9)
    np.testing.assert_allclose(force, ref["force"], atol=1e-6 * np.abs(ref["force"]).max())


@pytest.mark.parametrize("model", ["prism", "barrier"])
def test_cpu_matches_stored_reference(model):
    """The stored CPU answer that the CUDA test compares with is the current CPU solver's answer (the GPU
    machines have no CPU code generator for Warp, so both cannot run in one process there)."""
    path = BARRIER_REFERENCE if model == "barrier" else REFERENCE
    _assert_matches_reference(*_reference_press("cpu", "direct", model), path=path)


@pytest.mark.parametrize("linear_solver", ["banded", "dense_banded"])
def test_banded_solver_solves_with_the_couplings(linear_solver):
    """The banded solver factors the block pattern alone and adds the couplings outside it by a low-rank
    update of its solutions: every coupled solve is exact for the whole Hessian (pattern and couplings), and
    the press reaches the direct solver's equilibrium (which factors the couplings in) in as many Newton
    iterations (without the couplings: 4400 for the first contact increment)."""
    from defgraspnets.fem import system
    from defgraspnets.fem.profiling import time_linear_solves

    residuals = []
    update = system.BatchedSystem._solve_coupled

    def checked(self, ids, x, coupling):
        out = update(self, ids, x, coupling)
        fresh = [k for k, p in enumerate(ids) if self.fresh_factor[p]]  # reused factors: chord steps
        if not fresh:
            return out
        index = torch.as_tensor([ids[k] for k in fresh])
        B = self.batch_size
        b = wp.to_torch(self.rhs).reshape(B, -1)[index]  # the Newton step's right-hand side
        values = wp.to_torch(self.values)[: B * self.pattern.nnz].reshape(B, -1)
        x = (out if out.dim() == 2 else out[..., 0])[fresh]
        product = self._coupled_product(values, index, coupling, x)
        residuals.append(float(((product - b).norm(dim=1) / b.norm(dim=1)).max()))
        return out

    system.BatchedSystem._solve_coupled = checked
    try:
        # dense_banded: banded from one problem to factor (else this one problem would go to dense)
        extra = {"banded_min_problems": 1} if linear_solver == "dense_banded" else {}
        eq, solver, _ = pressed_blocks(1.0, 2e-3, linear_solver=linear_solver, **extra)
    finally:
        system.BatchedSystem._solve_coupled = update
    direct, _, _ = pressed_blocks(1.0, 2e-3)
    assert eq.status[0] == direct.status[0] == fem.SolveStatus.CONVERGED
    assert residuals and max(residuals) < 1e-9
    assert abs(int(eq.newton_iterations[0]) - int(direct.newton_iterations[0])) <= 2
    np.testing.assert_allclose(eq.displacement, direct.displacement, atol=1e-9)
    # at the pressed state (pairs active): a random right-hand side solved with fresh factors by the dense
    # solver (couplings factored in) and the banded one (updated) alike, each residual of the whole matrix
    # at round-off
    assert solver.self_contact_forces()[1].max() > 0
    timed = time_linear_solves(solver, methods=("dense", "banded"), counts=(1,), repeats=1)
    assert timed["max_relative_difference"] < 1e-10
    assert max(timed["methods"][m][0]["residual"] for m in ("dense", "banded")) < 1e-12


def test_low_rank_update_of_a_padded_batch_equals_each_problem_alone():
    """The CUDA path's batch, run on the CPU: two problems whose pairs touch different numbers of unknowns
    (the pressed blocks' pairs, and half of them) padded to the larger count; each problem's update equals
    its update alone and solves its whole matrix (pattern and its own couplings)."""
    _, solver, _ = pressed_blocks(1.0, 2e-3, linear_solver="banded")
    sysm = solver.system
    solver._assemble(solver._active_array(np.ones(1, dtype=bool)))  # the pressed state, pairs active
    rng = np.random.default_rng(3)
    sysm.rhs.assign(rng.normal(size=(sysm.pattern.rows_per_problem, 3)) * solver._free.numpy().reshape(-1, 3))
    sysm.forget_factors()
    sysm.solve_banded(residual=False)  # stores the banded factor of the pattern alone
    rows, cols, entries = sysm._coupling_entries()
    half = entries.clone()
    nonzero = torch.nonzero(half[0]).flatten()
    half[0, nonzero[len(nonzero) // 2 :]] = 0.0
    R, C, V = rows.repeat(2, 1), cols.repeat(2, 1), torch.cat([entries, half])
    counts = [len(torch.unique(torch.cat([R[j][V[j] != 0], C[j][V[j] != 0]]))) for j in range(2)]
    assert counts[0] > counts[1] > 0  # the second problem is padded
    b = wp.to_torch(sysm.rhs).reshape(1, -1)
    x0 = sysm._dense_substitute([0], b).unsqueeze(2)
    batched = sysm._low_rank_update([0, 0], x0.repeat(2, 1, 1), R, C, V)
    values = wp.to_torch(sysm.values)[: sysm.pattern.nnz].reshape(1, -1)
    for j in range(2):
        alone = sysm._low_rank_update([0], x0, R[j : j + 1], C[j : j + 1], V[j : j + 1])
        np.testing.assert_allclose(
            batched[j].numpy(), alone[0].numpy(), rtol=0, atol=1e-12 * alone.abs().max()
        )
        own = (R[j : j + 1], C[j : j + 1], V[j : j + 1])
        residual = sysm._coupled_product(values, torch.tensor([0]), own, batched[j, :, 0][None]) - b
        assert float(residual.norm() / b.norm()) < 1e-12
    assert float((batched[0] - batched[1]).abs().max()) > 1e-6 * float(batched.abs().max())  # other couplings


@pytest.mark.gpu
def test_cuda_banded_with_couplings_matches_cpu():
    """The banded solver's low-rank coupled update, batched on CUDA, gives the CPU's equilibrium."""
    _assert_matches_reference(*_reference_press("cuda", "banded"))


@pytest.mark.gpu
def test_cuda_dense_with_couplings_matches_cpu():
    """The self-contact kernels on CUDA and the dense solver's couplings scattered on the GPU give the CPU's
    equilibrium (session 42, one H200: within 2e-11 m and 7e-10 N)."""
    _assert_matches_reference(*_reference_press("cuda", "dense"))


@pytest.mark.gpu
@pytest.mark.parametrize("linear_solver", ["dense", "banded"])
def test_cuda_barrier_matches_cpu(linear_solver):
    """The barrier's kernels (pairs, energies, gradients, couplings, step bounds) on CUDA give the CPU's
    equilibrium of the pressed blocks."""
    displacement, force = _reference_press("cuda", linear_solver, "barrier")
    _assert_matches_reference(displacement, force, path=BARRIER_REFERENCE)


# ---------------------------------------------------------------- the "feature" model
CREASE_X = 0.01  # [m] the valley's crease line (a column of the lower block's vertices)
PROBE_Y = 0.0075  # [m] the probe's sweep, between two rows of vertices
PROBE_DEPTH = 4e-4  # [m] below the crease line


def crease_probe(slope: float = 0.3):
    """The lower 20 x 20 x 10 mm block with its top bent into a valley (z + slope |x - 10 mm| at the top,
    a crease along a column of vertices: a concave crease seen from above) and a separate 1 mm tet above
    it, whose lowest vertex is the probe: (mesh, probe vertex, deformed positions)."""
    a = fem.TetMesh.box(size=SIZE, divisions=(4, 4, 2))
    n = a.num_vertices
    tip = np.array([CREASE_X, PROBE_Y, SIZE[2] + 3e-3])
    tet = tip + 1e-3 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [-0.5, 0.87, 1.0], [-0.5, -0.87, 1.0]])
    mesh = fem.TetMesh(np.vstack([a.points, tet]), np.vstack([a.tets, [[n, n + 1, n + 2, n + 3]]]))
    x = mesh.points.copy()
    x[:n, 2] += x[:n, 2] / SIZE[2] * slope * np.abs(x[:n, 0] - CREASE_X)
    return mesh, n, x


def _probe_along(model, offsets):
    """The self-contact energy and the probe's penetration with the probe PROBE_DEPTH below the crease
    line, moved by each of ``offsets`` [m] across it (the energy with the pairs found once, in the middle;
    the penetration with the pairs of each state)."""
    from defgraspnets.fem.system import BlockPattern

    mesh, v, x = crease_probe()
    x[v] = [CREASE_X, PROBE_Y, SIZE[2] - PROBE_DEPTH]
    h = mesh.median_surface_edge_length
    sc = sk.SelfContact(mesh, BlockPattern.build(mesh, 0), 1, h, "cpu", model)
    sc.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    s_v = int(np.searchsorted(mesh.surface_vertices, v))
    probe = sk.SelfContact(mesh, BlockPattern.build(mesh, 0), 1, h, "cpu", model)
    energy, pen = [], []
    for dx in offsets:
        y = x.copy()
        y[v, 0] += dx
        energy.append(_energy(sc, y, youngs, 1000.0, 1e-2))
        pen.append(probe.forces(wp.array(y, dtype=wp.vec3d, device="cpu"), youngs, 1000.0, 1e-2)[1][0, s_v])
    return np.array(energy), np.array(pen)


def test_prism_rule_jumps_at_a_concave_crease_and_the_feature_model_is_continuous():
    """A vertex 0.4 mm below a valley's crease, moved across it: the prism rule releases it in the wedge
    between the two faces' prisms (energy 0 there, the full penalty a step away: a jump that does not shrink
    with the step); the feature model holds it all along at its distance from the crease, its energy's steps
    shrink with the step, and outside the wedge it is the prism rule."""
    coarse = np.linspace(-1e-3, 1e-3, 201)
    fine = np.linspace(-1e-3, 1e-3, 2001)
    prism, prism_pen = _probe_along("prism", coarse)
    assert prism.max() > 0 and np.any(prism == 0) and np.any(prism_pen == 0)  # released in the wedge
    jump = np.abs(np.diff(prism)).max()
    assert jump > 0.3 * prism.max()
    assert np.abs(np.diff(_probe_along("prism", fine)[0])).max() > 0.9 * jump  # the same at 10x finer steps

    feature, pen = _probe_along("feature", coarse)
    assert feature.min() > 0.2 * feature.max()  # held everywhere below the surface
    step = np.abs(np.diff(feature)).max()
    assert step < 0.05 * feature.max()
    assert np.abs(np.diff(_probe_along("feature", fine)[0])).max() < 0.2 * step  # continuous
    outside = prism > 0
    np.testing.assert_allclose(feature[outside], prism[outside], rtol=1e-12)
    np.testing.assert_allclose(pen[outside], prism_pen[outside], rtol=1e-12)
    # in the wedge: the distance from the crease line (x = 10 mm, z = 10 mm)
    wedge = ~outside
    np.testing.assert_allclose(pen[wedge], np.hypot(coarse[wedge], PROBE_DEPTH), rtol=1e-9)


def _assemble(sc, pattern, x):
    N = len(x)
    grad = wp.zeros(N, dtype=wp.vec3d, device="cpu")
    hess = wp.zeros(pattern.nnz, dtype=wp.mat33d, device="cpu")
    sc.add_gradient_hessian(
        wp.array(x, dtype=wp.vec3d, device="cpu"),
        wp.array([E], dtype=wp.float64, device="cpu"),
        1000.0,
        1e-2,
        N,
        pattern.nnz,
        wp.array([1], dtype=wp.int32, device="cpu"),
        wp.array(np.ones((N, 3)), dtype=wp.vec3d, device="cpu"),
        grad,
        hess,
    )
    return grad.numpy(), hess.numpy()


@pytest.mark.parametrize("dx", [-2.5e-4, -6e-5, 0.0, 3e-4, 1.1e-3])
def test_feature_gradient_matches_finite_differences(dx):
    """The feature model's exact gradient (the probe and the acting triangle's vertices: the closest point
    on the crease edge in the wedge, in a face's interior outside it) against central differences; its
    forces sum to zero; the Gauss-Newton Hessian, pattern blocks and couplings, symmetric PSD."""
    from defgraspnets.fem.system import BlockPattern

    mesh, v, x = crease_probe()
    x[v] = [CREASE_X + dx, PROBE_Y, SIZE[2] - PROBE_DEPTH]
    pattern = BlockPattern.build(mesh, 0)
    sc = sk.SelfContact(mesh, pattern, 1, mesh.median_surface_edge_length, "cpu", model="feature")
    sc.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    g, H = _assemble(sc, pattern, x)
    touched = np.flatnonzero(np.linalg.norm(g, axis=1) > 0)
    assert v in touched and len(touched) >= 3
    np.testing.assert_allclose(g.sum(axis=0), 0.0, atol=1e-12 * np.abs(g).max())
    assert g[v, 2] < 0  # pushed up, out of the valley
    _assert_fd_gradient(sc, x, g, touched, youngs, 1000.0, 1e-2)
    rows, cols, coupling = (a.numpy() for a in sc.coupling)
    index = {u: k for k, u in enumerate(touched)}
    full = np.zeros((3 * len(touched), 3 * len(touched)))
    for a_ in touched:
        for b_ in touched:
            k = pattern.block_index(np.array([a_]), np.array([b_]))[0]
            if k >= 0:
                full[3 * index[a_] : 3 * index[a_] + 3, 3 * index[b_] : 3 * index[b_] + 3] += H[k]
    for r, c, blk in zip(rows, cols, coupling):
        if np.abs(blk).max() > 0:
            full[3 * index[r] : 3 * index[r] + 3, 3 * index[c] : 3 * index[c] + 3] += blk
            full[3 * index[c] : 3 * index[c] + 3, 3 * index[r] : 3 * index[r] + 3] += blk.T
    assert np.abs(full).max() > 0
    np.testing.assert_allclose(full, full.T, atol=1e-12 * np.abs(full).max())
    assert np.linalg.eigvalsh(full).min() > -1e-9 * np.abs(full).max()


def test_adjacent_triangles():
    """Each surface edge's two triangles are each other's neighbours across it, on a closed surface."""
    mesh, _, _ = crease_probe()
    faces = mesh.surface_faces
    adj = sk.adjacent_triangles(faces)
    assert adj.shape == faces.shape and np.all(adj >= 0)
    for f in range(0, len(faces), 5):
        for k in range(3):
            g = adj[f, k]
            edge = {faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]}
            assert g != f and edge <= set(faces[g])
            assert f in adj[g]


def test_feature_model_pressed_blocks_converge_and_balance():
    """The two pressed blocks with the feature model: converged, nothing pressed deeper than the cap, the
    penetration within the penalty's tolerance, the self-contact forces summing to zero and carried by the
    lower block's support, the press force within a few per cent of the prism rule's; "dense" the same
    equilibrium. A bad model name is refused."""
    with pytest.raises(ValueError, match="self_contact_model"):
        fem.SolverOptions(self_contact=1.0, self_contact_model="ipc")
    press = 2e-3
    on, solver, n = pressed_blocks(1.0, press, self_contact_model="feature")
    assert on.status[0] == fem.SolveStatus.CONVERGED
    mesh = on.mesh
    x = mesh.points + on.displacement[0]
    assert mesh.surface_vertices_inside(x, depth=sk.self_contact_depth(mesh)).size == 0
    force, pen = solver.self_contact_forces()
    pushed = assert_blocks_balance(on, force, n)
    h = solver.contact_length
    tolerance = pushed[2] / (SIZE[0] * SIZE[1]) * h / (1000.0 * E) + 1e-2 * h / 2
    assert 0 < pen.max() < 3 * tolerance
    _, prism_solver, _ = pressed_blocks(1.0, press)
    prism_pushed = prism_solver.self_contact_forces()[0][0, n:].sum(axis=0)
    assert pushed[2] == pytest.approx(prism_pushed[2], rel=0.05)
    dense, _, _ = pressed_blocks(1.0, press, linear_solver="dense", self_contact_model="feature")
    assert dense.status[0] == fem.SolveStatus.CONVERGED
    np.testing.assert_allclose(dense.displacement, on.displacement, atol=1e-9)


if __name__ == "__main__":
    write_cpu_reference()


# ---------------------------------------------------------------- the "barrier" model
def _barrier_state(drop: float = 3.5e-4, twist: float = 0.05, seed: int = 1, aligned: bool = False):
    """The blocks with the upper block lowered by ``drop`` (0.15 mm apart: inside the barrier's 0.25 mm
    activation distance), turned by ``twist`` rad about the vertical (its edges cross the lower block's),
    every vertex jiggled by ~10 um; ``aligned``: first moved back over the lower block, vertex above vertex
    (edges above edges): (mesh, upper block's first vertex, positions, SelfContact, pattern)."""
    from defgraspnets.fem.system import BlockPattern

    mesh, n = two_blocks()
    x = mesh.points.copy()
    if aligned:
        x[n:, :2] -= SHIFT
    c = x[n:].mean(axis=0)
    cos, sin = np.cos(twist), np.sin(twist)
    d = x[n:] - c
    x[n:, 0] = c[0] + cos * d[:, 0] - sin * d[:, 1]
    x[n:, 1] = c[1] + sin * d[:, 0] + cos * d[:, 1]
    x[n:, 2] -= drop
    x += np.random.default_rng(seed).normal(scale=1e-5, size=x.shape)
    pattern = BlockPattern.build(mesh, 0)
    sc = sk.SelfContact(mesh, pattern, 1, mesh.median_surface_edge_length, "cpu", model="barrier")
    sc.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))
    return mesh, n, x, sc, pattern


def _active_pairs(sc, x):
    """Numbers of vertex-triangle and edge-edge candidate pairs closer than the activation distance at x."""
    from defgraspnets.fem.self_contact import SelfContactArrays  # noqa: F401 (the arrays' layout)

    a = sc.arrays
    S, K, E, KE = sc.num_surface, a.candidates, sc.num_edges, a.edge_candidates
    faces, surface, edges = a.faces.numpy(), a.surface.numpy(), a.edges.numpy()
    vt = 0
    for s, f in zip(*np.nonzero(a.pair.numpy()[: S * K].reshape(S, K) >= 0)):
        tri = x[faces[a.pair.numpy()[s * K + f]]]
        vt += _point_triangle_distance(x[surface[s]], tri) < sc.gap
    ee = 0
    pairs = a.edge_pair.numpy()[: E * KE].reshape(E, KE)
    for e, k in zip(*np.nonzero(pairs >= 0)):
        p, q = x[surface[edges[e]]], x[surface[edges[pairs[e, k]]]]
        ee += _segment_distance(p, q) < sc.gap
    return vt, ee


def _point_segment_distance(p, a, b):
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(a + t * (b - a) - p)


def _point_triangle_distance(p, tri):
    """Reference: the plane's distance where p projects inside the triangle, else the nearest edge's."""
    a, b, c = tri
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    q = p - ((p - a) @ n) * n
    inside = all(np.cross(v1 - v0, q - v0) @ n >= 0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return abs((p - a) @ n)
    return min(_point_segment_distance(p, *e) for e in ((a, b), (b, c), (c, a)))


def _segment_distance(p, q):
    """Reference: the interior critical point of |p(s) - q(t)|^2 where it lies in [0, 1]^2, else the
    least distance of an endpoint to the other segment."""
    d1, d2, r = p[1] - p[0], q[1] - q[0], p[0] - q[0]
    A = np.array([[d1 @ d1, -d1 @ d2], [-d1 @ d2, d2 @ d2]])
    candidates = [
        _point_segment_distance(p[0], *q),
        _point_segment_distance(p[1], *q),
        _point_segment_distance(q[0], *p),
        _point_segment_distance(q[1], *p),
    ]
    if abs(np.linalg.det(A)) > 1e-12 * A[0, 0] * A[1, 1]:
        s, t = np.linalg.solve(A, [-(d1 @ r), d2 @ r])
        if 0 <= s <= 1 and 0 <= t <= 1:
            candidates.append(np.linalg.norm(p[0] + s * d1 - q[0] - t * d2))
    return min(candidates)


def test_barrier_pairs_are_the_near_vertex_triangle_and_edge_edge_pairs():
    """With the blocks 0.15 mm apart and crossed, both kinds of pairs are active; each pair's distance (the
    kernels' closed-triangle and segment closest points) is the brute-force one."""
    mesh, n, x, sc, _ = _barrier_state()
    a = sc.arrays
    S, K, E, KE = sc.num_surface, a.candidates, sc.num_edges, a.edge_candidates
    assert sc.gap == pytest.approx(sk.SELF_CONTACT_GAP * mesh.median_surface_edge_length)
    vt, ee = _active_pairs(sc, x)
    assert vt > 10 and ee > 10
    surface, faces, edges = a.surface.numpy(), a.faces.numpy(), a.edges.numpy()
    pair, dist = a.pair.numpy()[: S * K].reshape(S, K), a.pair_distance.numpy()[: S * K].reshape(S, K)
    rng = np.random.default_rng(0)
    for s, k in rng.permutation(np.argwhere(pair >= 0))[:20]:
        ref = _point_triangle_distance(x[surface[s]], x[faces[pair[s, k]]])
        assert dist[s, k] == pytest.approx(ref, rel=1e-9)
        # never a pair inside one block (the two blocks are the only parts apart along the surface)
        assert (surface[s] < n) != (faces[pair[s, k]][0] < n)
    epair = a.edge_pair.numpy()[: E * KE].reshape(E, KE)
    edist = a.edge_pair_distance.numpy()[: E * KE].reshape(E, KE)
    for e, k in rng.permutation(np.argwhere(epair >= 0))[:20]:
        assert epair[e, k] > e  # each pair once
        ref = _segment_distance(x[surface[edges[e]]], x[surface[edges[epair[e, k]]]])
        assert edist[e, k] == pytest.approx(ref, rel=1e-9)


def _dense_hessian(pattern, blocks, couplings, touched):
    """The Hessian on the ``touched`` vertices' components, dense: the pattern's ``blocks`` and the
    ``couplings`` (rows, cols, blocks; each added with its transpose), and the vertices' row index."""
    index = {u: k for k, u in enumerate(touched)}
    full = np.zeros((3 * len(touched), 3 * len(touched)))

    def add(r, c, block):
        full[3 * index[r] : 3 * index[r] + 3, 3 * index[c] : 3 * index[c] + 3] += block

    for a_ in touched:
        for b_ in touched:
            k = pattern.block_index(np.array([a_]), np.array([b_]))[0]
            if k >= 0:
                add(a_, b_, blocks[k])
    for r, c, block in zip(*couplings):
        if np.abs(block).max() > 0:
            add(r, c, block)
            add(c, r, block.T)
    return full, index


@pytest.mark.parametrize("aligned", [False, True])
def test_barrier_gradient_and_hessian_match_finite_differences(aligned):
    """The barrier's exact gradient (vertex-triangle and edge-edge pairs; with the blocks aligned, edge above
    edge and turned by 0.01 rad, the pairs of near-parallel edges are within the mollifier's range, its
    gradient included) against central differences of its energy with the pairs fixed; the forces sum to
    zero; the Hessian (pattern blocks and the couplings outside it) is symmetric PSD and gives the contact's
    stiffness: the change of the upper block's vertical force for a vertical move of that block, against
    finite differences of the gradient."""
    mesh, n, x, sc, pattern = _barrier_state(twist=0.01 if aligned else 0.05, aligned=aligned)
    a = sc.arrays
    ne, ke = sc.num_edges, a.edge_candidates
    surface, edges = a.surface.numpy(), a.edges.numpy()
    pairs = a.edge_pair.numpy()[: ne * ke].reshape(ne, ke)
    dist = a.edge_pair_distance.numpy()[: ne * ke].reshape(ne, ke)
    sin2 = []
    for e, k in zip(*np.nonzero((pairs >= 0) & (dist < sc.gap))):
        u, w = (np.diff(x[surface[edges[i]]], axis=0)[0] for i in (e, pairs[e, k]))
        sin2.append(np.linalg.norm(np.cross(u, w)) ** 2 / (u @ u) / (w @ w))
    mollified = np.sum(np.array(sin2) < sk.SELF_CONTACT_PARALLEL)
    assert (mollified > 0) == aligned
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    g, H = _assemble(sc, pattern, x)
    touched = np.flatnonzero(np.linalg.norm(g, axis=1) > 0)
    assert len(touched) > 20 and np.any(touched < n) and np.any(touched >= n)
    assert _energy(sc, x, youngs, 1000.0, 1e-2) > 0
    np.testing.assert_allclose(g.sum(axis=0), 0.0, atol=1e-12 * np.abs(g).max())
    assert g[touched[touched >= n], 2].sum() < 0  # the upper block is pushed up (gradient = -force)
    _assert_fd_gradient(sc, x, g, touched[::3], youngs, 1000.0, 1e-2, eps=1e-10)
    rows, cols, coupling = (a.numpy() for a in sc.coupling)
    live = np.abs(coupling).reshape(len(coupling), -1).max(axis=1) > 0
    assert live.sum() > 10
    full, index = _dense_hessian(pattern, H, (rows, cols, coupling), touched)
    m = len(full)
    np.testing.assert_allclose(full, full.T, atol=1e-12 * np.abs(full).max())
    assert np.linalg.eigvalsh(full).min() > -1e-9 * np.abs(full).max()
    # vertical stiffness of the contact: d(upper block's force_z)/d(upper block's z)
    eps = 1e-9
    move = np.zeros_like(x)
    move[n:, 2] = eps
    fd = (_assemble(sc, pattern, x + move)[0] - _assemble(sc, pattern, x - move)[0])[n:, 2].sum() / (2 * eps)
    dz = np.zeros(m)
    dz[[3 * index[u] + 2 for u in touched if u >= n]] = 1.0
    upper = np.zeros(m)
    upper[[3 * index[u] + 2 for u in touched if u >= n]] = 1.0
    # the Hessian leaves out the mollifier's second derivatives and holds the distance's curvature with the
    # closest point's weights frozen: stiffer than the true one where closest points are corners (the
    # aligned blocks, vertex above vertex: 5.5 % measured)
    assert upper @ full @ dz == pytest.approx(fd, rel=8e-2 if aligned else 2e-2)


def test_barrier_energy_is_continuous_across_a_concave_crease():
    """A vertex 0.1 mm above a valley's crease (inside the activation distance) moved across it and along
    the faces (0.1 mm above the crease's height there): the barrier holds it all along, from the crease
    edge's pairs in the wedge and the faces' beside it; its energy's steps shrink with the step (no jump,
    where the prism rule has one below the surface)."""
    from defgraspnets.fem.system import BlockPattern

    mesh, v, x = crease_probe()
    h = mesh.median_surface_edge_length
    x[v] = [CREASE_X, PROBE_Y, SIZE[2] + 1e-4]
    assert 1e-4 < sk.SELF_CONTACT_GAP * h
    sc = sk.SelfContact(mesh, BlockPattern.build(mesh, 0), 1, h, "cpu", model="barrier")
    sc.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))
    youngs = wp.array([E], dtype=wp.float64, device="cpu")

    def energies(offsets):
        out = []
        for dx in offsets:
            y = x.copy()
            y[v, 0] += dx
            y[v, 2] += 0.3 * abs(dx)  # along the valley's faces, 0.1 mm above the crease's height there
            out.append(_energy(sc, y, youngs, 1000.0, 1e-2))
        return np.array(out)

    coarse = energies(np.linspace(-1e-3, 1e-3, 201))
    assert coarse.min() > 0.05 * coarse.max()
    step = np.abs(np.diff(coarse)).max()
    assert np.abs(np.diff(energies(np.linspace(-1e-3, 1e-3, 2001)))).max() < 0.2 * step


def test_barrier_step_bound_keeps_every_pair_apart():
    """From the blocks 0.15 mm apart, a direction that drives the upper block 1 mm down through the lower
    one (with random moves of every vertex): the full step would put vertices inside; the bound stops the
    step where the pairs have closed at most 90 % of their distances, short of any crossing: from there a
    fresh pairing finds every pair apart (finite energy) and no vertex inside."""
    mesh, n, x, sc, _ = _barrier_state()
    N = mesh.num_vertices
    rng = np.random.default_rng(5)
    direction = rng.normal(scale=2e-4, size=(N, 3))
    direction[n:, 2] -= 1e-3
    bound = sc.step_bound(
        wp.array(x, dtype=wp.vec3d, device="cpu"),
        wp.array(direction, dtype=wp.vec3d, device="cpu"),
        N,
        wp.array([1], dtype=wp.int32, device="cpu"),
    )
    assert bound.shape == (1,) and 0 < bound[0] < 0.15
    assert mesh.surface_vertices_inside(x + direction).size > 10
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    for t in np.linspace(0.0, bound[0], 6):
        y = x + t * direction
        assert mesh.surface_vertices_inside(y).size == 0
        sc.update_pairs(wp.array(y, dtype=wp.vec3d, device="cpu"))
        assert np.isfinite(_energy(sc, y, youngs, 1000.0, 1e-2))
    # nothing moves: no bound
    still = sc.step_bound(
        wp.array(x, dtype=wp.vec3d, device="cpu"),
        wp.zeros(N, dtype=wp.vec3d, device="cpu"),
        N,
        wp.array([1], dtype=wp.int32, device="cpu"),
    )
    assert still[0] == np.inf


def _left_out_distances(sc, mesh, y):
    """Brute force at y: per surface vertex the least distance to a triangle that is neither excluded for it
    nor in its list, and per surface edge (of a sample) to an edge of higher index not in its list."""
    a = sc.arrays
    S, K, E, KE = sc.num_surface, a.candidates, sc.num_edges, a.edge_candidates
    surface, faces, edges = a.surface.numpy(), a.faces.numpy(), a.edges.numpy()
    start, excluded = a.excluded_start.numpy(), a.excluded.numpy()
    pair, epair = a.pair.numpy()[: S * K].reshape(S, K), a.edge_pair.numpy()[: E * KE].reshape(E, KE)
    vertex = np.full(S, np.inf)
    for s in range(S):
        skip = set(excluded[start[s] : start[s + 1]]) | set(pair[s][pair[s] >= 0])
        for f in range(len(faces)):
            if f not in skip:
                vertex[s] = min(vertex[s], _point_triangle_distance(y[surface[s]], y[faces[f]]))
    sample = np.random.default_rng(2).permutation(E)[:40]
    edge = np.full(len(sample), np.inf)
    for i, e in enumerate(sample):
        ends = edges[e]
        skip_faces = set(excluded[start[ends[0]] : start[ends[0] + 1]]) | set(
            excluded[start[ends[1]] : start[ends[1] + 1]]
        )
        near = {int(g) for f in skip_faces for g in a.face_edges.numpy()[f]}
        for g in range(e + 1, E):
            if g not in near and g not in epair[e]:
                edge[i] = min(edge[i], _segment_distance(y[surface[ends]], y[surface[edges[g]]]))
    return vertex, sample, edge


def test_barrier_pair_lists_are_kept_only_while_no_left_out_pair_can_act(monkeypatch):
    """A problem's pair lists are kept from one pairing to the next while every clear radius, less the
    surface's drift since the build, stays at or above SELF_CONTACT_KEPT_CLEAR of its value at the build and
    above d^: the kept radii are then true lower bounds of every left-out pair's distance (brute force) and
    the barrier's energy and gradient are those of a fresh pairing. A larger move rebuilds them (as a fresh
    pairing would), and so does a drift that would leave a left-out pair possibly within d^."""
    mesh, n, x, sc, pattern = _barrier_state()
    lists, a = sc._lists, sc.arrays
    built = a.pair.numpy().copy(), a.edge_pair.numpy().copy()
    clear0, edge_clear0 = a.clear.numpy().copy(), a.edge_clear.numpy().copy()
    y = x + np.random.default_rng(4).normal(scale=1e-5, size=x.shape)
    y[n:, 2] -= 5e-5  # the upper block 50 um lower: 0.1 mm apart
    sc.update_pairs(wp.array(y, dtype=wp.vec3d, device="cpu"))
    assert lists.rebuild.numpy()[0] == 0
    np.testing.assert_array_equal(a.pair.numpy(), built[0])
    np.testing.assert_array_equal(a.edge_pair.numpy(), built[1])
    surface, ends = a.surface.numpy(), a.edges.numpy()
    drift = np.linalg.norm((y - x)[surface], axis=1)
    np.testing.assert_allclose(a.clear.numpy(), clear0 - drift - drift.max(), rtol=1e-12)
    edge_drift = np.maximum(drift[ends[:, 0]], drift[ends[:, 1]])
    np.testing.assert_allclose(a.edge_clear.numpy(), edge_clear0 - edge_drift - drift.max(), rtol=1e-12)
    vertex, sample, edge = _left_out_distances(sc, mesh, y)
    assert np.all(vertex >= a.clear.numpy()) and np.all(edge >= a.edge_clear.numpy()[sample])
    fresh = sk.SelfContact(mesh, pattern, 1, mesh.median_surface_edge_length, "cpu", model="barrier")
    fresh.update_pairs(wp.array(y, dtype=wp.vec3d, device="cpu"))
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    kept_energy, fresh_energy = _energy(sc, y, youngs, 1000.0, 1e-2), _energy(fresh, y, youngs, 1000.0, 1e-2)
    assert kept_energy > 0 and kept_energy == pytest.approx(fresh_energy, rel=1e-12)
    g_kept, g_fresh = _assemble(sc, pattern, y)[0], _assemble(fresh, pattern, y)[0]
    np.testing.assert_allclose(g_kept, g_fresh, rtol=0, atol=1e-12 * np.abs(g_fresh).max())

    z = y.copy()
    z[n:, 0] += 1.5e-3  # the upper block 1.5 mm sideways: more than half a clear radius
    sc.update_pairs(wp.array(z, dtype=wp.vec3d, device="cpu"))
    assert lists.rebuild.numpy()[0] == 1
    fresh = sk.SelfContact(mesh, pattern, 1, mesh.median_surface_edge_length, "cpu", model="barrier")
    fresh.update_pairs(wp.array(z, dtype=wp.vec3d, device="cpu"))
    for mine, theirs in (
        (a.pair, fresh.arrays.pair),
        (a.edge_pair, fresh.arrays.edge_pair),
        (a.clear, fresh.arrays.clear),
        (a.edge_clear, fresh.arrays.edge_clear),
    ):
        np.testing.assert_array_equal(mine.numpy(), theirs.numpy())

    # the d^ floor alone (no fraction): the upper block slid sideways by t drifts its vertices by t (and the
    # problem's largest drift is t), so the least kept radius reaches d^ at t*
    monkeypatch.setattr(sk, "SELF_CONTACT_KEPT_CLEAR", 0.0)
    sc.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))  # rebuilt at x
    upper = surface >= n
    t_star = min(
        ((clear0 - sc.gap) / (1 + upper)).min(),
        ((edge_clear0 - sc.gap) / (1 + upper[ends].any(axis=1))).min(),
    )
    for t, rebuilt in ((0.9 * t_star, 0), (1.1 * t_star, 1)):
        w = x.copy()
        w[n:, 1] += t
        sc.update_pairs(wp.array(w, dtype=wp.vec3d, device="cpu"))
        assert lists.rebuild.numpy()[0] == rebuilt
        if not rebuilt:
            assert min(a.clear.numpy().min(), a.edge_clear.numpy().min()) >= sc.gap


def test_barrier_pair_lists_are_kept_or_rebuilt_per_problem():
    """Two problems in one batch: the one that moved a little keeps its lists (and its clear radii shrink by
    its own drift), the one whose upper block slid 1.5 mm rebuilds them, exactly as a fresh pairing of that
    problem alone; each problem's drift is its own."""
    mesh, n, x, single, pattern = _barrier_state()
    h = mesh.median_surface_edge_length
    sc = sk.SelfContact(mesh, pattern, 2, h, "cpu", model="barrier")
    sc.update_pairs(wp.array(np.concatenate([x, x]), dtype=wp.vec3d, device="cpu"))
    S, E, K, KE = sc.num_surface, sc.num_edges, sc.arrays.candidates, sc.arrays.edge_candidates
    built = sc.arrays.pair.numpy().copy()
    clear0 = sc.arrays.clear.numpy().copy()
    y = x.copy()
    y[n:, 2] -= 2e-5
    z = x.copy()
    z[n:, 0] += 1.5e-3
    sc.update_pairs(wp.array(np.concatenate([y, z]), dtype=wp.vec3d, device="cpu"))
    np.testing.assert_array_equal(sc._lists.rebuild.numpy(), [0, 1])
    np.testing.assert_array_equal(sc.arrays.pair.numpy()[: S * K], built[: S * K])
    assert sc._lists.max_drift.numpy()[0] == pytest.approx(2e-5, rel=1e-9)
    np.testing.assert_allclose(
        sc.arrays.clear.numpy()[:S],
        clear0[:S] - np.where(sc.arrays.surface.numpy() >= n, 2e-5, 0.0) - 2e-5,
        rtol=1e-12,
    )
    alone = sk.SelfContact(mesh, pattern, 1, h, "cpu", model="barrier")
    alone.update_pairs(wp.array(z, dtype=wp.vec3d, device="cpu"))
    np.testing.assert_array_equal(sc.arrays.pair.numpy()[S * K :], alone.arrays.pair.numpy())
    np.testing.assert_array_equal(sc.arrays.edge_pair.numpy()[E * KE :], alone.arrays.edge_pair.numpy())
    np.testing.assert_array_equal(sc.arrays.clear.numpy()[S:], alone.arrays.clear.numpy())


def test_barrier_refuses_a_surface_that_touches_itself_at_rest():
    """Two blocks 0.1 mm apart at rest (within the 0.25 mm activation distance): refused with the vertex,
    the distance and what to do."""
    from defgraspnets.fem.system import BlockPattern

    a = fem.TetMesh.box(size=SIZE, divisions=(4, 4, 2))
    upper = a.points + [SHIFT[0], SHIFT[1], SIZE[2] + 1e-4]
    mesh = fem.TetMesh(np.vstack([a.points, upper]), np.vstack([a.tets, a.tets + a.num_vertices]))
    with pytest.raises(ValueError, match="within the activation distance"):
        sk.SelfContact(
            mesh, BlockPattern.build(mesh, 0), 1, mesh.median_surface_edge_length, "cpu", "barrier"
        )
    with pytest.raises(ValueError, match="within the activation distance"):
        fem.QuasiStaticSolver(
            mesh, [], options=fem.SolverOptions(self_contact=1.0, self_contact_model="barrier")
        )


def test_barrier_pressed_blocks_stay_apart_and_balance():
    """The upper block pressed 2 mm onto the lower one (0.5 mm apart) with the barrier: converged with no
    vertex inside the other block and every active pair's distance between 0 and the activation distance
    d^; the forces sum to zero and are carried by the lower block's support; the blocks meet d^ early,
    so the press force is the prism rule's at a d^ deeper press (within 3 %); "dense" and "banded" reach the
    same equilibrium."""
    press = 2e-3
    on, solver, n = pressed_blocks(1.0, press, self_contact_model="barrier")
    assert on.status[0] == fem.SolveStatus.CONVERGED
    mesh = on.mesh
    x = mesh.points + on.displacement[0]
    assert mesh.surface_vertices_inside(x).size == 0
    force, pen = solver.self_contact_forces()
    assert not pen.any()
    sc = solver._self_contact
    vt, ee = _active_pairs(sc, x)
    assert vt > 10
    dist = sc.arrays.pair_distance.numpy()[sc.arrays.pair.numpy() >= 0]
    assert dist.min() > 0.5 * sc.gap  # held near d^: the barrier is stiff (kappa = 1000)
    pushed = assert_blocks_balance(on, force, n)
    prism, prism_solver, _ = pressed_blocks(1.0, press + sc.gap)
    assert prism.status[0] == fem.SolveStatus.CONVERGED
    assert pushed[2] == pytest.approx(prism_solver.self_contact_forces()[0][0, n:, 2].sum(), rel=3e-2)
    for linear_solver in ("dense", "banded"):
        other, _, _ = pressed_blocks(1.0, press, self_contact_model="barrier", linear_solver=linear_solver)
        assert other.status[0] == fem.SolveStatus.CONVERGED
        np.testing.assert_allclose(other.displacement, on.displacement, atol=1e-9)


def test_barrier_increment_does_not_start_from_a_prediction_through_the_surface(monkeypatch):
    """The upper block pressed 0.2 mm, then 1.35 mm: the predictor's extrapolation (twice the first press)
    would carry it 0.1 mm into the lower block; its path is checked with the step bound and the increment
    starts from the last converged state instead. The press ends where a fine path of 0.1 mm presses ends,
    nothing inside; without the step bounds (line search and predictor) it ends elsewhere."""
    fine = press_path(np.linspace(0.2e-3, 1.35e-3, 12), self_contact_model="barrier")
    coarse = press_path([0.2e-3, 1.35e-3], self_contact_model="barrier")
    mesh = coarse.mesh
    assert mesh.surface_vertices_inside(mesh.points + coarse.displacement[0]).size == 0
    np.testing.assert_allclose(coarse.displacement, fine.displacement, rtol=0, atol=1e-9)
    # measured: converged with 32 surface vertices inside the other block, 0.72 mm from the fine path's end
    monkeypatch.setattr(sk.SelfContact, "step_bound", lambda self, *a: np.full(self.batch_size, np.inf))
    unbounded = press_path([0.2e-3, 1.35e-3], self_contact_model="barrier")
    assert mesh.surface_vertices_inside(mesh.points + unbounded.displacement[0]).size > 10
    assert np.abs(unbounded.displacement - fine.displacement).max() > 1e-4


@pytest.mark.slow
def test_barrier_carries_the_thin_ring_squeezed_flat():
    """The thin ring (annulus_ro30_ri25_h50, 953 fTetWild vertices, 100 kPa) squeezed 0-15 N in 50 steps by
    grasp 24 of the data path's grasps: with the barrier every step converges, and no surface vertex is ever
    inside the object (the prism model also reaches 15 N here, with 6 vertices inside;
    ``benchmarks/fem_self_contact_barrier_s50.md``: ~40 s on the 2-core CPU)."""
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp, squeeze_solver_options

    mesh = fem.TetMesh.load(Path(__file__).parent / "data" / "annulus_ro30_ri25_h50_ftetwild.vtu")
    grasps = sample_antipodal_grasps(mesh, 100, friction_coefficient=0.7, rotations_per_axis=4, seed=0)
    options = squeeze_solver_options(linear_solver="direct", self_contact=1.0, self_contact_model="barrier")
    material = fem.Material(1e5, 0.3, 1000.0, model="neohookean")
    solver = make_squeeze_solver(mesh, grasps[[24]], material, 0.7, device="cpu", options=options)
    steps = squeeze_ramp(solver, 15.0, 50)
    assert [int(e.status[0]) for e in steps] == [0] * 50
    for e in steps:
        assert mesh.surface_vertices_inside(mesh.points + e.displacement[0]).size == 0


def test_barrier_line_search_shortens_full_steps_that_overshoot(monkeypatch):
    """Newton steps made 1.8 times too long (the barrier's Hessian can jump where a pair's closest point
    moves from a face to an edge or a corner): the line search accepts the full step (the energy falls) but
    the energy along it curves more than Newton's model, so the step is cut to the parabola's minimum and the
    press converges (57 Newton iterations against 22 with exact steps: steps shortened by the step bound or
    the largest-move cap are not refined); without that it overshoots back and forth, each iteration's
    error about -0.8 times the last, and is still not converged after 400 iterations (measured on the 2-core
    CPU; here each run may bisect its load once)."""
    from defgraspnets.fem import solver as solver_module

    original = solver_module.QuasiStaticSolver._linear_solve

    def too_long(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        inc = self.system.increment
        inc.assign(inc.numpy() * 1.8)
        return out

    # (one load bisection at most: the stall without the refinement shows in 80 iterations)
    options = {"self_contact_model": "barrier", "max_load_bisections": 1}
    exact, _, _ = pressed_blocks(1.0, 1e-3, **options)
    monkeypatch.setattr(solver_module.QuasiStaticSolver, "_linear_solve", too_long)
    refined, _, _ = pressed_blocks(1.0, 1e-3, **options)
    assert exact.status[0] == refined.status[0] == fem.SolveStatus.CONVERGED
    assert int(refined.newton_iterations[0]) < 3 * int(exact.newton_iterations[0])
    np.testing.assert_allclose(refined.displacement, exact.displacement, atol=1e-8)
    monkeypatch.setattr(solver_module.QuasiStaticSolver, "_refine_full_steps", lambda self, *a: None)
    plain, _, _ = pressed_blocks(1.0, 1e-3, **options)
    assert plain.status[0] != fem.SolveStatus.CONVERGED


@pytest.mark.parametrize("trials", [1, 4])
def test_barrier_line_search_with_nothing_to_search(trials):
    """A line search in which no problem searches (none working, or every direction uphill) leaves the state
    as it is, with several trial states per pass (CUDA's default) too: no energy was evaluated, nothing to
    refine (a crash on the H200 before this test)."""
    solver, _, _ = blocks_solver(1.0, self_contact_model="barrier", line_search_trials=trials)
    before = solver._q.numpy().copy()
    for working in (np.zeros(1, dtype=bool), np.ones(1, dtype=bool)):
        solver.system.increment.zero_()  # a zero step: no descent
        failed, first, alpha = solver._line_search(working, 1.0)
        assert alpha[0] == 0.0 and failed[0] == int(working[0])
    np.testing.assert_array_equal(solver._q.numpy(), before)


# ---------------------------------------------------------------- the barrier's friction
MU = 0.5


def _friction_state(slide: float, seed: int = 2):
    """The crossed blocks 0.15 mm apart (``_barrier_state``) with barrier friction mu = 0.5 lagged there,
    then the upper block slid sideways by ``slide`` [m] along (1, 0.3) and every vertex jiggled by ~0.3 um:
    (mesh, upper block's first vertex, lag state, slid state, the frictional and frictionless SelfContact,
    pattern, slide direction)."""
    mesh, n, x0, frictionless, pattern = _barrier_state()
    sc = sk.SelfContact(
        mesh, pattern, 1, mesh.median_surface_edge_length, "cpu", model="barrier", friction=MU
    )
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    lag = wp.array(x0, dtype=wp.vec3d, device="cpu")
    sc.update_pairs(lag)
    sc.lag_friction(lag, youngs, 1000.0, wp.array([1], dtype=wp.int32, device="cpu"))
    direction = np.array([1.0, 0.3, 0.0]) / np.linalg.norm([1.0, 0.3, 0.0])
    x = x0.copy()
    x[n:] += slide * direction
    x += np.random.default_rng(seed).normal(scale=3e-7, size=x.shape)
    for contact in (sc, frictionless):
        contact.update_pairs(wp.array(x, dtype=wp.vec3d, device="cpu"))
    return mesh, n, x0, x, sc, frictionless, pattern, direction


def test_barrier_friction_option_is_checked():
    mesh, n, x0, _, pattern = _barrier_state()
    h = mesh.median_surface_edge_length
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="friction"):
            sk.SelfContact(mesh, pattern, 1, h, "cpu", model="barrier", friction=bad)
        with pytest.raises(ValueError, match="self_contact_friction"):
            fem.SolverOptions(self_contact=1.0, self_contact_model="barrier", self_contact_friction=bad)
    with pytest.raises(ValueError, match="barrier"):
        sk.SelfContact(mesh, pattern, 1, h, "cpu", model="prism", friction=0.3)
    with pytest.raises(ValueError, match="self_contact_model 'barrier'"):
        fem.SolverOptions(self_contact=1.0, self_contact_friction=0.3)
    with pytest.raises(ValueError, match="self_contact > 0"):
        fem.SolverOptions(self_contact_model="barrier", self_contact_friction=0.3)


@pytest.mark.parametrize("slide", [1e-5, 2e-4])
def test_barrier_friction_gradient_and_hessian_match_finite_differences(slide):
    """Lagged friction (mu 0.5) of the crossed blocks, the upper block slid by 10 um (inside the stick zone
    eps = 0.01 h, ~50 um) or 0.2 mm (sliding): the lagged pairs are the barrier's active ones; the gradient
    matches central differences of the energy; the friction forces are internal; sliding, they oppose the
    slide with Coulomb's magnitude mu sum(lambda) (every pair at its capacity), sticking, less; the friction
    Hessian is symmetric PSD and matches differences of the friction gradient."""
    mesh, n, x0, x, sc, frictionless, pattern, direction = _friction_state(slide)
    fr = sc._friction
    vt, ee = _active_pairs(frictionless, x0)
    other = fr.other.numpy()
    vertex_slots = sc.num_surface * sc.arrays.candidates
    lagged_vt, lagged_ee = int((other[:vertex_slots] >= 0).sum()), int((other[vertex_slots:] >= 0).sum())
    assert (lagged_vt, lagged_ee) == (vt, ee)
    assert sc.slip == pytest.approx(sk.SELF_CONTACT_FRICTION_SLIP * mesh.median_surface_edge_length)
    capacity = MU * fr.force.numpy()[other >= 0].sum()
    assert capacity > 0
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    g, H = _assemble(sc, pattern, x)
    g0, H0 = _assemble(frictionless, pattern, x)
    friction = -(g - g0)  # the friction forces
    np.testing.assert_allclose(friction.sum(axis=0), 0.0, atol=1e-12 * np.abs(friction).max())
    on_upper = friction[n:].sum(axis=0)
    tangential = on_upper - (on_upper @ [0, 0, 1.0]) * np.array([0, 0, 1.0])
    assert tangential @ direction < 0  # against the slide
    if slide > sc.slip:
        assert np.linalg.norm(tangential) == pytest.approx(capacity, rel=1e-2)
    else:
        assert 0.05 * capacity < np.linalg.norm(tangential) < 0.9 * capacity
    touched = np.flatnonzero(np.linalg.norm(friction, axis=1) > 0)
    _assert_fd_gradient(sc, x, g, touched[::4], youngs, 1000.0, 1e-2, eps=1e-10)
    # the friction Hessian (pattern blocks and its couplings, after the barrier's): symmetric PSD, the
    # derivative of its gradient
    first = sc.couplings_per_problem - 4 * sc.friction_slots
    friction_couplings = [a.numpy()[first:] for a in sc.coupling]
    assert np.abs(friction_couplings[2]).max() > 0
    full, index = _dense_hessian(pattern, H - H0, friction_couplings, touched)
    np.testing.assert_allclose(full, full.T, atol=1e-12 * np.abs(full).max())
    assert np.linalg.eigvalsh(full).min() > -1e-9 * np.abs(full).max()
    v = np.random.default_rng(3).normal(size=(len(touched), 3))
    move = np.zeros_like(x)
    move[touched] = v
    eps = 1e-11
    diff = []
    for sign in (1, -1):
        xs = x + sign * eps * move
        for contact in (sc, frictionless):
            contact.update_pairs(wp.array(xs, dtype=wp.vec3d, device="cpu"))
        diff.append(_assemble(sc, pattern, xs)[0] - _assemble(frictionless, pattern, xs)[0])
    fd = ((diff[0] - diff[1]) / (2 * eps))[touched].ravel()
    np.testing.assert_allclose(full @ v.ravel(), fd, rtol=0, atol=1e-4 * np.abs(fd).max())


def _slid_block(mu: float, slides, press: float = 2e-3, device: str = "cpu", linear_solver: str = "direct"):
    """A 10 mm cube of one mesh with a 30 x 30 x 10 mm slab, 0.5 mm above the slab's middle; the slab's
    bottom and the cube's top fixed (prescribed); barrier self-contact with friction ``mu``. The top pressed
    down by ``press``, then moved sideways (x) by each of ``slides`` [m] in turn with the press held (the
    cube stays over the slab): per slide the contact force on the cube [N] (barrier and friction)."""
    slab = fem.TetMesh.box(size=(0.03, 0.03, 0.01), divisions=(6, 6, 2))
    cube = fem.TetMesh.box(size=(0.01, 0.01, 0.01), divisions=(2, 2, 2))
    n = slab.num_vertices
    mesh = fem.TetMesh(
        np.vstack([slab.points, cube.points + [0.0103, 0.0107, 0.0105]]),
        np.vstack([slab.tets, cube.tets + n]),
    )
    z = mesh.points[:, 2]
    fixed = np.zeros((mesh.num_vertices, 3), dtype=bool)
    top = z > 0.0205 - 1e-9
    fixed[(z < 1e-9) | top] = True
    options = fem.SolverOptions(
        linear_solver=linear_solver,
        self_contact=1.0,
        contact_smoothing=1e-2,
        self_contact_model="barrier",
        self_contact_friction=mu,
    )
    material = fem.Material(E, 0.3, 1000.0, model="neohookean")
    solver = fem.QuasiStaticSolver(mesh, [], material, fixed=fixed, device=device, options=options)
    u = np.zeros((mesh.num_vertices, 3))
    u[top, 2] = -press
    assert (
        solver.solve(prescribed_displacement=u, initial_fraction=0.25).status[0] == fem.SolveStatus.CONVERGED
    )
    out = []
    for slide in slides:
        u[top, 0] = slide
        eq = solver.solve(prescribed_displacement=u, initial_fraction=0.5)
        assert eq.status[0] == fem.SolveStatus.CONVERGED
        force, _ = solver.self_contact_forces()
        pushed = force[0, n:].sum(axis=0)
        np.testing.assert_allclose(force[0].sum(axis=0), 0.0, atol=1e-9 * np.abs(force).max())
        support = eq.reaction_force[0, z < 1e-9].sum(axis=0)
        np.testing.assert_allclose(support, pushed, rtol=1e-4, atol=1e-6 * pushed[2])
        if mu > 0:  # accepted with its own normal forces: the lagged ones are the converged state's
            sc, stats = solver._self_contact, wp.zeros((3, 1), dtype=wp.float64, device=device)
            sc.update_pairs(solver._positions)
            active = wp.array([1], dtype=wp.int32, device=device)
            sc.friction_lag_error(solver._positions, solver._youngs, 1000.0, active, stats)
            largest, total, capacity = stats.numpy()[:, 0]
            assert capacity > 0.2 * mu * pushed[2]
            assert total < 1e-3 * capacity
        out.append(pushed)
    return out


def test_barrier_friction_sticks_then_slides_at_coulombs_limit():
    """A cube pressed onto a slab (one mesh), its top then moved sideways with the press held, with and
    without friction (mu = 0.5): the friction's share of the lateral force on the cube (the difference of
    the two, per mu F_z) grows with the move while the interface sticks (the bodies' shear and partial
    slip), then is Coulomb's limit while the cube slides (within 10 %: the slab's dent under the cube's
    leading edge tilts normals; measured 1.00-1.07). Without friction the lateral force is a few % of F_z.
    The lagged normal forces are re-lagged until consistent. Forces balance the slab's support."""
    slides = [5e-4, 1e-3, 2e-3, 4e-3, 5e-3, 6e-3]
    frictionless = _slid_block(0.0, slides)
    with_friction = _slid_block(MU, slides)
    share = []
    for p0, p in zip(frictionless, with_friction):
        assert abs(p0[0]) < 0.03 * p0[2]
        share.append(-(p[0] - p0[0]) / (MU * p[2]))
    assert 0.05 < share[0] < share[1] < share[2] < 0.8
    for s in share[3:]:
        assert s == pytest.approx(1.0, abs=0.1)


#: the cube's contact forces [N] pushed 1 and 5 mm across the slab with friction on the CPU ("direct")
FRICTION_REFERENCE = Path(__file__).parent / "data" / "self_contact_friction_cpu_reference.npz"
FRICTION_SLIDES = [1e-3, 5e-3]


def write_friction_cpu_reference():
    """Regenerate tests/data/self_contact_friction_cpu_reference.npz (a GPU machine may have no CPU kernel
    compiler: its tests compare with stored CPU results)."""
    np.savez(FRICTION_REFERENCE, force=np.array(_slid_block(MU, FRICTION_SLIDES)))


def test_friction_cpu_matches_stored_reference():
    """The CPU's forces are the stored ones that the CUDA test compares with (regenerate them with
    :func:`write_friction_cpu_reference` after a change of the path)."""
    force = np.load(FRICTION_REFERENCE)["force"]
    np.testing.assert_allclose(np.array(_slid_block(MU, FRICTION_SLIDES)), force, rtol=1e-6)


@pytest.mark.gpu
@pytest.mark.parametrize("linear_solver", ["dense", "banded"])
def test_cuda_barrier_friction_matches_cpu(linear_solver):
    """The friction's kernels (lag, energy, gradient-Hessian and couplings, forces, lag check) on CUDA give
    the CPU's contact forces on the cube pushed across the slab, sticking and sliding."""
    cuda = _slid_block(MU, FRICTION_SLIDES, device="cuda", linear_solver=linear_solver)
    for a, b in zip(np.load(FRICTION_REFERENCE)["force"], cuda):
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6 * abs(a[2]))


def test_barrier_friction_lag_check_matches_pairs_by_their_features():
    """The lag check of a state against its own lag is zero however the lists order their pairs (a list
    rebuilt in another order: every vertex's and edge's slots reversed), and it sees a moved pair: the upper
    block lowered by 10 um changes every normal force (summed error ~ mu times their change)."""
    mesh, n, x0, x, sc, _, pattern, _ = _friction_state(0.0)
    youngs = wp.array([E], dtype=wp.float64, device="cpu")
    active = wp.array([1], dtype=wp.int32, device="cpu")
    at = wp.array(x, dtype=wp.vec3d, device="cpu")

    def check(positions):
        stats = wp.zeros((3, 1), dtype=wp.float64, device="cpu")
        sc.friction_lag_error(positions, youngs, 1000.0, active, stats)
        return stats.numpy()[:, 0]

    sc.update_pairs(at)
    sc.lag_friction(at, youngs, 1000.0, active)
    largest, total, capacity = check(at)
    assert capacity == pytest.approx(MU * sc._friction.force.numpy()[sc._friction.other.numpy() >= 0].sum())
    assert total == 0.0
    a = sc.arrays
    for pair, k in ((a.pair, a.candidates), (a.edge_pair, a.edge_candidates)):
        pair.assign(pair.numpy().reshape(-1, k)[:, ::-1].ravel().copy())
    listed = np.concatenate([a.pair.numpy(), a.edge_pair.numpy()])
    lagged = sc._friction.other.numpy()
    assert np.any((lagged >= 0) & (listed != lagged))  # slot by slot, pairs would read as changed
    assert check(at)[1] == 0.0
    lowered = x.copy()
    lowered[n:, 2] -= 1e-5
    moved = wp.array(lowered, dtype=wp.vec3d, device="cpu")
    sc.update_pairs(moved)
    largest, total, now = check(moved)
    assert now > capacity and total >= 0.9 * (now - capacity) and largest > 0
