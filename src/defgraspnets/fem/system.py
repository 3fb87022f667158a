"""The batched block-sparse Newton system and its linear solvers.

Unknowns of one problem are R = N + D block rows of 3 scalars: the N vertex displacements, then one
row per travel degree of freedom (only its first component is used; the other two are identity
rows). B problems on the same mesh form one block-diagonal BSR matrix of B * R block rows; Warp's
batched Krylov solvers run the B conjugate-gradient iterations in lockstep, each with its own step
sizes and its own convergence test.

Sparsity of one problem: (v, w) for every mesh edge and vertex, (N+d, N+d), and (N+d, s), (s, N+d)
for every travel dof d and every surface vertex s (a body driven by d may touch any surface vertex).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp
import warp.optim.linear as wpl
import warp.sparse as wps

from .block_tridiagonal import BlockTridiagonalFactor, BlockTridiagonalLayout, FactorGraphs
from .mesh import TetMesh

f64 = wp.float64


@dataclass
class BlockPattern:
    """Block sparsity of one problem and the block index of every element/contact coupling."""

    num_vertices: int
    num_dofs: int
    rows: np.ndarray  # (nnz,) block row, sorted by (row, col)
    cols: np.ndarray  # (nnz,)
    tet_blocks: np.ndarray  # (M, 16) block of (tets[e, a], tets[e, c]) at 4a + c
    vertex_diag: np.ndarray  # (N,)
    dof_diag: np.ndarray  # (D,)
    dof_vertex: np.ndarray  # (D, S) block (N + d, surface[s])
    vertex_dof: np.ndarray  # (D, S) block (surface[s], N + d)

    @property
    def rows_per_problem(self) -> int:
        return self.num_vertices + self.num_dofs

    @property
    def nnz(self) -> int:
        return len(self.rows)

    def block_index(self, rows, cols) -> np.ndarray:
        """Block index (within one problem) of each pair (rows[i], cols[i]); -1 where not in the pattern."""
        r, c = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        n = self.rows_per_problem
        key = self.rows.astype(np.int64) * n + self.cols
        want = r * n + c
        k = np.minimum(np.searchsorted(key, want), len(key) - 1)
        return np.where(key[k] == want, k, -1).astype(np.int32)

    @classmethod
    def build(cls, mesh: TetMesh, num_dofs: int) -> BlockPattern:
        n = mesh.num_vertices
        s = mesh.surface_vertices
        t = mesh.tets
        pairs = [np.stack([t[:, a], t[:, c]], axis=1) for a in range(4) for c in range(4)]
        dof_rows = n + np.arange(num_dofs)
        extra = [np.stack([dof_rows, dof_rows], axis=1)]
        for d in dof_rows:
            extra.append(np.stack([np.full(len(s), d), s], axis=1))
            extra.append(np.stack([s, np.full(len(s), d)], axis=1))
        allp = np.concatenate(pairs + extra).astype(np.int64)
        key = np.unique(allp[:, 0] * (n + num_dofs) + allp[:, 1])
        rows, cols = key // (n + num_dofs), key % (n + num_dofs)

        def index(r, c):
            k = np.searchsorted(key, np.asarray(r) * (n + num_dofs) + np.asarray(c))
            return k.astype(np.int32)

        tet_blocks = np.stack([index(t[:, a], t[:, c]) for a in range(4) for c in range(4)], axis=1)
        return cls(
            num_vertices=n,
            num_dofs=num_dofs,
            rows=rows.astype(np.int32),
            cols=cols.astype(np.int32),
            tet_blocks=tet_blocks,
            vertex_diag=index(np.arange(n), np.arange(n)),
            dof_diag=index(dof_rows, dof_rows),
            dof_vertex=np.array([index(np.full(len(s), d), s) for d in dof_rows], np.int32).reshape(
                num_dofs, len(s)
            ),
            vertex_dof=np.array([index(s, np.full(len(s), d)) for d in dof_rows], np.int32).reshape(
                num_dofs, len(s)
            ),
        )


@wp.kernel
def constrain_system_kernel(
    block_rows: wp.array(dtype=wp.int32),
    block_cols: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    diagonal_shift: wp.array(dtype=wp.vec3d),
    rows_per_problem: int,
    blocks_per_problem: int,
    hessian: wp.array(dtype=wp.mat33d),
):
    """Zero the rows and columns of fixed components (free = 0), put 1 on their diagonal, and add the
    regularization ``diagonal_shift`` to the free diagonal entries."""
    b, k = wp.tid()
    r = block_rows[k]
    c = block_cols[k]
    fr = free[r]
    fc = free[c]
    i = b * blocks_per_problem + k
    A = hessian[i]
    for p in range(3):
        for q in range(3):
            A[p, q] = A[p, q] * fr[p] * fc[q]
    if r == c:
        shift = diagonal_shift[b * rows_per_problem + r]
        for p in range(3):
            A[p, p] = A[p, p] + (f64(1.0) - fr[p]) + fr[p] * shift[p]
    hessian[i] = A


# Dense solves factor up to this many problems one by one and larger sets as one batch. H100, 2883 unknowns,
# float64 Cholesky: one problem 1.5 ms; a batch of k costs about 7 + 1.0 k ms (2: 8.7, 16: 22.6, 64: 73.6 ms)
DENSE_LOOP_MAX_PROBLEMS = 12


class BatchedSystem:
    """BSR Hessian, gradient and increment of B problems with a shared pattern, and their solvers."""

    def __init__(self, pattern: BlockPattern, batch_size: int, device, points: np.ndarray | None = None):
        self.pattern = pattern
        #: the vertices' rest positions (N, 3) or None: the banded solver's level structure may sweep along
        #: the object's principal axes (``block_tridiagonal.level_blocks``)
        self.points = None if points is None else np.asarray(points, dtype=float)
        self.batch_size = batch_size
        self.device = wp.get_device(device)
        rpp, nnz = pattern.rows_per_problem, pattern.nnz
        offs = (np.arange(batch_size, dtype=np.int64) * rpp)[:, None]
        rows = (pattern.rows[None, :] + offs).ravel().astype(np.int32)
        cols = (pattern.cols[None, :] + offs).ravel().astype(np.int32)
        self.matrix = wps.bsr_zeros(batch_size * rpp, batch_size * rpp, block_type=wp.mat33d, device=device)
        wps.bsr_set_from_triplets(
            self.matrix,
            wp.array(rows, dtype=wp.int32, device=device),
            wp.array(cols, dtype=wp.int32, device=device),
            values=wp.zeros(len(rows), dtype=wp.mat33d, device=device),
            prune_numerical_zeros=False,
        )
        if self.matrix.nnz_sync() != batch_size * nnz:
            raise RuntimeError("internal error: BSR pattern size mismatch")
        got = self.matrix.columns.numpy()[: batch_size * nnz]
        if not np.array_equal(got, cols):
            raise RuntimeError("internal error: BSR block order differs from the precomputed pattern")
        self.values = self.matrix.values
        self.block_rows = wp.array(pattern.rows, dtype=wp.int32, device=device)
        self.block_cols = wp.array(pattern.cols, dtype=wp.int32, device=device)
        self.gradient = wp.zeros(batch_size * rpp, dtype=wp.vec3d, device=device)
        self.rhs = wp.zeros_like(self.gradient)
        self.increment = wp.zeros_like(self.gradient)
        self.batch_offsets = wp.array(np.arange(batch_size + 1) * rpp * 3, dtype=wp.int32, device=device)
        self.operator = wpl.aslinearoperator(
            self.matrix, batch_offsets=self.batch_offsets, max_batch_length=rpp * 3
        )
        self._amg: dict[int, list] = {}  # problem -> [multigrid hierarchy, CG iterations when built]
        self._dense_index = None  # flat index of every block entry in one problem's dense matrix
        self._banded_layout = None  # BlockTridiagonalLayout of the pattern
        self._banded_scatter = None  # its (source, target) indices as tensors on the device
        self._product = None  # H increment of the banded solver's residual check (allocated on first use)
        self._pattern_index = None  # the pattern's block rows and columns as tensors (coupled products)
        # factorizations of the direct, dense and banded solvers, per problem: SuperLU objects, and
        # ("cholesky", L), ("banded", BlockTridiagonalFactor, position in it) or LU fallbacks
        # ("lu", LU, pivots); see ``keep_factors``
        self._direct_factors: dict[int, object] = {}
        self._dense_factors: dict[int, tuple] = {}
        #: keep each problem's factorization across matrix changes (``zero``), to be reused by later Newton
        #: steps (chord / modified Newton, see SolverOptions.max_factor_reuse); False: a new matrix drops them
        self.keep_factors = False
        #: matrix factorizations per problem so far (direct and dense solvers)
        self.factorizations = np.zeros(batch_size, dtype=np.int64)
        #: per problem: the last direct or dense solve used a factorization made in that call
        self.fresh_factor = np.zeros(batch_size, dtype=bool)
        #: (B,) bool or None, set by the caller: problems whose matrix, if its Cholesky factorization breaks
        #: down (not positive definite), is reported in :attr:`indefinite` with a zero increment instead of
        #: being factored by LU (dense, banded, dense_banded); the others fall back to LU as documented
        self.report_indefinite = None
        #: per problem: the last factorizing solve found its matrix not positive definite and, as
        #: :attr:`report_indefinite` asked, neither factored nor solved it (increment zero, no stored factor)
        self.indefinite = np.zeros(batch_size, dtype=bool)
        #: a second right-hand side per problem ((B, 3R) torch tensor on the device, or None) that the
        #: factorizing solves (dense, banded, dense_banded) solve with the same factors in the same
        #: substitutions as ``rhs``, into :attr:`extra_increment`; the caller clears it
        self.extra_rhs = None
        #: (B, 3R) solutions of :attr:`extra_rhs` of the last factorizing solve (zero for problems whose
        #: ``rhs`` was zero), or None
        self.extra_increment = None
        #: symmetric couplings outside the block pattern (self-contact between vertices that are no mesh
        #: neighbours), or None: (rows, cols, blocks) Warp arrays of C entries per problem, problem-local
        #: block rows and columns (C,) ... (B C,) int32 and (B C,) mat33d; each block adds (row, col) and its
        #: transpose at (col, row). The direct and dense solvers add them to the matrix they factor; the
        #: banded solver factors the pattern alone and adds them by a low-rank update of its solutions
        #: (:meth:`_solve_coupled`); CG and AMG lack them
        self.coupling = None
        #: CUDA streams on which :meth:`solve_dense` factors a few problems side by side (one cuSOLVER
        #: Cholesky of a 2883-unknown matrix keeps only part of an H200 busy); 1: one after another on the
        #: current stream (the default here; the solver sets SolverOptions.factor_streams)
        self.factor_streams = 1
        #: fraction of the GPU's memory that CUDA graphs of the banded solver's Cholesky factorization may
        #: hold (``block_tridiagonal.FactorGraphs``; 0: factor eagerly, the default here; the solver sets
        #: SolverOptions.factor_graphs). The CPU always factors eagerly
        self.factor_graphs = 0.0
        self._factor_graphs = None  # FactorGraphs of the banded layout (made on first use)
        self._side_streams: list = []  # torch.cuda.Stream objects, made on first use
        self._stream_views: dict = {}  # Warp's stream as a torch stream and torch's as a Warp one (CUDA)

    def _torch_after_warp(self) -> None:
        """PyTorch's current stream waits, on the device (the host does not block), for the work queued on
        Warp's stream so far: the PyTorch solvers then read the assembled matrix and right-hand side."""
        if not self.device.is_cuda:
            return
        import torch

        dev = torch.device(wp.device_to_torch(self.device))
        warp_stream = self.device.stream
        key = ("torch", id(warp_stream))
        if key not in self._stream_views:
            self._stream_views[key] = wp.stream_to_torch(warp_stream)
        torch.cuda.current_stream(dev).wait_stream(self._stream_views[key])

    def _warp_after_torch(self) -> None:
        """Warp's stream waits, on the device, for the work queued on PyTorch's current stream so far: Warp's
        next kernels (the line search) read the increment the PyTorch solvers wrote."""
        if not self.device.is_cuda:
            return
        import torch

        current = torch.cuda.current_stream(torch.device(wp.device_to_torch(self.device)))
        key = ("warp", current.cuda_stream)
        if key not in self._stream_views:
            self._stream_views[key] = wp.stream_from_torch(current)
        self.device.stream.wait_stream(self._stream_views[key])

    def zero(self):
        self.values.zero_()
        self.gradient.zero_()
        if not self.keep_factors:
            self.forget_factors()  # a new matrix follows

    def forget_factors(self, mask: np.ndarray | None = None):
        """Drop the stored factorizations of the masked problems (all by default)."""
        for p in range(self.batch_size) if mask is None else np.nonzero(mask)[0]:
            self._direct_factors.pop(int(p), None)
            self._dense_factors.pop(int(p), None)

    def share_factors_from(
        self, other: BatchedSystem, rows: np.ndarray, into: np.ndarray | None = None
    ) -> None:
        """Problem ``into[i]`` (default: i, every problem) takes problem ``rows[i]`` of ``other``'s stored
        factorizations and multigrid hierarchy (shared, not copied: they are never modified after being
        made, only replaced or dropped), and its factorization counters; other problems keep theirs."""
        rows = np.asarray(rows, dtype=np.int64)
        into = np.arange(self.batch_size) if into is None else np.asarray(into, dtype=np.int64)
        mask = np.zeros(self.batch_size, dtype=bool)
        mask[into] = True
        self.forget_factors(mask)
        for b in into.tolist():
            self._amg.pop(b, None)
        for b, r in zip(into.tolist(), rows.tolist()):
            if r in other._direct_factors:
                self._direct_factors[b] = other._direct_factors[r]
            if r in other._dense_factors:
                self._dense_factors[b] = other._dense_factors[r]
            if r in other._amg:
                self._amg[b] = list(other._amg[r])
        self.fresh_factor[into] = other.fresh_factor[rows]
        self.factorizations[into] = other.factorizations[rows]

    def _to_factor(self, todo, stored: dict, refactor: np.ndarray | None) -> list[int]:
        """The problems of ``todo`` that need a new factorization: those asked to (``refactor``) and those
        without a stored one. Records ``fresh_factor`` and counts them in ``factorizations``."""
        fresh = [p for p in todo if p not in stored or (refactor is not None and refactor[p])]
        self.fresh_factor[:] = False
        self.indefinite[:] = False
        self.fresh_factor[fresh] = True
        self.factorizations[fresh] += 1
        return fresh

    def constrain(self, free, diagonal_shift):
        wp.launch(
            constrain_system_kernel,
            dim=(self.batch_size, self.pattern.nnz),
            inputs=[
                self.block_rows,
                self.block_cols,
                free,
                diagonal_shift,
                self.pattern.rows_per_problem,
                self.pattern.nnz,
                self.values,
            ],
            device=self.device,
        )

    # -------------------------------------------------------------- linear solves: H increment = rhs
    def solve_cg(self, rtol: float, maxiter: int) -> tuple[int, float]:
        """Block-Jacobi preconditioned CG on all problems at once (per-problem step sizes and tolerances)."""
        M = wpl.preconditioner(self.matrix, ptype="block_jacobi_direct")
        self.increment.zero_()
        iters, residual, _ = wpl.cg(
            self.operator,
            self.rhs,
            self.increment,
            tol=rtol,
            atol=0.0,
            maxiter=maxiter,
            M=M,
            check_every=10,
            use_cuda_graph=self.device.is_cuda,  # one captured graph per check interval: fewer launches
        )
        return int(iters), float(residual)

    def host_matrix(self) -> sp.csr_matrix:
        """The (constrained) Hessian of all problems as a SciPy CSR matrix."""
        B, rpp, nnz = self.batch_size, self.pattern.rows_per_problem, self.pattern.nnz
        values = self.values.numpy()[: B * nnz]
        offsets = self.matrix.offsets.numpy()[: B * rpp + 1]
        cols = self.matrix.columns.numpy()[: B * nnz]
        return sp.bsr_matrix((values, cols, offsets), shape=(B * rpp * 3, B * rpp * 3)).tocsr()

    def _set_increment(self, x: np.ndarray):
        self.increment.assign(wp.array(x.reshape(-1, 3), dtype=wp.vec3d, device=self.device))

    def solve_direct(self, refactor: np.ndarray | None = None) -> tuple[int, float]:
        """Sparse LU (SuperLU) of each problem's Hessian on the host, one factorization per problem.

        Problems are factored one by one, never as one block-diagonal matrix: the fill-reducing ordering
        of a combined matrix depends on every block (minimum degree is a global choice), so a problem's
        round-off, and with it a path-dependent friction history, would depend on which other problems
        share the batch. Problems whose right-hand side is zero (converged or inactive) are skipped.

        The Hessian is symmetric, so SuperLU runs in its symmetric mode: minimum-degree ordering of A^T + A
        and diagonal pivots preferred, about half the fill and time of the general COLAMD ordering on
        tetrahedral meshes (11k unknowns: 4.7M vs 7.6M factor entries, 0.45 vs 0.73 s).

        ``refactor`` (B,) marks the problems whose stored factorization is out of date; the others solve
        with their stored one (an earlier matrix when ``keep_factors``: a chord step), and a problem without
        one is factored. None: no stored factorization is out of date (a new right-hand side).
        Returns (1, residual norm of the freshly factored problems)."""
        B, rpp, nnz = self.batch_size, self.pattern.rows_per_problem, self.pattern.nnz
        n = 3 * rpp
        values = self.values.numpy()[: B * nnz].reshape(B, nnz, 3, 3)
        offsets = self.matrix.offsets.numpy()[: rpp + 1]
        cols = self.matrix.columns.numpy()[:nnz]  # problem 0's block columns: the per-problem pattern
        b_all = self.rhs.numpy().reshape(B, n)
        x = np.zeros_like(b_all)
        residual2 = 0.0
        todo = np.nonzero(np.abs(b_all).max(axis=1) > 0)[0].tolist()
        fresh = set(self._to_factor(todo, self._direct_factors, refactor))
        coupling = self._host_coupling_entries(fresh) if fresh else None
        for p in todo:
            if p in fresh:
                A = sp.bsr_matrix((values[p], cols, offsets), shape=(n, n)).tocsc()
                if coupling is not None:
                    r, c, v = coupling[p]
                    A = A + sp.coo_matrix((np.r_[v, v], (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsc()
                self._direct_factors[p] = spla.splu(
                    A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.01, options={"SymmetricMode": True}
                )
            x[p] = self._direct_factors[p].solve(b_all[p])
            if p in fresh:
                residual2 += float(np.sum((A @ x[p] - b_all[p]) ** 2))
        self._set_increment(x)
        return 1, float(np.sqrt(residual2))

    def _host_coupling_entries(self, problems) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
        """Per problem of ``problems``, (rows, cols, values) of :attr:`coupling`'s nonzero scalar entries on
        the host (the empty pair slots, most of them, are left out before their entries are spelled out),
        or None without couplings."""
        if self.coupling is None:
            return None
        B = self.batch_size
        rows, cols = (a.numpy().reshape(B, -1) for a in self.coupling[:2])
        blocks = self.coupling[2].numpy().reshape(B, -1, 3, 3)
        k = np.arange(3)
        out = {}
        for p in problems:
            live = np.flatnonzero(np.abs(blocks[p]).reshape(len(blocks[p]), 9).max(axis=1) > 0)
            r = (3 * rows[p, live, None, None] + k[None, :, None]).repeat(3, axis=2)
            c = (3 * cols[p, live, None, None] + k[None, None, :]).repeat(3, axis=1)
            v = blocks[p, live]
            nonzero = v.ravel() != 0
            out[p] = (r.ravel()[nonzero], c.ravel()[nonzero], v.ravel()[nonzero])
        return out

    def _coupling_entries(self):
        """(rows, cols, values) of :attr:`coupling`'s scalar entries per problem ((B, 9 C) each), as
        tensors on the system's device (read after Warp's assembly has finished), or None."""
        if self.coupling is None:
            return None
        import torch

        rows, cols, blocks = self.coupling
        B = self.batch_size
        r = wp.to_torch(rows).view(B, -1, 1, 1).long()
        c = wp.to_torch(cols).view(B, -1, 1, 1).long()
        k = torch.arange(3, device=r.device)
        rr = (r * 3 + k.view(1, 1, 3, 1)).expand(-1, -1, 3, 3)
        cc = (c * 3 + k.view(1, 1, 1, 3)).expand(-1, -1, 3, 3)
        v = wp.to_torch(blocks).view(B, -1, 3, 3)
        return rr.reshape(B, -1), cc.reshape(B, -1), v.reshape(B, -1)

    def _torch_solve_start(self, refactor, todo: list[int] | None = None):
        """Common start of the PyTorch factorizing solves, after Warp's assembly has finished (Warp and
        PyTorch may run on different streams): (device, values (B, nnz * 9), rhs (B, n), increment (B, n),
        zeroed, problems with a nonzero right-hand side, those of them to factor). ``todo``: those problems,
        where the caller has already found them (:meth:`_problems_with_rhs`)."""
        import torch

        B, nnz = self.batch_size, self.pattern.nnz
        n = 3 * self.pattern.rows_per_problem
        dev = torch.device(wp.device_to_torch(self.device))
        if todo is None:
            todo = self._problems_with_rhs()
        else:
            self._torch_after_warp()
        values = wp.to_torch(self.values)[: B * nnz].reshape(B, nnz * 9)
        rhs = wp.to_torch(self.rhs).reshape(B, n)
        increment = wp.to_torch(self.increment).reshape(B, n)
        increment.zero_()
        if self.extra_rhs is not None:
            # both right-hand sides as the two columns of one (B, n, 2) system: one substitution each
            self.extra_increment = torch.zeros_like(rhs)
            rhs = torch.stack([rhs, self.extra_rhs.reshape(B, n)], dim=2)
        else:
            self.extra_increment = None
        return dev, values, rhs, increment, todo, self._to_factor(todo, self._dense_factors, refactor)

    def _store_solution(self, increment, index, x) -> None:
        """Rows ``index`` of the increment <- solutions ``x`` (m, n), or (m, n, 2) with :attr:`extra_rhs`'s
        solutions as the second column (into :attr:`extra_increment`)."""
        if x.dim() == 3:
            increment[index] = x[..., 0]
            self.extra_increment[index] = x[..., 1]
        else:
            increment[index] = x

    def _problems_with_rhs(self) -> list[int]:
        """Problems whose right-hand side is not zero (the others are converged or inactive), after Warp's
        assembly has finished."""
        import torch

        self._torch_after_warp()
        rhs = wp.to_torch(self.rhs).reshape(self.batch_size, 3 * self.pattern.rows_per_problem)
        return torch.nonzero(rhs.abs().amax(dim=1) > 0).flatten().tolist()

    def _dense_matrices(self, values, index):
        """(len(index), n, n) dense Hessians of the problems ``index`` (a LongTensor)."""
        import torch

        n = 3 * self.pattern.rows_per_problem
        if self._dense_index is None:
            r = self.pattern.rows.astype(np.int64)[:, None, None] * 3 + np.arange(3)[None, :, None]
            c = self.pattern.cols.astype(np.int64)[:, None, None] * 3 + np.arange(3)[None, None, :]
            self._dense_index = torch.as_tensor((r * n + c).ravel(), device=values.device)
        A = torch.zeros(len(index), n * n, dtype=torch.float64, device=values.device)
        A[:, self._dense_index] = values[index]
        return A.view(len(index), n, n)

    def _whole_matrices(self, values, index, coupling):
        """:meth:`_dense_matrices` plus the couplings outside the pattern and their transposes
        (``coupling``: :meth:`_coupling_entries`, or None)."""
        A = self._dense_matrices(values, index)
        if coupling is not None:
            n = A.shape[1]
            r, c, v = (a[index] for a in coupling)
            flat = A.view(len(index), n * n)
            flat.scatter_add_(1, r * n + c, v)
            flat.scatter_add_(1, c * n + r, v)
        return A

    def solve_dense(
        self,
        refactor: np.ndarray | None = None,
        memory_fraction: float = 0.5,
        todo: list[int] | None = None,
        residual: bool = True,
    ) -> tuple[int, float]:
        """Batched dense factorization of each problem's Hessian on the system's device (PyTorch: cuSOLVER
        on CUDA, LAPACK on the CPU), exact to round-off.

        One problem of R block rows is a dense (3R x 3R) float64 matrix (2883 unknowns: 66 MB); problems
        are factored in chunks that fit ``memory_fraction`` of the free device memory. Cholesky first; a
        problem whose matrix is not positive definite (the exact, unprojected Hessian away from a stable
        equilibrium) is solved by LU with partial pivoting instead, or, where :attr:`report_indefinite`
        marks it, left unsolved and flagged in :attr:`indefinite`. Problems whose right-hand side is zero
        (converged or inactive) are skipped. The factors are kept until the matrix changes (:meth:`zero`),
        or, with ``keep_factors``, until :meth:`forget_factors` (one (3R)^2 float64 factor per problem
        stays allocated). ``refactor`` as in :meth:`solve_direct`: a problem not marked solves with its
        stored factor by two triangular solves. ``todo``: the problems with a nonzero right-hand side where
        the caller knows them already (:meth:`solve_dense_banded`, the Newton loop's working problems: then
        they are not read from the device). On CUDA the solve is ordered after Warp's queued work and
        Warp's next kernels after it by stream waits on the device, not by host synchronizations.
        Returns (1, largest relative residual of the freshly factored chunks); ``residual=False``: (1, nan),
        without computing it (a batched product and a device synchronization per chunk: the Newton loop
        checks its own residual)."""
        import torch

        n = 3 * self.pattern.rows_per_problem
        dev, values, rhs, increment, todo, fresh = self._torch_solve_start(refactor, todo)
        if not todo:
            self._warp_after_torch()  # the zeroed increment
            return 1, 0.0
        bytes_per_problem = 3 * n * n * 8  # matrix, factor, workspace
        if dev.type == "cuda":
            free, _ = torch.cuda.mem_get_info(dev)
            budget = memory_fraction * free
        else:
            budget = 2e9
        chunk = max(1, int(budget // bytes_per_problem))
        worst = 0.0 if residual else float("nan")
        coupling = self._coupling_entries()
        for ids in [fresh[i : i + chunk] for i in range(0, len(fresh), chunk)]:
            index = torch.as_tensor(ids, device=dev)
            A = self._whole_matrices(values, index, coupling)
            if len(ids) <= DENSE_LOOP_MAX_PROBLEMS:
                # a few problems: one factorization each (cuSOLVER's batched potrf has a large fixed cost)
                L, info = self._cholesky_each(A)
            else:
                L, info = torch.linalg.cholesky_ex(A)
                # kept factors are copied out of the batch, which would otherwise stay allocated as a whole
                L = [L[k].clone() if self.keep_factors else L[k] for k in range(len(ids))]
                info = info.tolist()
            # not positive definite (exact Hessian off a stable equilibrium): reported unsolved
            # (report_indefinite), their earlier (kept) factorizations out of date; the others LU-factored
            report = self._reported(ids, info)
            if report:
                for p in report:
                    self._dense_factors.pop(p, None)
                keep = [k for k, p in enumerate(ids) if p not in report]
                ids, index, A = [ids[k] for k in keep], index[keep], A[keep]
                L, info = [L[k] for k in keep], [info[k] for k in keep]
                if not ids:
                    continue
            for k, p in enumerate(ids):  # LU with partial pivoting where Cholesky broke down
                self._dense_factors[p] = (
                    ("lu", *torch.linalg.lu_factor(A[k])) if info[k] else ("cholesky", L[k])
                )
            x = self._dense_substitute(ids, rhs)
            self._store_solution(increment, index, x)
            if residual:
                if x.dim() == 3:  # the residual of the Newton step's right-hand side (the first column)
                    x = x[..., 0]
                b_ = rhs[index] if rhs.dim() == 2 else rhs[index, :, 0]
                res = torch.linalg.vector_norm(torch.bmm(A, x.unsqueeze(2)).squeeze(2) - b_, dim=1)
                norm = torch.linalg.vector_norm(b_, dim=1).clamp_min(torch.finfo(torch.float64).tiny)
                worst = max(worst, float((res / norm).max()))
            del A, L, x
        fresh = set(fresh)
        reused = [p for p in todo if p not in fresh]
        for ids in [reused[i : i + chunk] for i in range(0, len(reused), chunk)]:
            index = torch.as_tensor(ids, device=dev)
            x = self._dense_substitute(ids, rhs)
            if coupling is not None:  # factors of the pattern alone, made by the banded solver
                x = self._solve_coupled(ids, x, coupling)
            self._store_solution(increment, index, x)
        self._warp_after_torch()
        return 1, worst

    def _cholesky_each(self, A) -> tuple[list, list[int]]:
        """Cholesky factorization of each matrix of ``A`` (m, n, n) on its own: (factors, LAPACK infos).

        On CUDA with :attr:`factor_streams` > 1 the factorizations run on that many side streams, the
        current stream waiting for them all (the side streams first wait for the current one, which built
        ``A``); the infos come back in one device read."""
        import torch

        m = A.shape[0]
        count = min(self.factor_streams, m) if A.device.type == "cuda" else 1
        if count <= 1:
            factors = [torch.linalg.cholesky_ex(A[k]) for k in range(m)]
        else:
            current = torch.cuda.current_stream(A.device)
            while len(self._side_streams) < count:
                self._side_streams.append(torch.cuda.Stream(device=A.device))
            side = self._side_streams[:count]
            factors = []
            for s in side:
                s.wait_stream(current)
                A.record_stream(s)  # A's memory is not reused before the side streams are done with it
            for k in range(m):
                with torch.cuda.stream(side[k % count]):
                    factors.append(torch.linalg.cholesky_ex(A[k]))
                for t in factors[-1]:
                    t.record_stream(current)  # used (and freed) on the current stream
            for s in side:
                current.wait_stream(s)
        L = [f[0] for f in factors]
        info = torch.stack([f[1] for f in factors]).tolist()
        return L, info

    def solve_dense_banded(
        self,
        refactor: np.ndarray | None = None,
        banded_from: int = 4,
        residual: bool = True,
        todo: list[int] | None = None,
    ) -> tuple[int, float]:
        """:meth:`solve_dense` when fewer than ``banded_from`` problems need a new factorization,
        :meth:`solve_banded` otherwise (both exact; their factors are stored side by side and substituted
        alike). The dense solver costs about one cuSOLVER factorization per problem, the banded one a
        fixed ~9 ms for any batch up to ~16 problems and then little per problem (one H100, the 960-vertex
        box: 1 / 16 / 100 problems dense 3.1 / 32.4 / 142.8 ms, banded 9.1 / 22.7 / 37.2 ms): one call breaks
        even near 7 problems; over the whole FEM benchmark (100 squeeze ramps of that box) ``banded_from``
        4 / 8 / 12 / 16 / 32 took 89.6 / 79.1 / 75.6 / 77.6 / 81.0 s against 92.8 s dense (session 28, with
        triangular-solve substitutions; since they are batched products 4 is the fastest of 4 / 8 / 12:
        ``SolverOptions.banded_min_problems``, the solver's default, says by how much). Which solver
        factors a problem depends on how many others factor with it, so its answer may differ in round-off
        with the batch (as the batched banded solver's already may). ``residual`` and ``todo`` as in
        :meth:`solve_dense`."""
        if banded_from < 1:
            raise ValueError(f"banded_from must be >= 1, got {banded_from}")
        if todo is None:
            todo = self._problems_with_rhs()
        count = sum(1 for p in todo if p not in self._dense_factors or (refactor is not None and refactor[p]))
        solve = self.solve_banded if count >= banded_from else self.solve_dense
        return solve(refactor, todo=todo, residual=residual)

    def banded_layout(self) -> BlockTridiagonalLayout:
        """The block-tridiagonal layout of this system's pattern (built on first use)."""
        if self._banded_layout is None:
            p = self.pattern
            self._banded_layout = BlockTridiagonalLayout.build(
                p.rows, p.cols, p.num_vertices, p.num_dofs, self.points
            )
        return self._banded_layout

    def solve_banded(
        self, refactor: np.ndarray | None = None, todo: list[int] | None = None, residual: bool = True
    ) -> tuple[int, float]:
        """Batched block-tridiagonal Cholesky of each problem's Hessian on the system's device, exact to
        round-off (:mod:`defgraspnets.fem.block_tridiagonal`): the vertices in breadth-first levels, the
        travel rows eliminated through their Schur complement.

        All problems to factor go in one batch (a factor holds sum_i s_i (s_i + s_{i-1}) + n_v n_t + n_t^2
        float64 per problem: 11 MB for the 960-vertex box, against 66 MB dense). A problem whose matrix
        is not positive definite is factored by block LU (partial pivoting inside the blocks), and by
        dense LU with partial pivoting if a pivot block is singular (or flagged unsolved,
        :attr:`report_indefinite`). With :attr:`coupling` (self-contact) the block-tridiagonal factors hold
        the pattern alone and every solution is updated to the whole matrix (:meth:`_solve_coupled`); the
        dense LU fallback factors the whole matrix. ``refactor``, skipped problems and kept factors and
        ``todo`` as in :meth:`solve_dense`. Returns (1, largest relative residual of the freshly factored
        problems)."""
        import torch

        layout = self.banded_layout()
        dev, values, rhs, increment, todo, fresh = self._torch_solve_start(refactor, todo)
        if not todo:
            self._warp_after_torch()  # the zeroed increment
            return 1, 0.0
        coupling = self._coupling_entries()  # None without self-contact
        worst = 0.0
        if fresh:
            if self._banded_scatter is None:
                self._banded_scatter = tuple(
                    torch.as_tensor(a, device=dev) for a in (layout.source, layout.target)
                )
            source, target = self._banded_scatter

            def factor(ids, lu):
                """Factor problems ``ids``; returns those whose factorization broke down."""
                index = torch.as_tensor(ids, device=dev)
                packed = torch.zeros(len(ids), layout.size, dtype=torch.float64, device=dev)
                packed[:, target] = values.index_select(0, index)[:, source]
                made = BlockTridiagonalFactor(layout, packed, lu=lu, graphs=self._graphs())
                failed = made.failed.tolist()
                for k, p in enumerate(ids):
                    self._dense_factors[p] = ("banded", made, k)
                return [p for k, p in enumerate(ids) if failed[k]]

            # CUDA: one batch; CPU: one problem at a time (batched BLAS calls round differently for other
            # batch sizes, and a problem's answer must not depend on its batch; LAPACK loops anyway)
            batches = [fresh] if dev.type == "cuda" else [[p] for p in fresh]
            # not positive definite (exact Hessian off a stable equilibrium): reported unsolved
            # (report_indefinite), or block LU with partial pivoting inside the blocks, and dense LU where
            # a pivot block is singular
            indefinite = [p for ids in batches for p in factor(ids, lu=False)]
            report = self._reported(indefinite)
            if report:
                for p in report:
                    del self._dense_factors[p]  # its broken factorization must not be used
                indefinite = [p for p in indefinite if p not in report]
                todo = [p for p in todo if p not in report]
                fresh = [p for p in fresh if p not in report]
            batches = [indefinite] if dev.type == "cuda" else [[p] for p in indefinite]
            singular = [p for ids in batches if ids for p in factor(ids, lu=True)]
            if singular:
                A = self._whole_matrices(values, torch.as_tensor(singular, device=dev), coupling)
                for k, p in enumerate(singular):
                    self._dense_factors[p] = ("lu", *torch.linalg.lu_factor(A[k]))
                del A
        if todo:
            x = self._dense_substitute(todo, rhs)
            if coupling is not None:
                x = self._solve_coupled(todo, x, coupling)
            self._store_solution(increment, torch.as_tensor(todo, device=dev), x)
        if fresh and residual:
            worst = (
                self._relative_residual(fresh)
                if coupling is None
                else self._coupled_residual(fresh, rhs, increment, values, coupling)
            )
        elif fresh:
            worst = float("nan")
        self._warp_after_torch()
        return 1, worst

    def factor_graph_counts(self) -> dict | None:
        """Captures, replays and memory [bytes] of the banded factorization's CUDA graphs so far, or None
        (none made: off, the CPU, or no banded factorization yet)."""
        g = self._factor_graphs
        return None if g is None else {"captures": g.captures, "replays": g.replays, "bytes": g.bytes}

    def _graphs(self) -> FactorGraphs | None:
        """The banded factorization's CUDA graphs (:attr:`factor_graphs`), or None (off, or the CPU)."""
        if not (self.device.is_cuda and self.factor_graphs > 0):
            return None
        if self._factor_graphs is None or self._factor_graphs.memory_fraction != self.factor_graphs:
            self._factor_graphs = FactorGraphs(self.banded_layout(), self.factor_graphs)
        return self._factor_graphs

    def _reported(self, ids: list[int], info=None) -> set[int]:
        """The problems of ``ids`` whose Cholesky factorization broke down (``info`` nonzero, per problem;
        None: all of them) and that :attr:`report_indefinite` asks to report: marked in
        :attr:`indefinite`, not solved."""
        if self.report_indefinite is None:
            return set()
        broke = [True] * len(ids) if info is None else [bool(i) for i in info]
        report = {p for p, b in zip(ids, broke) if b and self.report_indefinite[p]}
        self.indefinite[list(report)] = True
        return report

    def _relative_residual(self, problems: list[int]) -> float:
        """max over ``problems`` of |H increment - rhs| / |rhs| (one batched sparse product)."""
        import torch

        if self.device.is_cuda:
            torch.cuda.synchronize(self.device.ordinal)  # the increment was written by PyTorch
        if self._product is None:
            self._product = wp.zeros_like(self.increment)
        product = self._product
        wps.bsr_mv(self.matrix, self.increment, product, beta=0.0)
        wp.synchronize_device(self.device)
        B, n = self.batch_size, 3 * self.pattern.rows_per_problem
        index = torch.as_tensor(problems, device=wp.device_to_torch(self.device))
        b = wp.to_torch(self.rhs).reshape(B, n).index_select(0, index)
        r = wp.to_torch(product).reshape(B, n).index_select(0, index) - b
        norm = torch.linalg.vector_norm(b, dim=1).clamp_min(torch.finfo(torch.float64).tiny)
        return float((torch.linalg.vector_norm(r, dim=1) / norm).max())

    def _dense_substitute(self, ids: list[int], rhs):
        """(len(ids), n) solutions of the listed problems' right-hand sides (B, n) with their stored
        factors; (len(ids), n, k) for (B, n, k) right-hand sides (k columns solved together).

        Dense Cholesky: two triangular solves (trsm) per factor, not cholesky_solve (its batched potrs
        costs ~36 ms for any batch of two or more 2883-unknown problems on an H100, the triangular solves
        0.9-7 ms); on CUDA the factors are stacked and solved as one batch, on the CPU one by one (no
        copies of the factors; LAPACK solves a batch one matrix at a time anyway). Block-tridiagonal
        factors: one batched substitution per factorization batch. LU: one solve each."""
        import torch

        return self._substitute(ids, rhs[torch.as_tensor(ids, device=rhs.device)])

    def _substitute(self, ids: list[int], b):
        """:meth:`_dense_substitute` of right-hand sides ``b`` (len(ids), n[, k]) already gathered."""
        import torch

        vector = b.dim() == 2
        if vector:
            b = b.unsqueeze(2)
        x = torch.empty_like(b)
        factors = [self._dense_factors[p] for p in ids]
        chol = [k for k, f in enumerate(factors) if f[0] == "cholesky"]
        if b.device.type == "cuda" and len(chol) > 1:
            L = torch.stack([factors[k][1] for k in chol])
            k = torch.as_tensor(chol, device=b.device)
            y = torch.linalg.solve_triangular(L, b[k], upper=False)
            x[k] = torch.linalg.solve_triangular(L.transpose(1, 2), y, upper=True)
        else:
            for k in chol:
                L = factors[k][1]
                y = torch.linalg.solve_triangular(L, b[k], upper=False)
                x[k] = torch.linalg.solve_triangular(L.T, y, upper=True)
        groups: dict[int, tuple] = {}  # block-tridiagonal factorization batch -> (factor, [k], [position])
        for k, f in enumerate(factors):
            if f[0] == "lu":
                x[k] = torch.linalg.lu_solve(f[1], f[2], b[k])
            elif f[0] == "banded":
                group = groups.setdefault(id(f[1]), (f[1], [], []))
                group[1].append(k)
                group[2].append(f[2])
        for factor, ks, positions in groups.values():
            k = torch.as_tensor(ks, device=b.device)
            everything = positions == list(range(len(factor.failed)))
            rows = None if everything else torch.as_tensor(positions, device=b.device)
            x[k] = factor.solve(b[k], rows)
        return x.squeeze(2) if vector else x

    def _coupled_product(self, values, index, coupling, x):
        """(m, n) products with ``x`` (m, n) of the whole matrices of the problems ``index`` (a LongTensor):
        the pattern's blocks ``values`` plus the couplings and their transposes (``coupling``: their scalar
        entries, :meth:`_coupling_entries`)."""
        import torch

        if self._pattern_index is None:
            self._pattern_index = tuple(
                torch.as_tensor(a.astype(np.int64), device=x.device)
                for a in (self.pattern.rows, self.pattern.cols)
            )
        rows, cols = self._pattern_index
        m, n = x.shape
        blocks = values.index_select(0, index).view(m, -1, 3, 3)
        xv = x.view(m, n // 3, 3)
        y = torch.zeros_like(xv).index_add_(1, rows, torch.einsum("mkij,mkj->mki", blocks, xv[:, cols]))
        y = y.view(m, n)
        r, c, v = (a.index_select(0, index) for a in coupling)
        y.scatter_add_(1, r, v * torch.gather(x, 1, c))
        y.scatter_add_(1, c, v * torch.gather(x, 1, r))
        return y

    def _solve_coupled(self, ids: list[int], x, coupling):
        """Solutions of the problems ``ids`` with their whole matrices K = A + E: A the pattern's blocks
        (the stored factors), E the couplings outside the pattern and their transposes (``coupling``, as
        :meth:`_coupling_entries`), from ``x`` = A^-1 rhs (:meth:`_dense_substitute`'s shape).

        E is nonzero on the few unknowns of the self-contact pairs only: E = P E_s P^T with P their unit
        columns (m of them, a few per pair) and E_s the m x m couplings. Then (Woodbury, with E_s singular
        allowed) K^-1 b = x - Y E_s (I + G E_s)^-1 P^T x with Y = A^-1 P (one substitution of m columns) and
        G = P^T Y: exact to round-off, for indefinite matrices too (LU-factored blocks). Only problems whose
        stored factor is block-tridiagonal (the pattern alone) are updated: the dense factors (Cholesky, LU)
        hold the couplings already; a problem without couplings keeps ``x``. On the CPU one problem at a
        time (its answer must not depend on its batch), on CUDA all coupled ones at once (padded to the
        largest m)."""
        import torch

        dev = x.device
        vector = x.dim() == 2
        x = (x.unsqueeze(2) if vector else x).clone()
        rows, cols, entries = coupling
        has_pairs = (entries != 0).any(dim=1).tolist()  # one device synchronization
        coupled = [k for k, p in enumerate(ids) if has_pairs[p] and self._dense_factors[p][0] == "banded"]
        groups = [coupled] if dev.type == "cuda" else [[k] for k in coupled]
        for group in groups:
            if group:
                problems = [ids[j] for j in group]
                k, p = (torch.as_tensor(a, device=dev) for a in (group, problems))
                x[k] = self._low_rank_update(problems, x[k], rows[p], cols[p], entries[p])
        return x.squeeze(2) if vector else x

    def _low_rank_update(self, problems: list[int], x, rows, cols, entries):
        """:meth:`_solve_coupled` of one batch: ``x`` (g, n, k) the stored (banded) factors' solutions of
        ``problems``, ``rows``, ``cols``, ``entries`` (g, 9 C) their couplings' scalar entries; the unknowns
        of the problems' pairs padded to the largest count (a padded unknown has a zero unit column and
        zero couplings, so it changes nothing). Returns the whole matrices' solutions (g, n, k)."""
        import torch

        dev = x.device
        dofs, E_s = [], []
        for r, c, v in zip(rows, cols, entries):
            nonzero = v != 0
            r, c, v = r[nonzero], c[nonzero], v[nonzero]
            unknowns, local = torch.unique(torch.cat([r, c]), return_inverse=True)
            m = len(unknowns)
            block = torch.zeros(m, m, dtype=v.dtype, device=dev)
            block.index_put_((local[: len(r)], local[len(r) :]), v, accumulate=True)
            dofs.append(unknowns)
            E_s.append(block + block.T)
        g, n, width = len(problems), x.shape[1], max(len(d) for d in dofs)
        index = torch.zeros(g, width, dtype=torch.long, device=dev)
        units = torch.zeros(g, n, width, dtype=x.dtype, device=dev)
        E = torch.zeros(g, width, width, dtype=x.dtype, device=dev)
        for j, (d, e) in enumerate(zip(dofs, E_s)):
            m = len(d)
            index[j, :m] = d
            units[j, d, torch.arange(m, device=dev)] = 1.0
            E[j, :m, :m] = e
        Y = self._substitute(problems, units)  # (g, n, width) = A^-1 P
        G = torch.gather(Y, 1, index.unsqueeze(2).expand(-1, -1, width))  # P^T A^-1 P
        I = torch.eye(width, dtype=x.dtype, device=dev).expand(g, -1, -1)
        t = torch.gather(x, 1, index.unsqueeze(2).expand(-1, -1, x.shape[2]))  # P^T x
        correction = torch.linalg.solve(I + torch.bmm(G, E), t)
        return x - torch.bmm(Y, torch.bmm(E, correction))

    def _coupled_residual(self, problems: list[int], rhs, increment, values, coupling) -> float:
        """max over ``problems`` of |K increment - rhs| / |rhs| with the whole matrices K."""
        import torch

        index = torch.as_tensor(problems, device=increment.device)
        b = rhs[index] if rhs.dim() == 2 else rhs[index, :, 0]
        res = self._coupled_product(values, index, coupling, increment[index]) - b
        norm = torch.linalg.vector_norm(b, dim=1).clamp_min(torch.finfo(torch.float64).tiny)
        return float((torch.linalg.vector_norm(res, dim=1) / norm).max())

    def solve_amg(self, near_nullspace: np.ndarray, rtol: float, maxiter: int) -> tuple[int, float]:
        """CG preconditioned by smoothed-aggregation algebraic multigrid (pyamg) on the host, with the
        rigid-body modes as near-null space (about 20-30 iterations for elasticity at any mesh size).

        Each problem's block is solved on its own, to ``rtol`` times its own right-hand side (one global
        criterion would let problems with large residuals drown those with small ones). The Hessian
        changes little between Newton iterations: each problem keeps the multigrid hierarchy of an earlier
        matrix as preconditioner and rebuilds it only when CG needs clearly more iterations than it did."""
        import pyamg
        import pyamg.krylov

        A = self.host_matrix()
        b = self.rhs.numpy().reshape(-1)
        x = np.zeros_like(b)
        n = 3 * self.pattern.rows_per_problem
        total, worst = 0, 0.0
        for p in range(self.batch_size):
            rows = slice(p * n, (p + 1) * n)
            bp = b[rows]
            if not np.any(bp):
                continue
            Ap = A[rows, rows]
            cached = self._amg.get(p)
            for rebuild in (cached is None, True):
                if rebuild:
                    cached = [
                        pyamg.smoothed_aggregation_solver(
                            Ap, B=near_nullspace[rows], BH=near_nullspace[rows].copy()
                        ),
                        None,
                    ]
                    self._amg[p] = cached
                residuals: list[float] = []
                xp, info = pyamg.krylov.cg(
                    Ap,
                    bp,
                    tol=rtol,
                    maxiter=maxiter,
                    M=cached[0].aspreconditioner(cycle="V"),
                    residuals=residuals,
                )
                total = max(total, len(residuals))
                if cached[1] is None:
                    cached[1] = len(residuals)
                    break
                if info == 0 and len(residuals) <= 2 * cached[1] + 10:
                    break
            x[rows] = xp
            worst = max(worst, residuals[-1] / np.linalg.norm(bp) if residuals else 0.0)
        self._set_increment(x)
        return total, worst
