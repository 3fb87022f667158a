"""Sub-vertex contact (SolverOptions.contact_subdivisions): contact points on the surface triangles.

Off by default (the existing contact tests run unchanged); the layout and areas of the points; the contact
energy's gradient and Hessian against finite differences; the pressure stiffness kept (a plane pressed on a
face); a sphere narrower than the vertex spacing caught between vertices; friction at mu N; stick anchors
per point carried through copied and streamed states."""

import numpy as np
import pytest
import warp as wp
from fem_helpers import pressed_block

from defgraspnets import fem
from defgraspnets.fem import contact as ck

L = 0.02  # box edge [m]


def _box(divisions=(2, 2, 1), size=(L, L, L / 2)):
    return fem.TetMesh.box(size=size, divisions=divisions, origin=(-size[0] / 2, -size[1] / 2, -size[2]))


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_contact_points_are_the_subdivision_grid_once_with_the_surface_area(n):
    mesh = _box()
    vertex, weight, area = ck.surface_contact_points(mesh, n)
    S, F = len(mesh.surface_vertices), len(mesh.surface_faces)
    edges = len(np.unique(np.sort(mesh.surface_faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0))
    assert len(vertex) == S + (n - 1) * edges + (n - 1) * (n - 2) // 2 * F
    # vertex points first, as the vertex contact's slots
    np.testing.assert_array_equal(vertex[:S, 0], mesh.surface_vertices)
    np.testing.assert_array_equal(weight[:S], np.tile([1.0, 0.0, 0.0], (S, 1)))
    np.testing.assert_allclose(weight.sum(axis=1), 1.0, rtol=1e-15)
    assert area.sum() == pytest.approx(mesh.face_areas.sum(), rel=1e-12)  # no area counted twice
    if n == 1:
        np.testing.assert_array_equal(area, mesh.vertex_areas[mesh.surface_vertices])
    # every point once: the subdivided surface's grid has no duplicate positions
    x = np.einsum("pij,pi->pj", mesh.points[vertex], weight)
    assert len(np.unique(np.round(x / L * 1e9).astype(np.int64), axis=0)) == len(x)
    # every point lies on a surface triangle of its vertices (tet edges: in the FEM pattern)
    solver = fem.QuasiStaticSolver(mesh, [], device="cpu", options=fem.SolverOptions(contact_subdivisions=n))
    assert solver.num_contact_points == len(vertex)


def test_sub_vertex_contact_is_off_by_default_and_checked():
    assert fem.SolverOptions().contact_subdivisions == 1
    for bad in (0, 1.5, True, -2):
        with pytest.raises(ValueError, match="contact_subdivisions must be an int >= 1"):
            fem.SolverOptions(contact_subdivisions=bad)


def _energy_gradient_hessian(solver, positions, travel):
    """Contact energy, gradient (vertex rows and travel row) and dense Hessian of problem 0 (one body)."""
    dev = solver.device
    N, D, R = solver.mesh.num_vertices, solver.num_dofs, solver.rows_per_problem
    pos = wp.array(solver.mesh.points + positions, dtype=wp.vec3d, device=dev)
    tr = wp.array(np.atleast_1d(travel), dtype=wp.float64, device=dev)
    active = wp.array([1], dtype=wp.int32, device=dev)
    dims = (1, solver.num_contact_points, solver.num_bodies)
    energy = wp.zeros(1, dtype=wp.float64, device=dev)
    wp.launch(ck.contact_energy_kernel, dims, [*solver._contact_inputs(pos, tr), active, energy], device=dev)
    gradient = wp.zeros(R, dtype=wp.vec3d, device=dev)
    hessian = wp.zeros(solver.pattern.nnz, dtype=wp.mat33d, device=dev)
    exact = wp.array([1], dtype=wp.int32, device=dev)
    inputs = [*solver._contact_inputs(pos, tr), solver._blocks, active, exact, gradient, hessian]
    wp.launch(ck.contact_gradient_hessian_kernel, dims, inputs, device=dev)
    H = np.zeros((3 * R, 3 * R))
    for k, (r, c) in enumerate(zip(solver.pattern.rows, solver.pattern.cols)):
        H[3 * r : 3 * r + 3, 3 * c : 3 * c + 3] = hessian.numpy()[k]
    keep = np.r_[np.arange(3 * N), 3 * N + 3 * np.arange(D)]  # the travel rows' first components
    return energy.numpy()[0], gradient.numpy().ravel()[keep], H[np.ix_(keep, keep)]


def test_sampled_contact_gradient_and_hessian_match_finite_differences():
    """Penalty and friction of a force-controlled sphere on the sample points of a coarse box (exact
    Hessian: the sphere's curvature term, friction in stick and slip, the travel couplings): the gradient
    matches central differences of the energy and the Hessian central differences of the gradient, and
    sampled points (not vertices) carry them."""
    mesh = _box()
    ball = fem.RigidBody(
        "ball",
        fem.Sphere(radius=0.006, center=(0.0021, -0.0013, 0.006 - 0.0015)),  # 1.5 mm into the top face
        control=fem.Control.force((0, 0, -1)),
        friction=0.4,
    )
    solver = fem.QuasiStaticSolver(
        mesh,
        [ball],
        device="cpu",
        # a stick zone of 2 % of h (67 um), so that random motions of 0.1 mm leave some points in stick
        options=fem.SolverOptions(contact_subdivisions=3, contact_smoothing=0.1, friction_stick_slip=0.02),
    )
    P, K = solver.num_contact_points, solver.num_bodies
    rng = np.random.default_rng(3)
    u = 1e-4 * rng.standard_normal((mesh.num_vertices, 3))
    travel = 1e-4
    # lagged normal forces (some slots slip: a stretch beyond mu N / k_t), normals and stick stretches
    solver._lag_force.assign(rng.uniform(0.0, 0.2, P * K))
    nrm = rng.standard_normal((P * K, 3)) + [0.0, 0.0, 3.0]
    solver._lag_normal.assign(nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
    solver._stick_stretch.assign(2e-5 * rng.standard_normal((P * K, 3)))

    e0, g, H = _energy_gradient_hessian(solver, u, travel)
    S = len(mesh.surface_vertices)
    state = [solver._c_force, solver._c_normal, solver._c_gap, solver._c_friction, solver._c_stick]
    pos = wp.array(mesh.points + u, dtype=wp.vec3d, device="cpu")
    tr = wp.array([travel], dtype=wp.float64, device="cpu")
    wp.launch(ck.contact_state_kernel, (1, P, K), [*solver._contact_inputs(pos, tr), *state], device="cpu")
    fn, stick = solver._c_force.numpy(), solver._c_stick.numpy()
    assert fn[S:].max() > 0 and (fn[S:] > 0).sum() >= 3  # sample points press
    slipping = (solver._lag_force.numpy() > 0) & (stick == 0)
    assert slipping[S:].any() and stick[S:].any()  # friction in stick and in slip on samples

    n = len(g)
    h = 1e-8

    def shifted(i, s):
        du, dt = u.copy(), travel
        if i < 3 * mesh.num_vertices:
            du.reshape(-1)[i] += s
        else:
            dt += s
        return du, dt

    fd_g, fd_H = np.zeros(n), np.zeros((n, n))
    for i in range(n):
        ep, gp, _ = _energy_gradient_hessian(solver, *shifted(i, h))
        em, gm, _ = _energy_gradient_hessian(solver, *shifted(i, -h))
        fd_g[i] = (ep - em) / (2 * h)
        fd_H[:, i] = (gp - gm) / (2 * h)
    assert np.abs(g).max() > 0.1
    np.testing.assert_allclose(g, fd_g, atol=1e-5 * np.abs(g).max())
    np.testing.assert_allclose(H, fd_H, atol=1e-4 * np.abs(H).max())
    # the Hessian couples the vertices of loaded triangles (the w_i w_j blocks), not only their diagonals
    V = 3 * mesh.num_vertices
    off = H[:V, :V].copy()
    for v in range(mesh.num_vertices):
        off[3 * v : 3 * v + 3, 3 * v : 3 * v + 3] = 0.0
    assert np.abs(off).max() > 0.05 * np.abs(H[:V, :V]).max()  # 500x the tolerance above: not lumpable
    assert e0 > 0


def _plane_press(n, depth=2e-4, rigid=False):
    """A frictionless plane pressed ``depth`` (displacement-controlled) on the top face of a box resting on
    a frictionless floor, with a soft penalty (kappa = 1: the contact as compliant as the box); ``rigid``:
    every vertex fixed (only the penalty deforms)."""
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(3, 3, 3), origin=(-L / 2, -L / 2, 0))
    floor = fem.RigidBody("floor", fem.Plane(point=(0, 0, 0), normal=(0, 0, 1)))
    press = fem.RigidBody(
        "press", fem.Plane(point=(0, 0, L), normal=(0, 0, -1)), control=fem.Control.displacement((0, 0, -1))
    )
    options = fem.SolverOptions(contact_subdivisions=n, contact_stiffness=1.0, linear_solver="dense")
    fixed = np.arange(mesh.num_vertices) if rigid else None
    solver = fem.QuasiStaticSolver(
        mesh, [floor, press], fem.Material(1e5, 0.3, 1000.0), fixed=fixed, device="cpu", options=options
    )
    eq = solver.solve(targets={"press": depth})
    eq.require_converged()
    return eq, solver


def test_a_plane_on_a_face_presses_with_the_same_pressure_stiffness_with_samples():
    """Each point presses with kappa E A_p / h (the vertex contact's pressure stiffness) and the points'
    areas sum to the face's, so a plane pressed a given depth into a rigid box pushes with kappa E d / h
    times the area of the points on the face. That area is the face's plus the lumped share of the side
    faces at its rim (a rim vertex's area includes a third of its side triangles), an excess the samples
    shrink (n = 1: +67 %, n = 2: +33 %, n = 3: +22 % here; a soft box pressed between planes: +15.5 %, +9.6 %,
    +7.1 % over the exact force of box and penalties in series): so the forces agree within that excess,
    and approach the exact one with n. An area counted twice (samples added to full vertex areas) would
    press harder than the vertex contact; areas not scaled by 1 / n^2 would n^2 times harder."""
    E, depth, kappa = 1e5, 2e-4, 1.0
    h = L / 3  # the median surface edge
    top = L * L
    pushed = {}
    for n in (1, 2, 3):
        eq, solver = _plane_press(n, depth, rigid=True)
        x = np.einsum(
            "pij,pi->pj", solver.mesh.points[solver.contact_point_vertices], solver.contact_point_weights
        )
        area = ck.surface_contact_points(solver.mesh, n)[2][np.isclose(x[:, 2], L)].sum()
        assert solver.contact_length == pytest.approx(h, rel=1e-12)
        assert eq.body_force["press"][0, 2] == pytest.approx(kappa * E * depth / h * area, rel=1e-9)
        pushed[n] = area / top - 1.0
    # the rim excess: a third of the side triangles at the rim, a strip h / (2 n) wide along the perimeter
    for n in (1, 2, 3):
        assert pushed[n] == pytest.approx(4 * L * h / (2 * n) / top, rel=1e-9)
    # a soft box: box E / L and two penalties kappa E / h per unit area in series
    exact = depth * E * top / (L + 2 * h / kappa)
    forces = [_plane_press(n, depth)[0].body_force["press"][0, 2] for n in (1, 2, 3)]
    excess = np.array(forces) / exact - 1.0
    assert 0.0 < excess[2] < excess[1] < excess[0] < 0.16
    np.testing.assert_allclose(excess, [0.155, 0.096, 0.071], atol=0.002)


def _small_sphere_on_a_triangle(n, depth=1e-3, radius=5e-3):
    """A sphere (r = 5 mm: 10 mm wide, the vertex spacing) pressed ``depth`` past first touch onto the
    centroid of a top-face triangle (legs 10 mm) of a box clamped at its base. Returns the equilibrium,
    the solver, the triangle's deformed corners, the sphere's centre and the triangle's area."""
    mesh = _box()
    top = mesh.surface_faces[np.all(np.isclose(mesh.points[mesh.surface_faces][:, :, 2], 0.0), axis=1)]
    face = top[0]
    centroid = mesh.points[face].mean(axis=0)
    ball = fem.RigidBody(
        "ball",
        fem.Sphere(radius=radius, center=centroid + [0, 0, radius]),
        control=fem.Control.displacement((0, 0, -1)),
    )
    bottom = np.nonzero(np.isclose(mesh.points[:, 2], -L / 2))[0]
    options = fem.SolverOptions(contact_subdivisions=n, linear_solver="dense")
    solver = fem.QuasiStaticSolver(
        mesh, [ball], fem.Material(1e5, 0.3, 1000.0), fixed=bottom, device="cpu", options=options
    )
    eq = solver.solve(targets={"ball": depth})
    eq.require_converged()
    corners = eq.positions[0][face]
    center = centroid + [0, 0, radius - depth]
    area = 0.5 * np.linalg.norm(np.cross(*(mesh.points[face[1:]] - mesh.points[face[0]])))
    return eq, solver, corners, center, area


def _triangle_penetration(corners, center, radius):
    """How deep the sphere reaches past the (deformed, flat) triangle: r minus the distance from its centre
    to the triangle's nearest point (on a fine barycentric grid of the triangle)."""
    k = 399  # a multiple of 3: the centroid is on the grid
    i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1))
    inside = i + j <= k
    w = np.stack([i[inside], j[inside], k - i[inside] - j[inside]], axis=1) / k
    return radius - np.linalg.norm(w @ corners - center, axis=1).min()


