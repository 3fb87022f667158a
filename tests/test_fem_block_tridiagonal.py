"""The banded linear solver: level structures, block-tridiagonal Cholesky, and whole FEM solves with it."""

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from defgraspnets import fem
from defgraspnets.fem.block_tridiagonal import BlockTridiagonalFactor, BlockTridiagonalLayout, level_blocks
from defgraspnets.fem.system import BlockPattern


def _vertex_graph(mesh: fem.TetMesh) -> sp.csr_matrix:
    t = mesh.tets
    r = np.concatenate([t[:, a] for a in range(4) for _ in range(4)])
    c = np.concatenate([t[:, b] for _ in range(4) for b in range(4)])
    n = mesh.num_vertices
    return sp.csr_matrix((np.ones(len(r)), (r, c)), shape=(n, n))


def _two_boxes() -> fem.TetMesh:
    a = fem.TetMesh.box(size=(0.02, 0.02, 0.03), divisions=(2, 2, 3))
    b = fem.TetMesh.box(size=(0.02, 0.02, 0.02), divisions=(2, 2, 2), origin=(0.05, 0.0, 0.0))
    points = np.concatenate([a.points, b.points])
    return fem.TetMesh(points, np.concatenate([a.tets, b.tets + a.num_vertices]))


def _membrane() -> fem.TetMesh:
    from defgraspnets.tactile.membrane import build_membrane

    return build_membrane(cap_divisions=8, layers=2).mesh


@pytest.mark.parametrize(
    "make, max_flops_ratio",
    [
        (lambda: fem.TetMesh.box(size=(0.05, 0.04, 0.06), divisions=(9, 7, 11)), 0.15),  # the FEM benchmark's
        (_two_boxes, 1.0),
        (_membrane, 0.05),  # the tactile sensor's coarse membrane (915 vertices)
    ],
)
def test_level_blocks_join_each_mesh_edge_within_one_block_or_two_neighbours(make, max_flops_ratio):
    """Every vertex is ordered once, every edge joins a block to itself or a neighbour (K is block
    tridiagonal), no block is wider than the widest level, and the factorization costs a fraction of the
    dense one (the measured gain that makes the solver worth having)."""
    mesh = make()
    graph = _vertex_graph(mesh)
    order, sizes = level_blocks(graph)
    assert sorted(order.tolist()) == list(range(mesh.num_vertices)) and sizes.sum() == mesh.num_vertices
    block = np.repeat(np.arange(len(sizes)), sizes)[np.argsort(order)]
    rows, cols = graph.nonzero()
    assert np.abs(block[rows] - block[cols]).max() <= 1
    assert len(sizes) > 2
    pattern = BlockPattern.build(mesh, 1)
    layout = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, mesh.num_vertices, 1)
    assert layout.flops_ratio() < max_flops_ratio


def test_sweeps_along_the_principal_axes_slice_a_box_into_planes_and_never_cost_more():
    """With the rest positions, a sweep from the whole lowest end along each principal axis competes with
    the corner's shells: the FEM benchmark's box (10 x 8 x 12 vertices) becomes 12 planes of 80 vertices
    across its longest axis (0.39x the flops of the 12 shells of up to 167 around a corner), still block
    tridiagonal; on the fTetWild test meshes the chosen structure never costs more flops than the shells."""
    from pathlib import Path

    box = fem.TetMesh.box(size=(0.05, 0.04, 0.06), divisions=(9, 7, 11))
    graph = _vertex_graph(box)
    order, sizes = level_blocks(graph, box.points)
    assert sizes.tolist() == [80] * 12
    block = np.repeat(np.arange(len(sizes)), sizes)[np.argsort(order)]
    z = box.points[:, 2]
    assert np.unique(z[order[:80]]).tolist() in ([z.min()], [z.max()])  # the first plane: an end face
    for k in range(12):  # each block is one plane across z
        assert len(np.unique(np.round(z[block == k], 9))) == 1
    rows, cols = graph.nonzero()
    assert np.abs(block[rows] - block[cols]).max() <= 1
    pattern = BlockPattern.build(box, 1)
    shells = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, box.num_vertices, 1)
    planes = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, box.num_vertices, 1, box.points)
    assert planes.flops_ratio() < 0.4 * shells.flops_ratio()
    for path in sorted((Path(__file__).parent / "data").glob("*_ftetwild.vtu")):
        mesh = fem.TetMesh.load(path)
        pattern = BlockPattern.build(mesh, 1)
        graph_only, swept = (
            BlockTridiagonalLayout.build(pattern.rows, pattern.cols, mesh.num_vertices, 1, points)
            for points in (None, mesh.points)
        )
        assert swept.flops_ratio() <= graph_only.flops_ratio() + 1e-12, path.name


