"""The DefGraspNets multigraph: contact edges vs brute force, topology, batching, features."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_data_synthetic import box_object, grasp_poses, pad_fingers
from torch_geometric.data import Batch

from defgraspnets.fem.mesh import TetMesh
from defgraspnets.models import graph as graph_module
from defgraspnets.models.graph import (
    NODE_FINGER,
    NODE_INTERIOR,
    NODE_SURFACE,
    FingerTemplate,
    MultigraphFeaturizer,
    ObjectTemplate,
    build_grasp_batch,
    build_grasp_graph,
    contact_pairs,
    directed,
    unique_edges,
)


def _brute(a: np.ndarray, b: np.ndarray, r: float) -> set:
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return {(int(i), int(j)) for i, j in np.argwhere(d < r)}


def test_directed_edges_are_both_directions_ordered_by_target():
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    undirected = unique_edges(tets)
    e = directed(undirected).numpy()
    assert e.shape == (2, 2 * len(undirected))
    # every undirected edge in both directions, each directed edge once
    both_ways = [(i, j) for i, j in undirected] + [(j, i) for i, j in undirected]
    assert sorted(map(tuple, e.T)) == sorted(both_ways)
    # ordered by target, then source: a node's incoming edges are contiguous
    key = e[1] * 10 + e[0]
    assert np.all(np.diff(key) > 0)
    assert directed(np.zeros((0, 2), dtype=np.int64)).shape == (2, 0)


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_contact_pairs_match_brute_force(backend):
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.02, 0.02, size=(300, 3))
    b = rng.uniform(-0.02, 0.02, size=(2, 80, 3))
    b[0, 0] = a[0] + np.array([0.005, 0.0, 0.0])  # exactly at eps: excluded ("closer than")
    got = contact_pairs(torch.as_tensor(a), torch.as_tensor(b), 0.005, backend=backend).numpy()
    for gi in range(2):
        want = _brute(a, b[gi], 0.005)
        assert len(want) > 20
        assert {(int(i), int(j)) for _, i, j in got[got[:, 0] == gi]} == want
    assert (0, 0) not in {(int(i), int(j)) for g, i, j in got if g == 0}
    single = contact_pairs(torch.as_tensor(a), torch.as_tensor(b[1]), 0.005, backend=backend).numpy()
    assert {tuple(map(int, p)) for p in single} == _brute(a, b[1], 0.005)


@pytest.mark.skipif(
    not graph_module._triton_runs(torch.zeros(1, device="cuda" if torch.cuda.is_available() else "cpu")),
    reason="needs Triton on CUDA or its CPU interpreter (TRITON_INTERPRET=1, set by conftest without CUDA)",
)
def test_triton_contact_pairs_equal_the_torch_backend_in_float32():
    """The kernel's exact float32 distances give the pairs of the GEMM backend's exact recheck, in its
    lexicographic order, for a batch and for one grasp; float64 positions are refused."""
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    rng = np.random.default_rng(1)
    a = torch.as_tensor(rng.uniform(-0.02, 0.02, size=(130, 3)), dtype=torch.float32, device=dev)
    b = torch.as_tensor(rng.uniform(-0.02, 0.02, size=(3, 70, 3)), dtype=torch.float32, device=dev)
    want = contact_pairs(a, b, 0.005, backend="torch")
    got = contact_pairs(a, b, 0.005, backend="triton")
    assert len(want) > 50
    assert torch.equal(got, want)
    assert torch.equal(contact_pairs(a, b[2], 0.005, backend="triton"), want[want[:, 0] == 2][:, 1:])
    assert contact_pairs(a, b[:, :0], 0.005, backend="triton").shape == (0, 3)
    with pytest.raises(ValueError, match="float32"):
        contact_pairs(a.double(), b.double(), 0.005, backend="triton")


def _grasp(divisions=(4, 3, 3), g=0):
    obj = box_object("o", divisions=divisions)
    _, fpose, cdir = grasp_poses(obj, g + 1, 0)
    fingers = pad_fingers()
    fpos = torch.as_tensor(fingers.vertices_at(fpose[g]), dtype=torch.float64)
    return obj, fingers, fpos, torch.as_tensor(cdir[g])


def test_single_graph_topology_and_contacts():
    obj, fingers, fpos, cdir = _grasp()
    ot = ObjectTemplate.from_mesh(obj.points, obj.tets, obj.surface_faces, dtype=torch.float64)
    ft = FingerTemplate.from_mesh(fingers.vertices, fingers.faces, dtype=torch.float64)
    g = build_grasp_graph(ot, ft, fpos, cdir, 5.0, 1e5, contact_radius=0.005)
    n, v = len(obj.points), len(fingers.vertices)
    assert g.num_nodes == n + 2 * v
    mesh = TetMesh(obj.points, obj.tets)
    want_type = np.where(mesh.is_surface_vertex, NODE_SURFACE, NODE_INTERIOR)
    np.testing.assert_array_equal(g.node_type[:n].numpy(), want_type)
    assert (
        (g.node_type[n:] == NODE_FINGER).all()
        and (g.finger_id[n : n + v] == 0).all()
        and (g.finger_id[n + v :] == 1).all()
    )
    assert (g.closing_dir[:n] == 0).all() and torch.allclose(g.closing_dir[n + v :], cdir[1].expand(v, 3))
    # mesh edges: object tet edges + both finger triangle edge sets, both directions, never across parts
    n_edges = len(mesh.edges) + 2 * len(unique_edges(fingers.faces))
    assert g.mesh_edge_index.shape == (2, 2 * n_edges)
    src, dst = g.mesh_edge_index
    assert ((src < n) == (dst < n)).all()
    pairs = set(map(tuple, g.mesh_edge_index.T.tolist()))
    assert all((j, i) in pairs for i, j in pairs)
    # contact edges: exactly the object/finger pairs closer than 5 mm, both directions
    want = _brute(obj.points, fpos.reshape(-1, 3).numpy(), 0.005)
    assert len(want) > 0
    c = g.contact_edge_index.T.tolist()
    got = {(i, j - n) for i, j in c if i < n} | set()
    back = {(j, i - n) for i, j in c if i >= n}
    assert got == want and back == want and len(c) == 2 * len(want)


def test_pyg_batching_matches_vectorized_batch():
    obj, fingers, _, _ = _grasp()
    _, fpose, cdir = grasp_poses(obj, 2, 3)
    ot = ObjectTemplate.from_mesh(obj.points, obj.tets, obj.surface_faces, dtype=torch.float64)
    ft = FingerTemplate.from_mesh(fingers.vertices, fingers.faces, dtype=torch.float64)
    fpos = torch.as_tensor(fingers.vertices_at(fpose))
    singles = [
        build_grasp_graph(
            ot, ft, fpos[i], torch.as_tensor(cdir[i]), 3.0 + i, 1e4 * 10**i, contact_backend="kdtree"
        )
        for i in range(2)
    ]
    batch = Batch.from_data_list(singles)
    vec = build_grasp_batch(
        ot,
        ft,
        fpos,
        torch.as_tensor(cdir),
        torch.tensor([3.0, 4.0]),
        torch.tensor([1e4, 1e5]),
        contact_backend="torch",
    )
    for key in (
        "pos",
        "node_type",
        "finger_id",
        "closing_dir",
        "mesh_edge_index",
        "force",
        "youngs_modulus",
        "batch",
    ):
        assert torch.equal(batch[key], vec[key]), key
    # contact edges: same sets (orderings may differ)
    assert sorted(map(tuple, batch.contact_edge_index.T.tolist())) == sorted(
        map(tuple, vec.contact_edge_index.T.tolist())
    )
    n = singles[0].num_nodes
    assert batch.contact_edge_index[:, batch.contact_edge_index[0] >= n].min() >= n


def test_features_force_distribution_and_modulus():
    obj, fingers, _, _ = _grasp()
    _, fpose, cdir = grasp_poses(obj, 2, 5)
    ot = ObjectTemplate.from_mesh(obj.points, obj.tets, obj.surface_faces, dtype=torch.float64)
    ft = FingerTemplate.from_mesh(fingers.vertices, fingers.faces, dtype=torch.float64)
    g = build_grasp_batch(
        ot,
        ft,
        torch.as_tensor(fingers.vertices_at(fpose)),
        torch.as_tensor(cdir),
        torch.tensor([6.0, 9.0]),
        torch.tensor([1e4, 1e6]),
    )
    node, mesh, contact = MultigraphFeaturizer()(g)
    assert node.shape == (g.num_nodes, 9) and mesh.shape[1] == 5 and contact.shape[1] == 5
    src, dst = g.contact_edge_index
    for b, force in enumerate((6.0, 9.0)):
        on = g.batch[dst] == b
        pairs = int(on.sum()) // 2
        assert torch.allclose(contact[on, 4], torch.tensor(force / pairs, dtype=torch.float64))
    rel = g.pos[dst] - g.pos[src]
    assert torch.allclose(contact[:, :3], rel) and torch.allclose(contact[:, 3], rel.norm(dim=1))
    msrc = g.mesh_edge_index[0]
    obj_edge = g.node_type[msrc] != NODE_FINGER
    want = torch.log10(torch.tensor([1e4, 1e6], dtype=torch.float64))[g.batch[msrc]]
    assert torch.allclose(mesh[obj_edge, 4], want[obj_edge]) and (mesh[~obj_edge, 4] == 0).all()
    # ablations V3 / V4
    _, _, c3 = MultigraphFeaturizer(force_feature="total")(g)
    assert torch.allclose(c3[:, 4], torch.tensor([6.0, 9.0], dtype=torch.float64)[g.batch[dst]])
    n4, _, c4 = MultigraphFeaturizer(force_on="nodes")(g)
    assert n4.shape[1] == 10 and c4.shape[1] == 4
    with pytest.raises(ValueError, match="force_feature"):
        MultigraphFeaturizer(force_feature="per_node")


def test_features_are_differentiable_wrt_finger_positions():
    obj, fingers, fpos, cdir = _grasp()
    ot = ObjectTemplate.from_mesh(obj.points, obj.tets, obj.surface_faces, dtype=torch.float64)
    ft = FingerTemplate.from_mesh(fingers.vertices, fingers.faces, dtype=torch.float64)
    fpos = fpos.clone().requires_grad_(True)
    g = build_grasp_graph(ot, ft, fpos, cdir, 5.0, 1e5)
    node, mesh, contact = MultigraphFeaturizer()(g)
    (contact[:, 3].sum() + node[:, 3:6].square().sum()).backward()
    assert fpos.grad is not None and torch.isfinite(fpos.grad).all()
    in_contact = torch.unique(g.contact_edge_index[1][g.contact_edge_index[1] >= len(obj.points)]) - len(
        obj.points
    )
    assert fpos.grad.reshape(-1, 3)[in_contact].abs().sum() > 0