@pytest.mark.parametrize("n", [3, 4])
def test_a_sphere_as_wide_as_the_vertex_spacing_is_caught_by_the_samples(n):
    """Vertex contact misses a 10 mm sphere pressed 1 mm onto the middle of a triangle with 10 mm legs (its
    footprint, 3 mm in radius, fits between the vertices, 4.7 mm away): no force, the sphere 1 mm deep in
    the triangle. With the points of the n-subdivision the sphere pushes with a Hertz-like force, and its
    penetration stays within what point contact allows: at the points the penalty's tolerance for the
    force carried, F h / (kappa E A_p), and between them the sagitta of the sphere over the largest empty
    circle of the sub-triangle grid, r - sqrt(r^2 - R_c^2) with R_c the circumradius of a sub-triangle (here
    half its 14.1 / n mm hypotenuse), given 20 % for the stretch of the dimpled surface."""
    radius, depth, E = 5e-3, 1e-3, 1e5
    eq, _, corners, center, face_area = _small_sphere_on_a_triangle(1, depth, radius)
    assert face_area == pytest.approx(L * L / 8, rel=1e-9)  # 10 mm legs
    assert eq.body_force["ball"][0, 2] == 0.0
    assert _triangle_penetration(corners, center, radius) == pytest.approx(depth, rel=1e-9)

    eq, solver, corners, center, _ = _small_sphere_on_a_triangle(n, depth, radius)
    force = np.linalg.norm(eq.body_force["ball"][0])
    hertz = 4 / 3 * E / (1 - 0.3**2) * np.sqrt(radius) * depth**1.5  # 0.33 N (the fine mesh: 0.38 N)
    assert eq.body_force["ball"][0, 2] > 0.5 * hertz
    o, h = solver.options, solver.contact_length
    area = ck.surface_contact_points(solver.mesh, n)[2]
    at_points = force * h / (o.contact_stiffness * E * area.min()) + o.contact_smoothing * h / 2
    assert 0 < eq.max_penetration[0] <= at_points
    circumradius = 0.5 * np.sqrt(2) * 0.01 / n
    sagitta = radius - np.sqrt(radius**2 - circumradius**2)  # 0.59 mm (n = 3), 0.32 mm (n = 4)
    pen = _triangle_penetration(corners, center, radius)
    assert 0 < pen <= 1.2 * sagitta + at_points
    assert pen < 0.4 * depth


