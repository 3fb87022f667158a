"""Batched block-tridiagonal Cholesky (or LU) of the Newton Hessian: the "banded" linear solver.

A tetrahedral mesh's vertices, grouped by breadth-first distance from a pseudo-peripheral vertex
(the level structure of George & Liu, *Computer Solution of Large Sparse Positive Definite Systems*,
1981), couple only within a level and with the two neighbouring levels: every mesh edge joins
vertices whose distances differ by at most one. Ordered level by level, the vertex part K of one
problem's Hessian is block tridiagonal, with dense diagonal blocks A_i (s_i x s_i, three scalars per
vertex) and sub-diagonal blocks C_i (s_i x s_{i-1}):

    L_0 L_0^T = A_0,    W_i = C_i L_{i-1}^{-T},    L_i L_i^T = A_i - W_i W_i^T      (i = 1 .. m-1)

The travel rows of the force-controlled bodies couple to every surface vertex; they form the border
of an arrow matrix H = [[K, G], [G^T, E]] and are eliminated through their Schur complement

    Z = K^{-1} G,    S = E - G^T Z,    x_t = S^{-1} (b_t - G^T K^{-1} b_v),    x_v = K^{-1} b_v - Z x_t.

Each step is one batched dense operation over all problems (PyTorch: cuSOLVER / cuBLAS on CUDA,
LAPACK / BLAS on the CPU). Cost per problem: sum_i (s_i^3 / 3 + s_i s_{i-1} (s_i + s_{i-1})) instead
of n^3 / 3 for the whole matrix: on a 960-vertex box about 1/22 of the dense factorization (slabs,
below), on the 915-vertex membrane of the tactile sensor 1/29 (3747 vertices: 1/110), and a factor's
memory falls too (11 instead of 66 MB for the box; 72 MB instead of 1.0 GB for the 3747-vertex membrane).

Levels are merged, in order, while the merged block stays no larger than the widest level: fewer,
larger blocks mean fewer sequential launches at no more than the widest level's cost per block. Given
the vertices' rest positions, breadth-first sweeps from the whole lowest end of the object along each
principal axis (multi-source levels: slabs across the axis) compete with the pseudo-peripheral
vertex's shells, and the structure of least flops is taken (``level_blocks``): a corner's shells on
a box are diagonal sections up to twice as wide as its cross-section.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

__all__ = [
    "BlockTridiagonalLayout",
    "BlockTridiagonalFactor",
    "FactorGraphs",
    "graph_batch_size",
    "level_blocks",
]

_IDENTITIES: dict = {}  # (n, dtype, device) -> the n x n identity (_identities)


def _identities(g: int, n: int, like):
    """(g, n, n) identity matrices (a broadcast view) of ``like``'s dtype and device (one n x n identity
    per size, dtype and device is made once: a factorization asks for one per block)."""
    import torch

    key = (n, like.dtype, like.device)
    eye = _IDENTITIES.get(key)
    if eye is None:
        eye = _IDENTITIES[key] = torch.eye(n, dtype=like.dtype, device=like.device)
    return eye.expand(g, n, n)


def _bfs_levels(graph: sp.csr_matrix, start: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices reached from ``start`` in breadth-first order and their distances (levels)."""
    order, pred = breadth_first_order(graph, start, directed=False, return_predecessors=True)
    level = np.zeros(graph.shape[0], dtype=np.int64)
    for v in order[1:]:  # predecessors come first in breadth-first order
        level[v] = level[pred[v]] + 1
    return order, level[order]