def test_disconnected_components_are_ordered_one_after_the_other():
    mesh = _two_boxes()
    order, sizes = level_blocks(_vertex_graph(mesh))
    first = 3 * 3 * 4  # vertices of the first box
    bounds = np.cumsum(sizes)
    assert first in bounds  # a block boundary between the components
    assert set(order[:first].tolist()) == set(range(first))


@pytest.mark.parametrize("explicit_inverse", [False, True])
@pytest.mark.parametrize("lu", [False, True])
def test_factor_of_a_block_tridiagonal_matrix_with_border_matches_numpy(lu, explicit_inverse):
    """The layout scatters a BSR matrix into blocks; the factor solves it (several right-hand sides, a
    subset of its problems) as numpy does, with triangular solves or with the Cholesky blocks' inverses
    (CUDA's default; block LU keeps its solves). Block Cholesky flags the problem that is not positive
    definite; block LU solves it too."""
    from fem_helpers import symmetric_pattern_matrices

    mesh = fem.TetMesh.box(size=(0.02, 0.02, 0.04), divisions=(2, 2, 5))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    layout = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, pattern.num_vertices, pattern.num_dofs)
    assert layout.num_blocks > 2 and layout.border == 6
    rng = np.random.default_rng(1)
    definite = [True, False, True]
    dense, values = symmetric_pattern_matrices(pattern, 3, definite, rng)
    packed = _pack(layout, values, 3)
    factor = BlockTridiagonalFactor(layout, packed, lu=lu, explicit_inverse=explicit_inverse)
    assert factor.explicit_inverse == (explicit_inverse and not lu)
    assert factor.failed.tolist() == [False, not lu, False]
    n = dense.shape[1]
    problems = [2, 1, 0] if lu else [2, 0]
    rhs = rng.normal(size=(len(problems), n, 2))
    x = factor.solve(torch.as_tensor(rhs), torch.as_tensor(problems)).numpy()
    for k, b in enumerate(problems):
        reference = np.linalg.solve(dense[b], rhs[k])
        assert np.linalg.norm(x[k] - reference) < 1e-10 * np.linalg.norm(reference)


def test_explicit_inverses_solve_ill_conditioned_positive_definite_matrices_as_triangular_solves_do():
    """Stiffness-like conditioning (a soft mode 1e-7 of the stiffest, rows scaled over three decades as
    mixed moduli and contact penalties do): the Cholesky blocks' inverses (CUDA's default) are as accurate
    as triangular solves, both near numpy."""
    from fem_helpers import symmetric_pattern_matrices

    mesh = fem.TetMesh.box(size=(0.02, 0.02, 0.04), divisions=(2, 2, 5))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    layout = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, pattern.num_vertices, pattern.num_dofs)
    rng = np.random.default_rng(4)
    dense, _ = symmetric_pattern_matrices(pattern, 2, [False, False], rng)
    n = dense.shape[1]
    for b in range(2):  # shift the spectrum to [1e-7, 1] x its width, then scale rows and columns
        eigenvalues = np.linalg.eigvalsh(dense[b])
        dense[b] += np.eye(n) * (1e-7 * (eigenvalues[-1] - eigenvalues[0]) - eigenvalues[0])
        scale = 10.0 ** rng.uniform(-3, 0, size=n)
        dense[b] *= scale[:, None] * scale[None, :]
    assert min(np.linalg.cond(d) for d in dense) > 1e9
    values = np.stack(
        [
            dense[b][3 * r : 3 * r + 3, 3 * c : 3 * c + 3]
            for b in range(2)
            for r, c in zip(pattern.rows, pattern.cols)
        ]
    )
    packed = _pack(layout, values, 2)
    rhs = torch.as_tensor(rng.normal(size=(2, n, 2)))
    errors = {}
    for explicit in (False, True):
        factor = BlockTridiagonalFactor(layout, packed, explicit_inverse=explicit)
        assert not factor.failed.any()
        x = factor.solve(rhs).numpy()
        # normwise backward error |A x - b| / (|A| |x| + |b|) and forward error against numpy
        errors[explicit] = [
            (
                np.linalg.norm(A @ xb - r) / (np.linalg.norm(A, 2) * np.linalg.norm(xb) + np.linalg.norm(r)),
                np.linalg.norm(xb - np.linalg.solve(A, r)) / np.linalg.norm(xb),
            )
            for A, xb, r in zip(dense, x, rhs.numpy())
        ]
    for (backward, forward), (backward_ref, forward_ref) in zip(errors[True], errors[False]):
        assert backward_ref < 1e-14 and backward < 1e-14
        assert forward < 10 * forward_ref + 1e-12