def test_friction_on_samples_holds_below_mu_n_and_slips_above():
    """Stick anchors per (problem, point, body): the block holds a push of 0.9 mu N with its contact patch
    sticking (the points between the vertices carry their share of the friction), and slides at mu N under
    a push of 2 mu N."""
    mu, normal = 0.5, 1.0
    mesh, solver = pressed_block(mu, normal, contact_subdivisions=2)
    mass = mesh.mass(1000.0)
    tangential = 0.9 * mu * normal
    eq = solver.solve(body_load=fem.BodyLoad(gravity=(tangential / mass, 0, 0)))
    eq.require_converged()
    f_floor = eq.body_force["floor"][0]
    assert f_floor[0] == pytest.approx(tangential, rel=1e-5)
    assert f_floor[2] == pytest.approx(-normal, rel=1e-5)
    contact = eq.contact_normal_force["floor"][0] > 0
    slip = eq.displacement[0][mesh.surface_vertices[contact], 0]
    shear = tangential * L / (solver.materials[0].shear_modulus * L * L)
    assert np.abs(slip).max() < 0.2 * shear
    # the sample points (beyond the S vertex points) carry friction and stick
    P, K, S = solver.num_contact_points, solver.num_bodies, solver.num_surface
    stretch = solver._stick_stretch.numpy().reshape(P, K, 3)[S:, 0]
    assert np.count_nonzero(np.linalg.norm(stretch, axis=1)) > 12
    ft = np.linalg.norm(eq.contact_friction_force["floor"][0], axis=-1)
    fn = eq.contact_normal_force["floor"][0]
    assert np.all(ft <= mu * fn + solver.options.rtol * normal)  # lumped forces obey Coulomb too
    # at 0.9 mu N every point of the patch carries 95-100 % of mu f_n, so which of them are flagged sticking
    # is decided in round-off (3 of 16 on an Intel Xeon, at least 5 on the AMD EPYC of earlier sessions):
    # some stick, and the friction is nearly mobilized everywhere
    assert eq.contact_sticking["floor"][0][contact].any()
    assert np.median(ft[contact] / (mu * fn[contact])) > 0.9

    solver.reset()
    solver.solve(targets={"press": normal}).require_converged()
    eq = solver.solve(body_load=fem.BodyLoad(gravity=(2.0 * mu * normal / mass, 0, 0)))
    assert eq.status[0] == fem.SolveStatus.ESCAPED
    assert eq.load_fraction[0] == pytest.approx(0.5, abs=0.02)  # it held up to mu N


