"""Small reference implementations and builders shared by the FEM tests (NumPy only)."""

import numpy as np


def corotated_cauchy_stress(F: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """Cauchy stress of the fixed co-rotated model, computed independently with NumPy's SVD."""
    U, s, Vt = np.linalg.svd(F)
    if np.linalg.det(U) < 0:
        U[:, 2] *= -1
        s[2] *= -1
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
        s[2] *= -1
    J = np.prod(s)
    psi = 2 * mu * (s - 1) + lam * (J - 1) * J / s
    P = U @ np.diag(psi) @ Vt
    return P @ F.T / J


def neohookean_cauchy_stress(F: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """Cauchy stress of compressible Neo-Hookean, mu / J (F F^T - I) + lambda log J / J I (Bonet and Wood)."""
    J = np.linalg.det(F)
    return mu / J * (F @ F.T - np.eye(3)) + lam * np.log(J) / J * np.eye(3)


def linear_elastic_stress(grad_u: np.ndarray, E: float, nu: float) -> np.ndarray:
    """Hooke's law sigma = lambda tr(eps) I + 2 mu eps, eps = sym(grad u)."""
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    eps = 0.5 * (grad_u + grad_u.T)
    return lam * np.trace(eps) * np.eye(3) + 2 * mu * eps


def box_pad(size=(0.02, 0.02, 0.01)):
    """Closed outward triangle mesh of a box centred at the origin (a simple finger pad)."""
    import trimesh

    m = trimesh.creation.box(extents=size)
    return np.asarray(m.vertices), np.asarray(m.faces)


def pad_squeeze_solver(offsets, device: str = "cpu", **options):
    """Two Franka-like pads squeeze a 20 x 15 x 25 mm box (E = 100 kPa) with friction 0.7, force-controlled
    along the shared dof "grip"; one problem per entry of ``offsets`` [m], where the pads grip along x
    (off-centre grasps turn the object). ``options``: SolverOptions fields; on ``device``."""
    from defgraspnets import fem

    offsets = np.asarray(offsets, dtype=float)
    B = len(offsets)
    mesh = fem.TetMesh.box(size=(0.02, 0.015, 0.025), divisions=(4, 3, 5), origin=(-0.01, -0.0075, -0.0125))
    v, f = box_pad((0.012, 0.008, 0.012))
    bodies = [
        fem.RigidBody(
            name, fem.TriangleMesh(v, f), control=fem.Control.force((0, -s, 0), dof="grip"), friction=0.7
        )
        for name, s in (("left", 1), ("right", -1))
    ]
    solver = fem.QuasiStaticSolver(
        mesh,
        bodies,
        fem.Material(1e5, 0.3, 1000.0),
        batch_size=B,
        device=device,
        options=fem.SolverOptions(**options),
    )
    for name, s in (("left", 1), ("right", -1)):
        T = np.tile(np.eye(4), (B, 1, 1))
        T[:, 1, 3] = s * (0.0075 + 0.004)
        T[:, 0, 3] = offsets
        solver.set_body_pose(name, T)
    return solver


def assert_same_squeeze(a, b) -> None:
    """Two equilibria of pad squeezes (:func:`pad_squeeze_solver`) are the same bit for bit: statuses,
    load fractions, iterations, residuals, displacements, von Mises stresses, grip travel and force, and
    the pads' friction forces."""
    np.testing.assert_array_equal(b.status, a.status)
    for name in ("load_fraction", "newton_iterations", "linear_iterations", "residual", "displacement"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    np.testing.assert_array_equal(b.von_mises, a.von_mises)
    np.testing.assert_array_equal(b.travel["grip"], a.travel["grip"])
    np.testing.assert_array_equal(b.dof_force["grip"], a.dof_force["grip"])
    for body in ("left", "right"):
        np.testing.assert_array_equal(b.contact_friction_force[body], a.contact_friction_force[body])


def gmsh_tet_mesh(build, size_field: str, name: str):
    """Tet mesh from a gmsh OCC geometry built by ``build(occ)`` with a MathEval size field [m]."""
    import gmsh

    from defgraspnets.fem import TetMesh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(name)
        build(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        f = gmsh.model.mesh.field.add("MathEval")
        gmsh.model.mesh.field.setString(f, "F", size_field)
        gmsh.model.mesh.field.setAsBackgroundMesh(f)
        for k in ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature"):
            gmsh.option.setNumber(k, 0)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, conn = gmsh.model.mesh.getElementsByType(4)
    finally:
        gmsh.finalize()
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    return TetMesh.compacted(coords.reshape(-1, 3), index[conn.astype(np.int64)].reshape(-1, 4), name=name)


def sphere_octant_mesh(radius: float, pole_size: float, far_size: float, grading: float):
    """The x, y, z >= 0 eighth of a sphere, refined toward the pole (0, 0, R)."""

    def build(occ):
        s = occ.addSphere(0, 0, 0, radius)
        b = occ.addBox(0, 0, 0, 2 * radius, 2 * radius, 2 * radius)
        occ.intersect([(3, s)], [(3, b)])

    field = f"min({far_size}, {pole_size} + {grading}*Sqrt(x*x+y*y+(z-{radius})*(z-{radius})))"
    return gmsh_tet_mesh(build, field, "octant")


def thick_shell_octant_mesh(inner_radius: float, outer_radius: float, size: float):
    """The x, y, z >= 0 eighth of a thick-walled hollow sphere, uniform element size [m]."""

    def build(occ):
        s = occ.addSphere(0, 0, 0, outer_radius)
        hole = occ.addSphere(0, 0, 0, inner_radius)
        shell = occ.cut([(3, s)], [(3, hole)])[0]
        box = occ.addBox(0, 0, 0, 2 * outer_radius, 2 * outer_radius, 2 * outer_radius)
        occ.intersect(shell, [(3, box)])

    return gmsh_tet_mesh(build, f"{size}", "shell_octant")


def symmetric_pattern_matrices(pattern, batch: int, definite, rng) -> tuple[np.ndarray, np.ndarray]:
    """Random symmetric matrices with a BlockPattern's sparsity, as (B, n, n) dense matrices and their
    (B * nnz, 3, 3) BSR block values; ``definite[b]``: problem b positive definite (diagonally dominant)
    or indefinite (eigenvalues of both signs)."""
    n = 3 * pattern.rows_per_problem
    dense = np.zeros((batch, n, n))
    for b in range(batch):
        for r, c in zip(pattern.rows, pattern.cols):
            if r <= c:
                block = rng.normal(size=(3, 3))
                dense[b, 3 * r : 3 * r + 3, 3 * c : 3 * c + 3] = block
                dense[b, 3 * c : 3 * c + 3, 3 * r : 3 * r + 3] = block.T
        dense[b] = 0.5 * (dense[b] + dense[b].T)
        shift = np.abs(dense[b]).sum(axis=1).max() + 1.0
        dense[b] += np.eye(n) * (shift if definite[b] else 0.1)
        eigenvalues = np.linalg.eigvalsh(dense[b])
        assert (eigenvalues.min() > 0) if definite[b] else (eigenvalues.min() < 0 < eigenvalues.max())
    values = np.stack(
        [
            dense[b][3 * r : 3 * r + 3, 3 * c : 3 * c + 3]
            for b in range(batch)
            for r, c in zip(pattern.rows, pattern.cols)
        ]
    )
    return dense, values


def sealed_pole_poke(cap_divisions: int, depth: float, **solver_overrides):
    """Reading of a 20 mm sphere poking the pole of the sealed, inflated membrane (1.5 kPa gauge, CPU) with
    the sensor's solver options and ``solver_overrides`` (e.g. ``linear_solver``)."""
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, PVState, build_membrane
    from defgraspnets.tactile.sensor import MembraneSimulator, membrane_solver_options

    sensor = build_membrane(cap_divisions=cap_divisions, layers=2)
    gas = PVState(ATMOSPHERIC_PRESSURE + 1500.0, sensor.cavity_volume + sensor.dimensions.housing_volume)
    sim = MembraneSimulator(
        sensor,
        SphereIndenter(radius=0.01),
        gas,
        closed=True,
        batch_size=1,
        intrinsics=None,
        options=membrane_solver_options("cpu", **solver_overrides),
        device="cpu",
    )
    return sim, sim.indent([sim.pole_indentation(depth)], render=False)[0]


def pressed_block(mu: float, normal_force: float = 1.0, E: float = 1e5, size: float = 0.02, **options):
    """The contact tests' block: a cube of edge ``size`` [m] (3 x 3 x 3 hexes) on a floor plane of Coulomb
    coefficient ``mu``, pressed from above with ``normal_force`` [N] by a force-controlled plane, solved and
    checked converged; ``options``: SolverOptions fields. Returns (mesh, solver)."""
    from defgraspnets import fem

    L = size
    mesh = fem.TetMesh.box(size=(L, L, L), divisions=(3, 3, 3), origin=(-L / 2, -L / 2, 0))
    floor = fem.RigidBody("floor", fem.Plane(point=(0, 0, 0), normal=(0, 0, 1)), friction=mu)
    press = fem.RigidBody(
        "press", fem.Plane(point=(0, 0, L), normal=(0, 0, -1)), control=fem.Control.force((0, 0, -1))
    )
    solver = fem.QuasiStaticSolver(
        mesh, [floor, press], fem.Material(E, 0.3, 1000.0), device="cpu", options=fem.SolverOptions(**options)
    )
    solver.solve(targets={"press": normal_force}).require_converged()
    return mesh, solver


def two_unit_boxes():
    """Two 1 m boxes (2 x 2 x 2 divisions) of one mesh, 1 m apart along x, and the first box's vertex count:
    the data path's self-intersection tests move the second one into the first."""
    from defgraspnets.fem import TetMesh

    b = TetMesh.box(size=(1.0, 1.0, 1.0), divisions=(2, 2, 2))
    n = b.num_vertices
    return TetMesh(np.vstack([b.points, b.points + [2.0, 0.0, 0.0]]), np.vstack([b.tets, b.tets + n])), n


def converged_states(mesh, displacements):
    """A stand-in for the converged ``fem.Equilibrium`` of len(displacements) problems of ``mesh`` at the
    given (N, 3) displacements: what ``grasp.datagen._record_steps`` reads (status, inverted tets, positions,
    fields, grip force and travel)."""
    from types import SimpleNamespace

    u = np.stack(displacements)
    return SimpleNamespace(
        mesh=mesh, converged=np.ones(len(u), dtype=bool), status=np.zeros(len(u), dtype=np.int32),
        inverted_tets=np.zeros(len(u), dtype=int), positions=mesh.points[None] + u, displacement=u,
        von_mises=np.zeros((len(u), mesh.num_vertices)), dof_force={"grip": np.ones(len(u))},
        travel={"grip": np.ones(len(u))},
    )  # fmt: skip