def _multi_source_levels(graph: sp.csr_matrix, sources: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices reached from the set ``sources`` (level 0) in breadth-first order and their levels."""
    n = graph.shape[0]
    hub = sp.csr_matrix((np.ones(len(sources)), (np.full(len(sources), n), sources)), shape=(n + 1, n + 1))
    augmented = sp.bmat([[graph, None], [None, sp.csr_matrix((1, 1))]], format="csr") + hub
    order, level = _bfs_levels(augmented, n)
    return order[1:], level[1:] - 1


def _merged_sizes(level: np.ndarray) -> list[int]:
    """Consecutive levels merged while the merged block is no wider than the widest level."""
    widths = np.bincount(level)
    cap = widths.max()
    merged = [0]
    for w in widths:
        if merged[-1] and merged[-1] + w > cap:
            merged.append(0)
        merged[-1] += int(w)
    return merged


def _factor_cost(sizes) -> float:
    """Leading flops of the block-tridiagonal Cholesky with these block sizes (any common unit)."""
    s = np.asarray(sizes, dtype=float)
    return float(np.sum(s**3) / 3 + np.sum(s[1:] * s[:-1] * (s[1:] + s[:-1])))


def _slab_sources(graph: sp.csr_matrix, members: np.ndarray, points: np.ndarray) -> list[np.ndarray]:
    """Start sets for sweeps along a component's principal axes: per axis, the vertices within half a
    median edge of the component's lowest end along it (on a structured box: its end face)."""
    x = points[members]
    centred = x - x.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    sub = graph[members][:, members].tocoo()
    edge = np.linalg.norm(x[sub.row] - x[sub.col], axis=1)
    half = 0.5 * float(np.median(edge[edge > 0])) if np.any(edge > 0) else 0.0
    starts = []
    for axis in axes:
        t = centred @ axis
        starts.append(members[t <= t.min() + half])
    return starts


def level_blocks(graph: sp.csr_matrix, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Elimination order and block sizes (in vertices) of a level structure of ``graph``.

    Per connected component: a pseudo-peripheral start vertex (repeat: take the farthest vertex of
    least degree, until the eccentricity stops growing), its breadth-first levels, and consecutive
    levels merged while the merged block is no wider than the component's widest level. Blocks of
    different components do not couple. With the vertices' ``points`` (N, 3), sweeps that start from
    the whole lowest end of the component along each of its principal axes compete too (levels then
    are slabs across the axis: on the FEM benchmark's 960-vertex box 12 planes of 80 vertices instead
    of 12 diagonal shells of up to 167 around a corner, 0.39x the flops); the structure of least
    factorization flops is taken. Returns (order (N,), sizes (m,)) with sizes.sum() == N."""
    graph = sp.csr_matrix(graph)
    n = graph.shape[0]
    degree = np.diff(graph.indptr)
    points = None if points is None else np.asarray(points, dtype=float)
    _, component = connected_components(graph, directed=False)
    order_parts, sizes = [], []
    for c in np.unique(component):
        members = np.nonzero(component == c)[0]
        order, level = _bfs_levels(graph, int(members[np.argmin(degree[members])]))
        for _ in range(8):
            last = order[level == level[-1]]
            farther = _bfs_levels(graph, int(last[np.argmin(degree[last])]))
            if farther[1][-1] <= level[-1]:
                break
            order, level = farther
        merged = _merged_sizes(level)
        best = (_factor_cost(merged), order, merged)
        if points is not None and len(members) > 1:
            for sources in _slab_sources(graph, members, points):
                o, lv = _multi_source_levels(graph, sources)
                swept = _merged_sizes(lv)
                cost = _factor_cost(swept)
                if cost < best[0]:
                    best = (cost, o, swept)
        _, order, merged = best
        order_parts.append(order)
        sizes.extend(merged)
    order = np.concatenate(order_parts)
    if len(order) != n or len(np.unique(order)) != n:
        raise RuntimeError("internal error: the level structure does not cover every vertex once")
    return order.astype(np.int64), np.asarray(sizes, dtype=np.int64)


@dataclass
class BlockTridiagonalLayout:
    """Where each scalar entry of one problem's BSR Hessian goes in the packed block-tridiagonal storage.

    Packed storage of one problem (float64): the diagonal blocks A_i (s_i x s_i), the sub-diagonal blocks
    C_i (s_i x s_{i-1}, i >= 1), the border G (n_v x n_t) and its corner E (n_t x n_t), where n_v = 3 N
    vertex scalars in elimination order and n_t = 3 D travel rows. Upper blocks are the transposes of
    lower ones (the Hessian is symmetric) and are not stored."""

    sizes: np.ndarray  # (m,) scalars per diagonal block
    vertex_scalars: int  # n_v
    border: int  # n_t
    permutation: np.ndarray  # (n_v,) BSR scalar index of the k-th vertex scalar in elimination order
    source: np.ndarray  # (E,) flat index into one problem's BSR values (nnz x 3 x 3)
    target: np.ndarray  # (E,) flat index into the packed storage
    diag_offsets: np.ndarray  # (m,)
    sub_offsets: np.ndarray  # (m,) offset of C_i (entry 0 unused)
    border_offset: int
    corner_offset: int
    size: int  # packed scalars per problem

    @classmethod
    def build(
        cls,
        rows: np.ndarray,
        cols: np.ndarray,
        num_vertices: int,
        num_dofs: int,
        points: np.ndarray | None = None,
    ) -> BlockTridiagonalLayout:
        """From a BSR block pattern of one problem (block rows/cols; vertex rows first, then travel rows);
        ``points``: the vertices' rest positions (:func:`level_blocks`' slab sweeps), or None."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        N = num_vertices
        vv = (rows < N) & (cols < N)
        graph = sp.csr_matrix((np.ones(int(vv.sum())), (rows[vv], cols[vv])), shape=(N, N))
        order, vertex_sizes = level_blocks(graph, points)
        rank = np.empty(N, dtype=np.int64)
        rank[order] = np.arange(N)
        block_of = np.repeat(np.arange(len(vertex_sizes)), vertex_sizes)[rank]  # block of each vertex
        first = np.concatenate([[0], np.cumsum(vertex_sizes)[:-1]])  # first rank of each block
        sizes = 3 * vertex_sizes
        diag_off = np.concatenate([[0], np.cumsum(sizes**2)[:-1]])
        sub_sizes = np.concatenate([[0], sizes[1:] * sizes[:-1]])
        sub_off = diag_off[-1] + sizes[-1] ** 2 + np.concatenate([[0], np.cumsum(sub_sizes)[:-1]])
        border_offset = int(sub_off[-1] + sub_sizes[-1])
        n_v, n_t = 3 * N, 3 * num_dofs
        corner_offset = border_offset + n_v * n_t
        size = corner_offset + n_t * n_t

        k = np.arange(len(rows))
        p = np.arange(3)
        # every scalar entry (block k, component p, q)
        K_, P_, Q_ = (a.ravel() for a in np.meshgrid(k, p, p, indexing="ij"))
        source = K_ * 9 + P_ * 3 + Q_
        r, c = rows[K_], cols[K_]
        target = np.full(len(source), -1, dtype=np.int64)
        both = (r < N) & (c < N)
        br, bc = (
            np.where(both, block_of[np.minimum(r, N - 1)], -1),
            np.where(both, block_of[np.minimum(c, N - 1)], -1),
        )
        if np.any(both & (np.abs(br - bc) > 1)):
            raise RuntimeError("internal error: the level ordering is not block tridiagonal")
        # local scalar index of a vertex component within its block
        local = lambda v, comp: 3 * (rank[v] - first[block_of[v]]) + comp  # noqa: E731
        same = both & (br == bc)
        i = br[same]
        target[same] = diag_off[i] + local(r[same], P_[same]) * sizes[i] + local(c[same], Q_[same])
        lower = both & (br == bc + 1)
        i = br[lower]
        target[lower] = sub_off[i] + local(r[lower], P_[lower]) * sizes[i - 1] + local(c[lower], Q_[lower])
        vd = (r < N) & (c >= N)
        target[vd] = border_offset + (3 * rank[r[vd]] + P_[vd]) * n_t + 3 * (c[vd] - N) + Q_[vd]
        dd = (r >= N) & (c >= N)
        target[dd] = corner_offset + (3 * (r[dd] - N) + P_[dd]) * n_t + 3 * (c[dd] - N) + Q_[dd]
        keep = target >= 0
        permutation = (3 * order[:, None] + p[None, :]).ravel()
        return cls(
            sizes=sizes,
            vertex_scalars=n_v,
            border=n_t,
            permutation=permutation,
            source=source[keep],
            target=target[keep],
            diag_offsets=diag_off,
            sub_offsets=sub_off,
            border_offset=border_offset,
            corner_offset=int(corner_offset),
            size=int(size),
        )

    @property
    def num_blocks(self) -> int:
        return len(self.sizes)

    def flops_ratio(self) -> float:
        """Factorization flops of this layout over those of the dense matrix (leading terms)."""
        s = self.sizes.astype(float)
        n = self.vertex_scalars + self.border
        ours = (
            np.sum(s**3) / 3
            + np.sum(s[1:] * s[:-1] * (s[1:] + s[:-1]))
            + 2 * self.vertex_scalars * self.border**2
        )
        return float(ours / (n**3 / 3))


def _factorize(layout: BlockTridiagonalLayout, packed, lu: bool, explicit: bool):
    """The factorization of :class:`BlockTridiagonalFactor` (its docstring): (diagonal, coupling, Z, S,
    failed) of the problems ``packed`` (g, layout.size). Every call a fixed sequence of batched PyTorch
    operations on tensors of fixed shapes, with no host synchronization: :class:`FactorGraphs` captures it."""
    import torch

    lay = layout
    g = packed.shape[0]
    s = lay.sizes.tolist()
    blocks = lambda off, a, b: packed[:, off : off + a * b].view(g, a, b)  # noqa: E731
    diagonal: list = []
    coupling: list = [None]
    failed = torch.zeros(g, dtype=torch.bool, device=packed.device)
    for i, si in enumerate(s):
        A = blocks(int(lay.diag_offsets[i]), si, si)
        if i:
            Ct = blocks(int(lay.sub_offsets[i]), si, s[i - 1]).mT
            previous = diagonal[-1]
            if explicit:  # L_{i-1}^-1 C_i^T
                X = torch.bmm(previous, Ct)
            elif lu:
                X = torch.linalg.lu_solve(*previous, Ct)
            else:
                X = torch.linalg.solve_triangular(previous, Ct, upper=False)
            A = torch.baddbmm(A, Ct.mT if lu else X.mT, X, alpha=-1.0)
            coupling.append(X)
        if lu:
            LU, pivots, info = torch.linalg.lu_factor_ex(A)
            pivot = (LU, pivots)
        else:
            pivot, info = torch.linalg.cholesky_ex(A)
            if explicit:
                pivot = torch.linalg.solve_triangular(pivot, _identities(g, si, A), upper=False)
        diagonal.append(pivot)
        failed |= info != 0
    Z = S = None
    if lay.border:
        G = packed[:, lay.border_offset : lay.corner_offset].view(g, lay.vertex_scalars, lay.border)
        E = packed[:, lay.corner_offset : lay.size].view(g, lay.border, lay.border)
        Z = _vertex_solve(lay, diagonal, coupling, lu, explicit, G)
        S = torch.baddbmm(E, G.mT, Z, alpha=-1.0)
        if lu:
            LU, pivots, info = torch.linalg.lu_factor_ex(S)
            S = (LU, pivots)
        else:
            S, info = torch.linalg.cholesky_ex(0.5 * (S + S.mT))
        failed |= info != 0
    return diagonal, coupling, Z, S, failed


def _vertex_solve(layout: BlockTridiagonalLayout, D: list, X: list, lu: bool, explicit: bool, b):
    """K^{-1} b for (g, n_v, k) right-hand sides in elimination order with the factors' diagonal ``D``
    and coupling ``X`` blocks of those g problems.

    Forward: y_i = L_i^-1 (b_i - W_i y_{i-1}) (Cholesky) or g_i = b_i - X_i^T g_{i-1} (LU); backward:
    x_i = L_i^-T (y_i - W_{i+1}^T x_{i+1}) or x_i = D_i^-1 g_i - X_{i+1} x_{i+1}. With explicit
    inverses (Cholesky) every step is a batched product."""
    import torch

    s = layout.sizes.tolist()
    bounds = np.concatenate([[0], np.cumsum(s)]).tolist()

    def lower(i, v):  # L_i^-1 v
        return torch.bmm(D[i], v) if explicit else torch.linalg.solve_triangular(D[i], v, upper=False)

    def upper(i, v):  # L_i^-T v
        return torch.bmm(D[i].mT, v) if explicit else torch.linalg.solve_triangular(D[i].mT, v, upper=True)

    y = []
    for i in range(len(s)):
        bi = b[:, bounds[i] : bounds[i + 1]]
        if i:
            bi = torch.baddbmm(bi, X[i].mT, y[-1], alpha=-1.0)
        y.append(bi if lu else lower(i, bi))
    x = [None] * len(s)
    for i in reversed(range(len(s))):
        last = i + 1 == len(s)
        if lu:
            x[i] = torch.linalg.lu_solve(*D[i], y[i])
            if not last:
                x[i] = torch.baddbmm(x[i], X[i + 1], x[i + 1], alpha=-1.0)
        else:
            x[i] = upper(i, y[i] if last else torch.baddbmm(y[i], X[i + 1], x[i + 1], alpha=-1.0))
    return torch.cat(x, dim=1)


class BlockTridiagonalFactor:
    """Factors of a batch of problems in one layout, and solves with any subset of them.

    ``packed`` (g, layout.size) float64 tensor of the problems' packed Hessians. ``lu=False``: block
    Cholesky (module docstring; positive definite matrices). ``lu=True``: block LU for symmetric
    indefinite ones (an exact Hessian off a stable equilibrium), the block Thomas algorithm with partial
    pivoting inside each diagonal block,

        D_0 = A_0,    X_i = D_{i-1}^{-1} C_i^T,    D_i = A_i - C_i X_i,

    forward g_i = b_i - X_i^T g_{i-1} (D symmetric), backward x_i = D_i^{-1} g_i - X_{i+1} x_{i+1}.
    ``failed`` (g,) bool: a problem whose factorization broke down (Cholesky: a pivot block not positive
    definite; LU: a singular pivot block); its factors are garbage and must not be used.

    ``explicit_inverse`` (block Cholesky only; default: on CUDA): keep L_i^-1 (one triangular solve with
    the identity per block while factoring) and substitute with batched matrix products only: cuBLAS's
    batched triangular solve with one or two right-hand sides runs far below the memory bandwidth that a
    batched product reaches (one H100, two right-hand sides of 128 problems: the 915-vertex membrane's
    15 blocks 6.2 -> 1.5 ms, the 960-vertex box with its travel border 7.2 -> 2.1 ms; the factorization
    costs about the same; `benchmarks/block_tridiagonal_explicit_inverse_h100_s33.json`). The couplings
    are then products too (W_i^T = L_{i-1}^-1 C_i^T). End to end on that H100: the FEM benchmark (100
    squeeze ramps x 50 steps) 65.0 -> 55.6 s, the streamed poke benchmark 97.0 -> 86.3 s. The inverse of
    a Cholesky factor is as accurate as the solve (cond(L_i) = cond(A_i)^1/2; tested at cond(A) 1e9);
    block LU keeps its solves (an indefinite pivot block's inverse lost ~60x in a test). Off: LAPACK's
    triangular solves (the CPU's choice: there they cost what a product costs, and the inverses would
    add to the factorization)."""

    def __init__(
        self,
        layout: BlockTridiagonalLayout,
        packed,
        lu: bool = False,
        explicit_inverse: bool | None = None,
        graphs: FactorGraphs | None = None,
    ):
        import torch

        self.layout = layout
        self.lu = bool(lu)
        if explicit_inverse is None:
            explicit_inverse = packed.device.type == "cuda"
        self.explicit_inverse = explicit = bool(explicit_inverse) and not self.lu
        self.permutation = torch.as_tensor(layout.permutation, device=packed.device)
        # per block: Cholesky L_i (explicit: L_i^-1), or LU (LU_i, pivots_i) of D_i; coupling
        # W_i^T = L_{i-1}^{-1} C_i^T or X_i = D_{i-1}^-1 C_i^T; the border's Z and S; failed problems
        parts = None
        if graphs is not None and explicit and packed.device.type == "cuda":
            parts = graphs.factor(packed)  # None: too many problems, or the memory budget is spent
        if parts is None:
            parts = _factorize(layout, packed, self.lu, explicit)
        self.diagonal, self.coupling, self.Z, self.S, self.failed = parts

    @staticmethod
    def _pick(t, rows):
        """Rows ``rows`` (LongTensor, or None: all) of a tensor or a tuple of tensors."""
        if rows is None or t is None:
            return t
        if isinstance(t, tuple):
            return tuple(x.index_select(0, rows) for x in t)
        return t.index_select(0, rows)

    def _vertex_solve(self, b, rows):
        """K^{-1} b for (len(rows), n_v, k) right-hand sides in elimination order (``rows``: problems)."""
        D = [self._pick(t, rows) for t in self.diagonal]
        X = [self._pick(t, rows) for t in self.coupling]
        return _vertex_solve(self.layout, D, X, self.lu, self.explicit_inverse, b)

    def solve(self, rhs, rows=None):
        """Solutions (len(rows), n) of right-hand sides (len(rows), n) in the BSR's scalar order, with the
        factors of problems ``rows`` (a LongTensor of positions in this batch; None: all, in order).
        ``rhs`` (len(rows), n, k): k right-hand sides per problem, solved together (one substitution).

        With explicit inverses (CUDA), a subset of at least half the batch is solved as the whole batch
        with zero right-hand sides elsewhere: picking the rows would copy their factors (the whole
        factor's size) before reading them again; the batch's other problems cost one more read."""
        import torch

        lay = self.layout
        perm = self.permutation
        columns = rhs if rhs.dim() == 3 else rhs.unsqueeze(2)
        g = len(self.failed)
        if self.explicit_inverse and rows is not None and 2 * len(rows) >= g:
            padded = columns.new_zeros(g, *columns.shape[1:])
            padded[rows] = columns
            x = self.solve(padded).index_select(0, rows)
            return x if rhs.dim() == 3 else x.squeeze(2)
        b_v = columns.index_select(1, perm)
        x_v = self._vertex_solve(b_v, rows)
        x = torch.empty_like(columns)
        if lay.border:
            Z, S = self._pick(self.Z, rows), self._pick(self.S, rows)
            b_t = columns[:, lay.vertex_scalars :]
            # b_t - G^T K^{-1} b_v = b_t - Z^T b_v (K symmetric)
            r_t = torch.baddbmm(b_t, Z.mT, b_v, alpha=-1.0)
            x_t = torch.linalg.lu_solve(*S, r_t) if self.lu else torch.cholesky_solve(r_t, S)
            x_v = torch.baddbmm(x_v, Z, x_t, alpha=-1.0)
            x[:, lay.vertex_scalars :] = x_t
        x[:, perm] = x_v
        return x if rhs.dim() == 3 else x.squeeze(2)


def graph_batch_size(problems: int) -> int:
    """The batch of the CUDA graph that factors ``problems`` problems: the smallest power of two or 1.5
    times a power of two that holds them (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, ...): a graph per size
    class, padded by at most a third."""
    if problems < 1:
        raise ValueError(f"problems must be >= 1, got {problems}")
    power = 1
    while True:
        if power >= problems:
            return power
        if power >= 2 and power + power // 2 >= problems:
            return power + power // 2
        power *= 2


class FactorGraphs:
    """CUDA graphs of one layout's block-Cholesky factorization (explicit inverses), one per batch size
    class (:func:`graph_batch_size`): captured on first use, replayed after.

    Eager, a factorization is a sequence of small batched PyTorch calls (on the FEM benchmark's box 13
    Cholesky factorizations, each ~40 cuSOLVER kernels, 12 triangular inversions and ~40 products: about
    650 kernel launches, several ms of host time, `benchmarks/fem_cuda_kernel_profile_h200_s45.md`).
    Replayed, the host launches it in one call (~1.7 ms on an H200) and is free to queue the Newton pass's
    other work while the GPU factors (the GPU's own time is the same). A batch of g problems is copied
    into the graph's input with identity matrices in its remaining rows (they factor trivially), and the
    factors of the g problems are copied out of the graph's outputs (the next replay overwrites them; a
    factor is kept across Newton steps). The graphs share one memory pool: each replay's outputs are
    copied before another graph runs.

    ``memory_fraction``: the inputs and outputs of all captured graphs together (2 x 8 x layout.size
    bytes per problem of each size class: 21 MB on the FEM benchmark's 960-vertex box) stay below this
    fraction of the GPU's memory, and a new graph takes at most half of the memory free when it is
    captured (processes that share the GPU); a batch whose graph would not fit is factored eagerly
    (:meth:`factor` returns None). So is a batch of more than ``max_problems`` problems: there the GPU's
    work, not the launches, sets the time, and padding costs more than a graph saves (one H200, the box's
    real Newton systems: 100 problems 17.3 ms eager against 21.1 ms padded to 128; 1, 4 and 16 problems
    the same either way when timed alone, `benchmarks/fem_cuda_factor_graphs_h200_s47.json`)."""

    def __init__(self, layout: BlockTridiagonalLayout, memory_fraction: float, max_problems: int = 64):
        if not 0.0 < memory_fraction <= 1.0:
            raise ValueError(f"memory_fraction must be in (0, 1], got {memory_fraction!r}")
        self.layout = layout
        self.memory_fraction = float(memory_fraction)
        self.max_problems = int(max_problems)
        self._graphs: dict[int, tuple] = {}  # batch size -> (graph, static input, static outputs)
        self._pool = None
        self._stream = None
        self._padding = None  # (layout.size,) one problem's packed identity matrix
        self.captures = 0  # graphs captured so far
        self.replays = 0  # factorizations replayed

    @property
    def bytes(self) -> int:
        """Inputs and outputs of the captured graphs [bytes] (what the memory budget counts)."""
        return sum(self._graph_bytes(size) for size in self._graphs)

    def _graph_bytes(self, size: int) -> int:
        return 2 * 8 * self.layout.size * size

    def _padding_row(self, device):
        """One problem's packed identity matrix (layout.size,): the graphs' unused rows."""
        import torch

        if self._padding is None:
            lay = self.layout
            diagonal = zip(lay.diag_offsets.tolist(), lay.sizes.tolist())
            index = [off + j * (si + 1) for off, si in diagonal for j in range(si)]
            index += [lay.corner_offset + j * (lay.border + 1) for j in range(lay.border)]
            row = torch.zeros(lay.size, dtype=torch.float64, device=device)
            row[torch.as_tensor(index, device=device)] = 1.0
            self._padding = row
        return self._padding

    def _capture(self, size: int, device):
        import torch

        if self._pool is None:
            self._pool = torch.cuda.graph_pool_handle()
            self._stream = torch.cuda.Stream(device)
        static = self._padding_row(device).expand(size, -1).clone()
        # warm-up outside the capture, on the capture's stream: cuSOLVER / cuBLAS handles and workspaces,
        # and the cached identity blocks of _identities, exist before it
        self._stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(self._stream):
            _factorize(self.layout, static, False, True)
        torch.cuda.current_stream(device).wait_stream(self._stream)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self._pool, stream=self._stream, capture_error_mode="thread_local"):
            outputs = _factorize(self.layout, static, False, True)
        self.captures += 1
        self._graphs[size] = (graph, static, outputs)
        return self._graphs[size]

    def factor(self, packed):
        """(diagonal, coupling, Z, S, failed) of the problems ``packed`` (g, layout.size) on CUDA, as
        :func:`_factorize` with explicit inverses gives them; None when they are more than
        ``max_problems``, or their size class has no graph and one would exceed the memory budget
        (``memory_fraction``)."""
        g = packed.shape[0]
        if g > self.max_problems:
            return None
        size = graph_batch_size(g)
        entry = self._graphs.get(size)
        if entry is None:
            import torch

            free, total = torch.cuda.mem_get_info(packed.device)
            new = self._graph_bytes(size)
            if self.bytes + new > self.memory_fraction * total or new > 0.5 * free:
                return None
            entry = self._capture(size, packed.device)
        graph, static, (diagonal, coupling, Z, S, failed) = entry
        static[:g].copy_(packed)
        if g < size:
            static[g:].copy_(self._padding_row(packed.device).expand(size - g, -1))
        graph.replay()
        self.replays += 1

        def mine(t):  # the g problems' rows, copied out of the graph's memory
            return None if t is None else t[:g].clone()

        return (
            [mine(t) for t in diagonal],
            [mine(t) for t in coupling],
            mine(Z),
            mine(S),
            mine(failed),
        )