def test_banded_and_dense_solvers_reach_the_same_squeeze_equilibria():
    """Two Franka-like pads squeeze a box (force-controlled travel row: the border) with friction, for
    both material models: the banded solver's equilibria equal the dense solver's to round-off, and so do
    those of the dense_banded solver, which factors both problems banded and a lone one densely."""
    from fem_helpers import box_pad

    mesh = fem.TetMesh.box(size=(0.02, 0.015, 0.025), divisions=(4, 3, 5), origin=(-0.01, -0.0075, -0.0125))
    v, f = box_pad((0.012, 0.008, 0.012))
    results = {}
    for model in fem.MATERIAL_MODELS:
        for linear_solver in ("dense", "banded", "dense_banded"):
            bodies = [
                fem.RigidBody(
                    name,
                    fem.TriangleMesh(v, f),
                    control=fem.Control.force((0, -s, 0), dof="grip"),
                    friction=0.7,
                )
                for name, s in (("left", 1), ("right", -1))
            ]
            solver = fem.QuasiStaticSolver(
                mesh,
                bodies,
                fem.Material(1e5, 0.3, 1000.0, model=model),
                batch_size=2,
                device="cpu",
                options=fem.SolverOptions(linear_solver=linear_solver, banded_min_problems=2),
            )
            for name, s in (("left", 1), ("right", -1)):
                T = np.tile(np.eye(4), (2, 1, 1))
                T[:, 1, 3] = s * (0.0075 + 0.004)
                T[1, 0, 3] = 0.002  # off-centre grasp: the object turns
                solver.set_body_pose(name, T)
            eq = solver.ramp(3, targets={"grip": np.array([1.0, 2.0])})[-1]
            eq.require_converged()
            results[model, linear_solver] = eq
        a = results[model, "dense"]
        for b in (results[model, "banded"], results[model, "dense_banded"]):
            np.testing.assert_allclose(
                b.displacement, a.displacement, atol=1e-8 * np.abs(a.displacement).max()
            )
            np.testing.assert_allclose(b.travel["grip"], a.travel["grip"], rtol=1e-8)


def test_sealed_membrane_poke_with_the_banded_solver_equals_the_direct_one():
    """The tactile sensor's closed gas cavity adds a rank-one stiffness (a second solve with the same
    factors, Sherman-Morrison) and its clamped rim fixes rows: a pole poke gives the same wrench and gas
    pressure with the banded solver as with SuperLU."""
    from fem_helpers import sealed_pole_poke

    readings = {}
    for linear_solver in ("direct", "banded"):
        sim, readings[linear_solver] = sealed_pole_poke(8, 0.006, linear_solver=linear_solver)
        assert sim.solver.linear_solver == linear_solver
        assert readings[linear_solver].converged
    a, b = readings["direct"], readings["banded"]
    assert a.contact_force[2] > 0.1  # N: a real poke
    np.testing.assert_allclose(b.contact_force, a.contact_force, rtol=0, atol=1e-6 * a.contact_force[2])
    assert b.gauge_pressure == pytest.approx(a.gauge_pressure, rel=1e-8)


def test_graph_batch_sizes_are_powers_of_two_and_their_halves_padding_at_most_a_third():
    from defgraspnets.fem.block_tridiagonal import graph_batch_size

    sizes = [graph_batch_size(g) for g in range(1, 300)]
    assert sorted(set(sizes)) == [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384]
    for g, size in zip(range(1, 300), sizes):
        assert g <= size and (size - g) <= size / 3, g  # never smaller, at most a third padding
        assert size == min(s for s in set(sizes) if s >= g)  # the smallest class that holds g
    with pytest.raises(ValueError, match="problems"):
        graph_batch_size(0)


