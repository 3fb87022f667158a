r"""The DefGraspNets multigraph (thesis §7.3): object tet mesh + two finger-pad meshes + contact edges.

A grasp state ``X = (M_o, M_g, F_g)`` (object rest mesh, finger meshes at first contact, total normal grasp
force) and the object's Young's modulus ``E`` become a multigraph ``G = (V, E^M, E^C)``:

Nodes ``V``: the N object vertices first, then the V vertices of finger 0, then the V of finger 1.
    features ``x_i = [onehot(type_i) (3), p_i (3), c_i (3)]`` with type in (finger, object surface,
    object interior), position ``p_i`` [m] in the object frame and the unit closing direction ``c_i`` of
    the node's finger (zero for object nodes). Ablation V4 (``force_on="nodes"``) appends the force scalar.
Mesh edges ``E^M`` (both directions): object tet edges and finger triangle edges,
    ``e_ij = [p_i - p_j (3), |p_i - p_j| (1), log10(E) (1)]``; the modulus channel is zero on finger edges.
    ``log10 E`` rather than ``E``: moduli span 1e4..1e7 Pa and the response scales like ``1/E``, so the
    logarithm makes the feature-to-target map smooth and keeps the standardized feature O(1) for every
    material (a linear ``E`` would squash all but the stiffest materials to ~0 after standardization).
Contact edges ``E^C`` (both directions): every (object node, finger node) pair closer than ``eps = 5 mm`` at
    first contact, ``e_ij = [p_i - p_j (3), |p_i - p_j| (1), F_g / |E^C| (1)]``. Ablation V3
    (``force_feature="total"``) uses ``F_g``; V4 drops the force channel here and puts it on the nodes.

Edge ``(j -> i)`` is stored as column ``[j, i]`` of an index (source row 0, target row 1, PyG convention)
and ``p_i - p_j`` is "target minus source". Contact-edge *selection* is discrete (computed on detached
positions); all features are computed from ``pos`` by :class:`MultigraphFeaturizer` inside the model, so they
are differentiable w.r.t. finger vertex positions (and through them w.r.t. the gripper pose).

Static shapes (``torch.compile`` without recompiles): :func:`build_grasp_batch` can pad the contact edge set
to a fixed capacity. Padding edges are self-loops on node 0 with ``contact_mask`` False; the network zeroes
their messages and the force feature does not count them, so every output equals the unpadded one.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn
from torch_geometric.data import Data

from defgraspnets.models.fused_message_passing import tl, triton, triton_interpreting

__all__ = [
    "NODE_FINGER",
    "NODE_INTERIOR",
    "NODE_SURFACE",
    "FingerTemplate",
    "GraspGraph",
    "MultigraphFeaturizer",
    "ObjectTemplate",
    "build_grasp_batch",
    "build_grasp_graph",
    "contact_pairs",
    "directed",
    "unique_edges",
]

NODE_FINGER, NODE_SURFACE, NODE_INTERIOR = 0, 1, 2
NUM_NODE_TYPES = 3
DEFAULT_CONTACT_RADIUS = 5e-3  # eps [m], thesis §7.4


# ---------------------------------------------------------------------------------------------- topology
def unique_edges(cells: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges ``i < j`` of tets (M, 4) or triangles (T, 3)."""
    cells = np.asarray(cells, dtype=np.int64)
    if cells.ndim != 2 or cells.shape[1] not in (3, 4):
        raise ValueError(f"cells must be (M, 4) tets or (T, 3) triangles, got shape {cells.shape}")
    c = cells.shape[1]
    a, b = np.triu_indices(c, k=1)
    e = np.sort(np.stack([cells[:, a], cells[:, b]], axis=-1).reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def directed(edges: np.ndarray | Tensor) -> Tensor:
    """(2, 2E) long: both directions of undirected edges (E, 2), ordered by target node, then source.

    The order changes no result (messages are summed per target up to the order of float sums); it puts a
    node's incoming edges next to each other, so that the fused message-passing kernel's atomic additions
    to one node's sum come from one tile (:mod:`.fused_message_passing`; H100, bf16, 100 copies of a
    1573-vertex box: edge update 1.67 -> 1.58 ms per block)."""
    e = torch.as_tensor(np.asarray(edges), dtype=torch.long).reshape(-1, 2)
    both = torch.cat([e.T, e.flip(1).T], dim=1)
    if both.shape[1] == 0:
        return both
    order = torch.argsort(both[1] * (int(both.max()) + 1) + both[0])
    return both[:, order]


@dataclass(frozen=True)
class ObjectTemplate:
    """Everything of the object part of the multigraph that does not depend on the grasp.

    Attributes:
        points: (N, 3) rest positions [m]. node_type: (N,) NODE_SURFACE or NODE_INTERIOR.
        mesh_edge_index: (2, E_o) directed tet edges.
    """

    points: Tensor
    node_type: Tensor
    mesh_edge_index: Tensor

    @classmethod
    def from_mesh(cls, points, tets, surface_faces=None, dtype=torch.float32) -> ObjectTemplate:
        """From rest points (N, 3) [m], tets (M, 4) and optionally the (F, 3) surface (else derived)."""
        points = np.array(points, dtype=np.float64)
        tets = np.asarray(tets, dtype=np.int64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"object points must be (N, 3), got {points.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4 or tets.min() < 0 or tets.max() >= len(points):
            raise ValueError(f"object tets must be (M, 4) indices into {len(points)} points")
        if surface_faces is None:
            from defgraspnets.fem.mesh import TetMesh

            surface_faces = TetMesh(points.copy(), tets.copy()).surface_faces  # TetMesh freezes its arrays
        on_surface = np.zeros(len(points), dtype=bool)
        on_surface[np.asarray(surface_faces, dtype=np.int64).ravel()] = True
        node_type = np.where(on_surface, NODE_SURFACE, NODE_INTERIOR)
        return cls(
            torch.as_tensor(points, dtype=dtype),
            torch.as_tensor(node_type, dtype=torch.long),
            directed(unique_edges(tets)),
        )

    @classmethod
    def from_tet_mesh(cls, mesh, dtype=torch.float32) -> ObjectTemplate:
        """From a :class:`defgraspnets.fem.TetMesh`."""
        return cls.from_mesh(mesh.points, mesh.tets, mesh.surface_faces, dtype=dtype)

    @property
    def num_nodes(self) -> int:
        return self.points.shape[0]


@dataclass(frozen=True)
class FingerTemplate:
    """The finger-pad surface mesh (same for both fingers). vertices: (V, 3) finger frame [m];
    mesh_edge_index: (2, E_f) directed triangle edges."""

    vertices: Tensor
    mesh_edge_index: Tensor

    @classmethod
    def from_mesh(cls, vertices, faces, dtype=torch.float32) -> FingerTemplate:
        vertices = np.array(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"finger vertices must be (V, 3), got {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"finger faces must be (T, 3) indices into {len(vertices)} vertices")
        return cls(torch.as_tensor(vertices, dtype=dtype), directed(unique_edges(faces)))

    @property
    def num_nodes(self) -> int:
        return self.vertices.shape[0]


# ---------------------------------------------------------------------------------------------- contacts
def _kdtree_pairs(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    m = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
    m = m[m["v"] < radius]
    return np.stack([m["i"], m["j"]], axis=1).astype(np.int64)


if triton is not None:

    @triton.jit
    def _contact_mask_kernel(
        object_ptr,  # (N, 3) object node positions
        finger_ptr,  # (G, P, 3) finger node positions
        out_ptr,  # (G, N, P) int8: |x_i - y_j|^2 < r^2
        N,
        P,
        r2,
        BN: tl.constexpr,
        BP: tl.constexpr,
    ):
        g = tl.program_id(0).to(tl.int64)
        i = tl.program_id(1) * BN + tl.arange(0, BN)
        j = tl.program_id(2) * BP + tl.arange(0, BP)
        in_i, in_j = i < N, j < P
        fin = finger_ptr + g * P * 3
        dx = (
            tl.load(object_ptr + i * 3, mask=in_i, other=0.0)[:, None]
            - tl.load(fin + j * 3, mask=in_j, other=0.0)[None, :]
        )
        dy = (
            tl.load(object_ptr + i * 3 + 1, mask=in_i, other=0.0)[:, None]
            - tl.load(fin + j * 3 + 1, mask=in_j, other=0.0)[None, :]
        )
        dz = (
            tl.load(object_ptr + i * 3 + 2, mask=in_i, other=0.0)[:, None]
            - tl.load(fin + j * 3 + 2, mask=in_j, other=0.0)[None, :]
        )
        inside = in_i[:, None] & in_j[None, :]
        hit = (dx * dx + dy * dy + dz * dz < r2) & inside
        out = out_ptr + g * N * P + i[:, None].to(tl.int64) * P + j[None, :]
        tl.store(out, hit.to(tl.int8), mask=inside)


def _triton_contact_pairs(op: Tensor, fp: Tensor, radius: float) -> Tensor:
    """(C, 3) ``[grasp, object_index, finger_index]`` pairs closer than ``radius``: one kernel evaluates
    the exact squared distances of all (G, N, P) pairs and writes an int8 mask (no float32 distance matrix
    in memory), then one ``nonzero`` (lexicographic order)."""
    g, p, n = fp.shape[0], fp.shape[1], op.shape[0]
    mask = torch.empty(g, n, p, dtype=torch.int8, device=fp.device)
    if mask.numel():
        block = 64
        grid = (g, triton.cdiv(n, block), triton.cdiv(p, block))
        _contact_mask_kernel[grid](
            op.contiguous(), fp.contiguous(), mask, n, p, radius * radius, BN=block, BP=block
        )
    return mask.nonzero()


def _triton_runs(x: Tensor) -> bool:
    """Whether the contact kernel runs for positions ``x``: Triton on CUDA (or its interpreter), float32."""
    if triton is None or x.dtype != torch.float32:
        return False
    return x.is_cuda or triton_interpreting()


def contact_pairs(
    object_pos: Tensor,
    finger_pos: Tensor,
    radius: float = DEFAULT_CONTACT_RADIUS,
    backend: str = "auto",
    chunk: int | None = None,
) -> Tensor:
    """Object/finger node pairs closer than ``radius`` (strictly), one grasp or a batch of grasps.

    Args:
        object_pos: (N, 3) object node positions (shared by all grasps) [m].
        finger_pos: (P, 3) finger node positions of one grasp, or (G, P, 3) for G grasps [m].
        radius: contact threshold eps [m].
        backend: ``"kdtree"`` (scipy cKDTree, CPU), ``"torch"`` (batched GEMM distances with an exact
            recheck, on the tensors' device: 3 ms for 100 grasps x 1000 x 450 nodes on an H100), ``"triton"``
            (one kernel of exact float32 distances writing an int8 mask, then ``nonzero``; CUDA, float32),
            ``"torch_cluster"`` (``torch_cluster.radius``; optional package, not exercised by the tests), or
            ``"auto"``: triton on CUDA for float32 positions (torch for others), kdtree on the CPU.
        chunk: max number of distances evaluated at once by the torch backend (default: 2^28 on CUDA, i.e.
            1 GiB of float32, so that a planning batch of 100 grasps is one GEMM and one host sync; 2^24 on
            the CPU).

    Returns:
        (C, 2) long ``[object_index, finger_index]`` for one grasp, or (C, 3) ``[grasp, object_index,
        finger_index]`` for a batch; sorted lexicographically, on ``finger_pos``'s device.
    """
    if radius <= 0:
        raise ValueError(f"contact radius must be positive, got {radius}")
    single = finger_pos.ndim == 2
    fp = finger_pos.detach().unsqueeze(0) if single else finger_pos.detach()
    op = object_pos.detach().to(fp.device)
    g, p, n = fp.shape[0], fp.shape[1], op.shape[0]
    if backend == "auto":
        backend = ("triton" if _triton_runs(fp) else "torch") if fp.is_cuda else "kdtree"
    if chunk is None:
        chunk = 1 << 28 if fp.is_cuda else 1 << 24
    if backend == "kdtree":
        o = op.cpu().double().numpy()
        parts = []
        for i, f in enumerate(fp.cpu().double().numpy()):
            ij = _kdtree_pairs(o, f, radius)
            parts.append(np.concatenate([np.full((len(ij), 1), i, dtype=np.int64), ij], axis=1))
        out = torch.as_tensor(
            np.concatenate(parts) if parts else np.zeros((0, 3), np.int64), device=fp.device
        )
    elif backend == "torch":
        # squared distances |x|^2 + |y|^2 - 2 x.y by batched GEMM (fast), with a margin covering its rounding
        # error, then the exact test |x - y|^2 < r^2 on the few candidates
        centre = op.mean(0)
        x, y = op - centre, fp - centre
        x2, y2 = (x * x).sum(-1), (y * y).sum(-1)
        # (a device scalar: no host sync)
        tol = 16 * torch.finfo(x.dtype).eps * (x2.max() + y2.max()) if n and p else 0.0
        per = max(1, chunk // max(1, n * p))
        parts = []
        for s in range(0, g, per):
            yc = y[s : s + per]
            d2 = torch.baddbmm(
                x2[None, :, None] + y2[s : s + per, None, :],
                x.expand(len(yc), n, 3),
                yc.transpose(1, 2),
                alpha=-2.0,
            )
            idx = (d2 < radius * radius + tol).nonzero()
            exact = (op[idx[:, 1]] - fp[s + idx[:, 0], idx[:, 2]]).square().sum(-1) < radius * radius
            idx = idx[exact]
            idx[:, 0] += s
            parts.append(idx)
        out = torch.cat(parts) if parts else torch.zeros((0, 3), dtype=torch.long, device=fp.device)
    elif backend == "triton":
        if not _triton_runs(fp):
            raise ValueError("contact backend 'triton' needs Triton, float32 positions and a CUDA device")
        out = _triton_contact_pairs(op.to(fp.dtype), fp, radius)
    elif backend == "torch_cluster":
        if importlib.util.find_spec("torch_cluster") is None:
            raise ImportError("contact backend 'torch_cluster' needs the torch-cluster package")
        import torch_cluster

        y = fp.reshape(-1, 3)
        x = op.repeat(g, 1)
        bx = torch.arange(g, device=fp.device).repeat_interleave(n)
        by = torch.arange(g, device=fp.device).repeat_interleave(p)
        row, col = torch_cluster.radius(y, x, radius, batch_x=by, batch_y=bx, max_num_neighbors=1 << 16)
        # torch_cluster.radius(x, y, r) finds for each y the x within r (inclusive): filter strictly
        keep = (x[row] - y[col]).norm(dim=1) < radius
        row, col = row[keep], col[keep]
        out = torch.stack([bx[row], row % n, col % p], dim=1)
    else:
        raise ValueError(f"unknown contact backend {backend!r} (kdtree, torch, triton, torch_cluster, auto)")
    if backend in ("kdtree", "torch_cluster") and len(out):
        # (the torch and triton backends' nonzero already lists the pairs in lexicographic order)
        key = (out[:, 0] * n + out[:, 1]) * p + out[:, 2]
        out = out[torch.argsort(key)]
    return out[:, 1:] if single else out


# ---------------------------------------------------------------------------------------------- data
class GraspGraph(Data):
    """A multigraph (or a batch of them) as a PyG ``Data`` with two edge sets.

    Node attributes (n = N + 2V per graph): ``pos`` (n, 3) [m], ``node_type`` (n,) long, ``closing_dir``
    (n, 3), ``finger_id`` (n,) long (-1 object, 0/1 finger). Edge sets: ``mesh_edge_index`` (2, E_M),
    ``contact_edge_index`` (2, E_C), both incremented by ``num_nodes`` when batched. Graph attributes (one
    entry per graph): ``force`` (1,) F_g [N], ``youngs_modulus`` (1,) E [Pa]. Optional: ``contact_mask``
    (E_C,) bool, False on padding contact edges (see :func:`build_grasp_batch`); targets ``stress``
    (n,) [Pa] and ``displacement`` (n, 3) [m] (finger nodes: rigid finger travel), ``prev_displacement``
    (n, 3) and ``prev_force`` (1,) for multi-step training, ``sample`` (1, 4) long ``(shard, k, g, s)``,
    ``object_id`` (1,) long.
    """

    def __inc__(self, key, value, *args, **kwargs):
        if key in ("mesh_edge_index", "contact_edge_index"):
            return self.num_nodes
        if key in ("sample", "object_id"):
            return 0
        return super().__inc__(key, value, *args, **kwargs)

    def __cat_dim__(self, key, value, *args, **kwargs):
        if key in ("mesh_edge_index", "contact_edge_index"):
            return 1
        if key in ("sample", "force", "youngs_modulus", "prev_force", "object_id"):
            return 0
        return super().__cat_dim__(key, value, *args, **kwargs)

    def to_dtype(self, dtype: torch.dtype) -> GraspGraph:
        """Cast every floating-point attribute to ``dtype`` (in place; returns self)."""
        return self.apply(lambda x: x.to(dtype) if x.is_floating_point() else x)

    @property
    def graph_count(self) -> int:
        """Number of graphs held (1 for a single graph)."""
        return int(self.force.numel())

    def node_graph(self) -> Tensor:
        """(n,) graph index of every node (zeros for a single graph)."""
        b = getattr(self, "batch", None)
        if b is None:
            return torch.zeros(self.num_nodes, dtype=torch.long, device=self.pos.device)
        return b

    @property
    def object_mask(self) -> Tensor:
        return self.node_type != NODE_FINGER

    @property
    def contact_edge_mask(self) -> Tensor | None:
        """(E_C,) bool, False on padding contact edges; None when the contact edges are not padded."""
        return getattr(self, "contact_mask", None)


def build_grasp_batch(
    obj: ObjectTemplate,
    finger: FingerTemplate,
    finger_pos: Tensor,
    closing_direction: Tensor,
    force: Tensor | float,
    youngs_modulus: Tensor | float,
    contact_radius: float = DEFAULT_CONTACT_RADIUS,
    contact_backend: str = "auto",
    pairs: Tensor | None = None,
    contact_capacity: int | None = None,
) -> GraspGraph:
    """G grasp multigraphs of one object, batched (vectorized, no per-graph Python work).

    Args:
        obj, finger: templates.
        finger_pos: (G, 2, V, 3) finger vertices at first contact in the object frame [m]; may require grad.
        closing_direction: (G, 2, 3) unit closing directions.
        force: (G,) or scalar F_g [N]. youngs_modulus: (G,) or scalar E [Pa].
        contact_radius: eps [m]. contact_backend: see :func:`contact_pairs`.
        pairs: precomputed (C, 3) ``[grasp, object_index, finger_index]`` (finger index in [0, 2V)).
        contact_capacity: pad the 2C directed contact edges to this many (>= 2C) so that the edge count
            does not depend on the grasps: the padding edges are self-loops on node 0 and ``contact_mask``
            (False on them) makes the network ignore them exactly. None: no padding, no ``contact_mask``.

    Returns:
        A :class:`GraspGraph` with ``batch`` (n_total,) and ``ptr`` (G + 1,) set (``num_nodes = G (N + 2V)``).
        Layout of each graph: nodes [object N | finger 0 V | finger 1 V], mesh edges [object E_o | finger 0 |
        finger 1]; contact edges [C object -> finger | C finger -> object | padding].
    """
    if finger_pos.ndim != 4 or finger_pos.shape[1] != 2 or finger_pos.shape[3] != 3:
        raise ValueError(f"finger_pos must be (G, 2, V, 3), got {tuple(finger_pos.shape)}")
    g, v = finger_pos.shape[0], finger_pos.shape[2]
    if v != finger.num_nodes:
        raise ValueError(f"finger_pos has {v} vertices per finger but the finger mesh has {finger.num_nodes}")
    if closing_direction.shape != (g, 2, 3):
        raise ValueError(f"closing_direction must be ({g}, 2, 3), got {tuple(closing_direction.shape)}")
    device, dtype = finger_pos.device, finger_pos.dtype
    n_obj = obj.num_nodes
    n = n_obj + 2 * v
    fpos = finger_pos.reshape(g, 2 * v, 3)
    obj_pos = obj.points.to(device=device, dtype=dtype)
    pos = torch.cat([obj_pos.expand(g, n_obj, 3), fpos], dim=1).reshape(g * n, 3)

    node_type = torch.cat([obj.node_type.to(device), torch.full((2 * v,), NODE_FINGER, device=device)])
    finger_id = torch.cat(
        [torch.full((n_obj,), -1, device=device), torch.arange(2, device=device).repeat_interleave(v)]
    )
    closing = torch.cat(
        [
            torch.zeros(g, n_obj, 3, device=device, dtype=dtype),
            closing_direction.to(dtype).repeat_interleave(v, dim=1),
        ],
        dim=1,
    ).reshape(g * n, 3)
    offsets = torch.arange(g, device=device) * n

    fe = finger.mesh_edge_index.to(device)
    edges_one = torch.cat([obj.mesh_edge_index.to(device), fe + n_obj, fe + n_obj + v], dim=1)  # (2, E)
    mesh_edge_index = (edges_one.unsqueeze(1) + offsets.view(1, g, 1)).reshape(2, -1)

    if pairs is None:
        pairs = contact_pairs(obj_pos, fpos, contact_radius, backend=contact_backend)
    pairs = pairs.to(device)
    obj_node = pairs[:, 0] * n + pairs[:, 1]
    fin_node = pairs[:, 0] * n + n_obj + pairs[:, 2]
    # first the C object -> finger edges, then the C finger -> object edges
    contact_edge_index = torch.stack(
        [torch.stack([obj_node, fin_node]), torch.stack([fin_node, obj_node])], 1
    )
    contact_edge_index = contact_edge_index.reshape(2, -1)
    contact_mask = None
    if contact_capacity is not None:
        real = contact_edge_index.shape[1]
        if contact_capacity < real:
            raise ValueError(f"contact_capacity {contact_capacity} < {real} directed contact edges")
        pad = torch.zeros(2, contact_capacity - real, dtype=torch.long, device=device)
        contact_edge_index = torch.cat([contact_edge_index, pad], dim=1)
        contact_mask = torch.arange(contact_capacity, device=device) < real

    def per_graph(x):
        return torch.as_tensor(x, dtype=dtype, device=device).reshape(-1).expand(g).clone()

    out = GraspGraph(
        pos=pos,
        node_type=node_type.repeat(g),
        finger_id=finger_id.repeat(g),
        closing_dir=closing,
        mesh_edge_index=mesh_edge_index,
        contact_edge_index=contact_edge_index,
        force=per_graph(force),
        youngs_modulus=per_graph(youngs_modulus),
        num_nodes=g * n,
    )
    if contact_mask is not None:
        out.contact_mask = contact_mask
    out.batch = torch.arange(g, device=device).repeat_interleave(n)
    out.ptr = torch.arange(g + 1, device=device) * n
    return out


def build_grasp_graph(
    obj: ObjectTemplate,
    finger: FingerTemplate,
    finger_pos: Tensor,
    closing_direction: Tensor,
    force,
    youngs_modulus,
    contact_radius: float = DEFAULT_CONTACT_RADIUS,
    contact_backend: str = "auto",
    pairs: Tensor | None = None,
) -> GraspGraph:
    """One grasp multigraph (no ``batch`` attribute), to be batched by a PyG ``DataLoader``.

    Args as :func:`build_grasp_batch` with ``finger_pos`` (2, V, 3), ``closing_direction`` (2, 3), and
    ``pairs`` (C, 2) ``[object_index, finger_index]``.
    """
    if pairs is not None:
        pairs = torch.cat([torch.zeros(len(pairs), 1, dtype=torch.long), torch.as_tensor(pairs)], dim=1)
    data = build_grasp_batch(
        obj,
        finger,
        finger_pos.unsqueeze(0),
        closing_direction.unsqueeze(0),
        force,
        youngs_modulus,
        contact_radius,
        contact_backend,
        pairs,
    )
    del data.batch, data.ptr
    return data


# ---------------------------------------------------------------------------------------------- features
def _safe_norm(v: Tensor) -> Tensor:
    """(E, 1) Euclidean length with a finite gradient at zero length."""
    return torch.sqrt((v * v).sum(dim=1, keepdim=True) + 1e-20)


class MultigraphFeaturizer(nn.Module):
    """Raw (unnormalized) features of nodes, mesh edges and contact edges, computed from ``pos``.

    Args:
        force_feature: ``"distributed"`` (``F_g / |E^C|`` of the graph, thesis) or ``"total"`` (``F_g``, V3).
        force_on: ``"contact_edges"`` (thesis) or ``"nodes"`` (V4: the force scalar on every node).

    Shapes: node features (n, 9 [+1]), mesh edge features (E_M, 5), contact edge features (E_C, 5 [-1]).
    """

    def __init__(self, force_feature: str = "distributed", force_on: str = "contact_edges"):
        super().__init__()
        if force_feature not in ("distributed", "total"):
            raise ValueError(f"force_feature must be 'distributed' or 'total', got {force_feature!r}")
        if force_on not in ("contact_edges", "nodes"):
            raise ValueError(f"force_on must be 'contact_edges' or 'nodes', got {force_on!r}")
        self.force_feature = force_feature
        self.force_on = force_on

    @property
    def node_dim(self) -> int:
        return 9 + (self.force_on == "nodes")

    @property
    def mesh_edge_dim(self) -> int:
        return 5

    @property
    def contact_edge_dim(self) -> int:
        return 4 + (self.force_on == "contact_edges")

    def graph_force(self, g: GraspGraph, force: Tensor | None = None) -> Tensor:
        """(B,) the per-graph force scalar: ``F_g / max(|E^C|, 1)`` or ``F_g``.

        ``|E^C|`` counts undirected contact edges (object-finger pairs), i.e. half the directed edges; padding
        edges (``contact_mask`` False) are not counted.
        """
        f = g.force if force is None else force
        if self.force_feature == "total":
            return f
        node_graph = g.node_graph()
        dst = g.contact_edge_index[1]
        mask = g.contact_edge_mask
        half = torch.full_like(dst, 0.5, dtype=f.dtype) if mask is None else mask.to(f.dtype) * 0.5
        count = torch.zeros(f.shape[0], device=f.device, dtype=f.dtype)
        count.index_add_(0, node_graph.index_select(0, dst), half)
        return f / count.clamp_min(1.0)

    @staticmethod
    def node_features(
        node_type: Tensor, pos: Tensor, closing_dir: Tensor, force: Tensor | None = None
    ) -> Tensor:
        """(..., 9 [+1]) ``[onehot(type), p, c (, force)]`` of nodes (...,) with positions and closing
        directions (..., 3); ``force`` (...,) only for ``force_on="nodes"``."""
        node = [
            nn.functional.one_hot(node_type, NUM_NODE_TYPES).to(pos.dtype),
            pos,
            closing_dir.to(pos.dtype),
        ]
        if force is not None:
            node.append(force.unsqueeze(-1))
        return torch.cat(node, dim=-1)

    @staticmethod
    def mesh_edge_features(pos: Tensor, edge_index: Tensor, log_modulus: Tensor) -> Tensor:
        """(E, 5) ``[p_i - p_j, |p_i - p_j|, log10 E]`` of edges (2, E) into ``pos`` (n, 3); ``log_modulus``
        (E,) is the edge's ``log10 E`` (zero on finger edges)."""
        src, dst = edge_index
        rel = pos.index_select(0, dst) - pos.index_select(0, src)
        return torch.cat([rel, _safe_norm(rel), log_modulus.unsqueeze(1)], dim=1)

    @staticmethod
    def contact_edge_features(pos: Tensor, edge_index: Tensor, force: Tensor | None = None) -> Tensor:
        """(E, 4 [+1]) ``[p_i - p_j, |p_i - p_j| (, force)]`` of contact edges (2, E); ``force`` (E,) only for
        ``force_on="contact_edges"``."""
        src, dst = edge_index
        rel = pos.index_select(0, dst) - pos.index_select(0, src)
        contact = [rel, _safe_norm(rel)]
        if force is not None:
            contact.append(force.unsqueeze(1))
        return torch.cat(contact, dim=1)

    def forward(self, g: GraspGraph, pos: Tensor | None = None, force: Tensor | None = None):
        """Features at positions ``pos`` (default ``g.pos``) and graph forces ``force`` (default ``g.force``).

        Returns:
            node (n, node_dim), mesh_edge (E_M, 5), contact_edge (E_C, contact_edge_dim) feature tensors.
        """
        pos = g.pos if pos is None else pos
        node_graph = g.node_graph()
        gforce = self.graph_force(g, force).to(pos.dtype)
        on_nodes = self.force_on == "nodes"
        node = self.node_features(
            g.node_type, pos, g.closing_dir, gforce.index_select(0, node_graph) if on_nodes else None
        )

        src = g.mesh_edge_index[0]
        log_e = torch.log10(g.youngs_modulus.to(pos.dtype)).index_select(0, node_graph.index_select(0, src))
        log_e = torch.where(g.node_type.index_select(0, src) == NODE_FINGER, torch.zeros_like(log_e), log_e)
        mesh = self.mesh_edge_features(pos, g.mesh_edge_index, log_e)

        dst = g.contact_edge_index[1]
        edge_force = None if on_nodes else gforce.index_select(0, node_graph.index_select(0, dst))
        return node, mesh, self.contact_edge_features(pos, g.contact_edge_index, edge_force)