def test_streamed_and_copied_states_carry_the_stick_anchors_of_the_samples():
    """The pad squeeze of the streaming tests with the points of the 2-subdivision: its friction holds the
    box against gravity through stick anchors on sample points; copy_state_from copies them, and jobs
    streamed through a smaller batch from copies of the gripped states reach, bit for bit, the equilibria
    of one solve_sequence of the gripped batch itself (the grip, ~750 Newton passes, is solved once)."""
    from fem_helpers import pad_squeeze_solver
    from test_fem_solve_stream import _assert_same, _levels, _row, _solver, _stream

    options = {"contact_subdivisions": 2}
    template = _solver(**options)
    S, P, K = template.num_surface, template.num_contact_points, template.num_bodies
    stretch = template._stick_stretch.numpy().reshape(template.batch_size, P, K, 3)
    assert np.count_nonzero(np.linalg.norm(stretch[:, S:], axis=-1)) > 0  # anchors on samples
    copy = pad_squeeze_solver(np.zeros(2), linear_solver="dense", **options)  # not gripped
    copy.copy_state_from(template, rows=[3, 1])
    np.testing.assert_array_equal(copy._stick_stretch.numpy().reshape(2, P, K, 3), stretch[[3, 1]])
    np.testing.assert_array_equal(
        copy._lag_force.numpy().reshape(2, P, K), template._lag_force.numpy().reshape(-1, P, K)[[3, 1]]
    )

    lengths = [3, 2, 3, 1, 2]
    got, _, _ = _stream(2, lengths, template=template, **options)  # from copies of the template's states
    # then the template itself (its own gripped states, not copies) goes through the levels
    expected = template.solve_sequence(
        [{"grip": [lv[k]["grip"] for lv in map(_levels, range(5))]} for k in range(3)]
    )
    for j, n in enumerate(lengths):
        for k in range(n):
            _assert_same(_row(expected[k], j), got[(j, k)])