def _pack(layout, values, batch: int):
    """(batch, layout.size) CPU tensor: the layout's blocks of ``batch`` problems' BSR block values
    (batch * nnz, 3, 3), problem-major."""
    flat = torch.as_tensor(values.reshape(batch, -1))
    packed = torch.zeros(batch, layout.size, dtype=torch.float64)
    packed[:, torch.as_tensor(layout.target)] = flat[:, torch.as_tensor(layout.source)]
    return packed


def _packed_problems(batch: int, definite, seed: int = 1):
    """(layout, packed (batch, size) CPU tensor, dense matrices) of random block-tridiagonal problems with a
    travel border."""
    from fem_helpers import symmetric_pattern_matrices

    mesh = fem.TetMesh.box(size=(0.02, 0.02, 0.04), divisions=(2, 2, 5))
    pattern = BlockPattern.build(mesh, num_dofs=2)
    layout = BlockTridiagonalLayout.build(pattern.rows, pattern.cols, pattern.num_vertices, pattern.num_dofs)
    dense, values = symmetric_pattern_matrices(pattern, batch, definite, np.random.default_rng(seed))
    packed = _pack(layout, values, batch)
    return layout, packed, dense


def test_the_graphs_padding_problem_is_the_identity_and_factors_to_identities():
    """A CUDA graph's unused rows hold one packed identity matrix per problem (``FactorGraphs._padding_row``):
    its factorization does not fail, its blocks' inverses are identities, its couplings and border zero,
    and it solves to its right-hand side (it must neither break a batch nor cost a fallback)."""
    from defgraspnets.fem.block_tridiagonal import FactorGraphs, _factorize

    layout, _, _ = _packed_problems(1, [True])
    row = FactorGraphs(layout, 0.1)._padding_row(torch.device("cpu"))
    assert row.sum() == layout.vertex_scalars + layout.border  # ones on the diagonal only
    diagonal, coupling, Z, S, failed = _factorize(layout, row.expand(2, -1).clone(), False, True)
    assert not failed.any()
    for block, size in zip(diagonal, layout.sizes.tolist()):
        torch.testing.assert_close(block, torch.eye(size, dtype=torch.float64).expand(2, -1, -1))
    assert all(float(x.abs().max()) == 0 for x in coupling[1:]) and float(Z.abs().max()) == 0
    torch.testing.assert_close(S, torch.eye(layout.border, dtype=torch.float64).expand(2, -1, -1))
    factor = BlockTridiagonalFactor(layout, row.expand(1, -1).clone(), explicit_inverse=True)
    b = torch.randn(1, layout.vertex_scalars + layout.border, dtype=torch.float64)
    torch.testing.assert_close(factor.solve(b), b)


def test_factor_graphs_are_a_cuda_setting_and_a_solve_only_fraction():
    """SolverOptions.factor_graphs is a memory fraction in [0, 1] (named errors otherwise); the CPU's
    banded solver never makes graphs whatever it says."""
    from defgraspnets.fem.system import BatchedSystem
    from defgraspnets.grasp.datagen import _SOLVE_ONLY_FIELDS

    for bad in (-0.1, 1.5, True, None, "0.1", float("nan")):
        with pytest.raises(ValueError, match="factor_graphs"):
            fem.SolverOptions(factor_graphs=bad)
    assert fem.SolverOptions().factor_graphs == 0.1 and fem.SolverOptions(factor_graphs=0).factor_graphs == 0
    assert "factor_graphs" in _SOLVE_ONLY_FIELDS
    mesh = fem.TetMesh.box(size=(0.02, 0.02, 0.04), divisions=(2, 2, 5))
    system = BatchedSystem(BlockPattern.build(mesh, num_dofs=2), 2, "cpu")
    system.factor_graphs = 0.5
    assert system._graphs() is None and system.factor_graph_counts() is None
    with pytest.raises(ValueError, match="memory_fraction"):
        from defgraspnets.fem.block_tridiagonal import FactorGraphs

        FactorGraphs(system.banded_layout(), 0.0)


@pytest.mark.gpu
def test_cuda_graph_factors_equal_eager_ones_and_survive_later_replays():
    """Replayed CUDA graphs factor batches of 5 and 3 problems (padded to 6 and 3) as the eager code does
    (to round-off), flag the problem that is not positive definite, and a factor kept from the first
    replay still solves its problems after a second replay of the same graph (its rows were copied out);
    a memory budget too small for a graph, or a batch above ``max_problems``, factors eagerly."""
    from defgraspnets.fem.block_tridiagonal import FactorGraphs

    definite = [True, True, False, True, True]
    layout, packed, dense = _packed_problems(5, definite)
    packed = packed.cuda()
    graphs = FactorGraphs(layout, 0.5)
    first = BlockTridiagonalFactor(layout, packed, graphs=graphs)
    eager = BlockTridiagonalFactor(layout, packed)
    assert graphs.captures == 1 and graphs.replays == 1 and graphs.bytes == 2 * 8 * layout.size * 6
    assert first.failed.tolist() == eager.failed.tolist() == [not d for d in definite]
    rows = torch.as_tensor([0, 1, 3, 4], device="cuda")
    n = dense.shape[1]
    rhs = torch.randn(4, n, 2, dtype=torch.float64, device="cuda")
    x_first = first.solve(rhs, rows)
    torch.testing.assert_close(x_first, eager.solve(rhs, rows), rtol=1e-10, atol=1e-14)
    # another batch through the same graph (5 and 6 problems share the size class 6), then a new class
    _, other, other_dense = _packed_problems(6, [True] * 6, seed=2)
    second = BlockTridiagonalFactor(layout, other.cuda(), graphs=graphs)
    third = BlockTridiagonalFactor(layout, other[:3].cuda(), graphs=graphs)
    assert graphs.captures == 2 and graphs.replays == 3
    torch.testing.assert_close(first.solve(rhs, rows), x_first, rtol=0, atol=0)  # untouched by the replays
    b = torch.randn(6, n, dtype=torch.float64, device="cuda")
    for factor, count in ((second, 6), (third, 3)):
        x = factor.solve(b[:count]).cpu().numpy()
        for k in range(count):
            reference = np.linalg.solve(other_dense[k], b[k].cpu().numpy())
            assert np.linalg.norm(x[k] - reference) < 1e-10 * np.linalg.norm(reference)
    for k, p in enumerate(rows.tolist()):
        reference = np.linalg.solve(dense[p], rhs[k].cpu().numpy())
        assert np.linalg.norm(x_first[k].cpu().numpy() - reference) < 1e-10 * np.linalg.norm(reference)
    tiny = FactorGraphs(layout, 1e-12)
    assert tiny.factor(packed) is None and tiny.captures == 0
    few = FactorGraphs(layout, 0.5, max_problems=4)  # more problems than that: eager
    assert few.factor(packed) is None and few.captures == 0 and few.factor(packed[:4]) is not None
    made = BlockTridiagonalFactor(layout, packed, graphs=tiny)  # eager
    torch.testing.assert_close(made.solve(rhs, rows), x_first, rtol=1e-10, atol=1e-14)


@pytest.mark.gpu
def test_cuda_squeeze_with_factor_graphs_reaches_the_eager_equilibria():
    """The banded solver's squeeze ramp (two pads, friction, a force-controlled travel border) with CUDA
    graphs of its factorization reaches the equilibria of the eager factorization to round-off, replaying
    graphs for its factorizations."""
    from fem_helpers import pad_squeeze_solver

    results = {}
    for fraction in (0.0, 0.1):
        # off-centre grasps: the object turns
        solver = pad_squeeze_solver(
            np.linspace(-0.002, 0.002, 5), device="cuda", linear_solver="banded", factor_graphs=fraction
        )
        eq = solver.ramp(3, targets={"grip": np.linspace(1.0, 3.0, 5)})[-1]
        eq.require_converged()
        counts = solver.system.factor_graph_counts()
        assert (counts is None) == (fraction == 0)
        if counts is not None:
            assert counts["replays"] > 0 and counts["captures"] >= 1 and counts["bytes"] > 0
        results[fraction] = eq
    a, b = results[0.0], results[0.1]
    np.testing.assert_allclose(b.displacement, a.displacement, atol=1e-8 * np.abs(a.displacement).max())
    np.testing.assert_allclose(b.travel["grip"], a.travel["grip"], rtol=1e-8)
