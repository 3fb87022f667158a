"""Tetrahedral meshes: geometry, topology and validation.

A :class:`TetMesh` is the reference (undeformed) configuration of a deformable body:
``points`` (N, 3) in metres and ``tets`` (M, 4) vertex indices, positively oriented
(``det[x1-x0, x2-x0, x3-x0] > 0``). Everything the solver needs that depends only on the
mesh is derived here once, on the host, with NumPy:

- rest volumes ``V_e = det(D_m) / 6`` and inverse rest shape matrices ``D_m^-1``,
- the boundary surface (faces used by exactly one tet, oriented outward),
- lumped vertex masses ``m_i = sum_e rho V_e / 4`` and lumped surface areas,
- unique edges (for graphs) and a characteristic element size per vertex.

Invalid input raises :class:`MeshError` naming the problem and the offending indices.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

__all__ = ["MeshError", "TetMesh"]

# local vertex triples of the four faces of a tet, ordered so that the face normal
# (b - a) x (c - a) points away from the opposite vertex for a positively oriented tet
_TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)


class MeshError(ValueError):
    """A mesh is unusable: non-finite coordinates, bad indices, inverted or degenerate elements."""


def _summarize(indices: np.ndarray, limit: int = 8) -> str:
    idx = np.asarray(indices).ravel()
    head = ", ".join(str(int(i)) for i in idx[:limit])
    return f"[{head}{', ...' if idx.size > limit else ''}] ({idx.size} in all)"


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated linear tetrahedral mesh in its rest configuration (SI units: metres).

    Args:
        points: (N, 3) vertex coordinates [m].
        tets: (M, 4) vertex indices of each tetrahedron, positively oriented.
        name: optional label used in error messages and outputs.
        degenerate_tol: a tet whose volume is below ``degenerate_tol * (mean edge length)^3``
            is degenerate (a regular tet has ``0.118 * l^3``).

    Raises:
        MeshError: for non-finite coordinates, out-of-range or repeated indices within a tet,
            unreferenced vertices, inverted (negative volume) or degenerate (near-zero volume) tets.
    """

    points: np.ndarray
    tets: np.ndarray
    name: str = "mesh"
    degenerate_tol: float = 1e-6
    _validated: bool = field(default=False, repr=False)

    def __post_init__(self):
        try:
            points = np.ascontiguousarray(np.asarray(self.points, dtype=np.float64))
        except (TypeError, ValueError) as err:
            raise MeshError(f"{self.name}: points must be an (N, 3) array of numbers [m] ({err})") from None
        tets = np.asarray(self.tets)
        if tets.size and not np.issubdtype(tets.dtype, np.integer):
            if not np.all(np.isfinite(tets)) or np.any(tets != np.round(tets)):
                raise MeshError(f"{self.name}: tet indices must be integers")
        tets = np.ascontiguousarray(tets.astype(np.int64))
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", tets)
        self._validate()
        points.setflags(write=False)
        tets.setflags(write=False)

    # ------------------------------------------------------------------ validation
    def _validate(self) -> None:
        p, t, name = self.points, self.tets, self.name
        if p.ndim != 2 or p.shape[1] != 3:
            raise MeshError(f"{name}: points must have shape (N, 3), got {p.shape}")
        if t.ndim != 2 or t.shape[1] != 4:
            raise MeshError(f"{name}: tets must have shape (M, 4), got {t.shape}")
        if len(p) < 4 or len(t) < 1:
            raise MeshError(f"{name}: needs at least 4 points and 1 tet, got {len(p)} points, {len(t)} tets")
        bad = ~np.all(np.isfinite(p), axis=1)
        if bad.any():
            raise MeshError(
                f"{name}: non-finite (NaN or inf) coordinates at vertices {_summarize(np.nonzero(bad)[0])}"
            )
        out = np.any((t < 0) | (t >= len(p)), axis=1)
        if out.any():
            raise MeshError(
                f"{name}: tets {_summarize(np.nonzero(out)[0])} reference vertices outside [0, {len(p)})"
            )
        s = np.sort(t, axis=1)
        rep = np.any(s[:, 1:] == s[:, :-1], axis=1)
        if rep.any():
            raise MeshError(
                f"{name}: tets {_summarize(np.nonzero(rep)[0])} repeat a vertex (collapsed elements)"
            )
        used = np.zeros(len(p), dtype=bool)
        used[t.ravel()] = True
        if not used.all():
            raise MeshError(
                f"{name}: vertices {_summarize(np.nonzero(~used)[0])} are not used by any tet "
                "(unreferenced vertices have no stiffness; remove them, e.g. with TetMesh.compacted)"
            )
        vol = self.volumes_signed
        inverted = vol < 0
        if inverted.any():
            raise MeshError(
                f"{name}: tets {_summarize(np.nonzero(inverted)[0])} are inverted (negative volume); "
                "reorder their vertices (TetMesh.oriented fixes a consistently mis-ordered mesh)"
            )
        lengths = np.linalg.norm(p[t[:, [1, 2, 3, 2, 3, 3]]] - p[t[:, [0, 0, 0, 1, 1, 2]]], axis=2)
        scale = lengths.mean(axis=1) ** 3
        degenerate = vol <= self.degenerate_tol * scale
        if degenerate.any():
            raise MeshError(
                f"{name}: tets {_summarize(np.nonzero(degenerate)[0])} are degenerate "
                f"(volume below {self.degenerate_tol:g} x edge^3: flat or sliver elements)"
            )

    # ------------------------------------------------------------------ constructors
    @classmethod
    def oriented(cls, points, tets, **kwargs) -> TetMesh:
        """Build a mesh after swapping two vertices of every negatively oriented tet."""
        points = np.asarray(points, dtype=np.float64)
        tets = np.array(tets, dtype=np.int64, copy=True)
        d = points[tets[:, 1:]] - points[tets[:, :1]]
        neg = np.linalg.det(d) < 0
        tets[neg] = tets[neg][:, [0, 2, 1, 3]]
        return cls(points, tets, **kwargs)

    @classmethod
    def compacted(cls, points, tets, **kwargs) -> TetMesh:
        """Build a mesh after dropping vertices that no tet references (indices are remapped)."""
        points = np.asarray(points, dtype=np.float64)
        tets = np.asarray(tets, dtype=np.int64)
        used, inverse = np.unique(tets.ravel(), return_inverse=True)
        return cls(points[used], inverse.reshape(tets.shape), **kwargs)

    @classmethod
    def box(cls, size=(1.0, 1.0, 1.0), divisions=(2, 2, 2), origin=(0.0, 0.0, 0.0), name="box") -> TetMesh:
        """Structured box ``[origin, origin + size]`` split into ``divisions`` hexes of 6 tets each.

        Each hex is split into 6 tets around a main diagonal (Kuhn), reflected cell by cell so the mesh is
        conforming and mirror-symmetric about the grid planes (about the box centre for even divisions).
        """
        nx, ny, nz = (int(d) for d in divisions)
        if min(nx, ny, nz) < 1:
            raise MeshError(f"{name}: divisions must be >= 1, got {divisions}")
        xs = [np.linspace(o, o + s, n + 1) for o, s, n in zip(origin, size, (nx, ny, nz))]
        return cls.from_grid(*xs, name=name)

    @classmethod
    def from_grid(cls, xs, ys, zs, name="grid") -> TetMesh:
        """Tensor-product grid with (possibly graded) coordinates ``xs, ys, zs``, 6 tets per hex."""
        xs, ys, zs = (np.asarray(a, dtype=np.float64) for a in (xs, ys, zs))
        X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
        points = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        nx, ny, nz = len(xs) - 1, len(ys) - 1, len(zs) - 1

        def vid(i, j, k):
            return (i * (ny + 1) + j) * (nz + 1) + k

        i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
        # hex corners c[b] with b = 4*dx + 2*dy + dz, each cell reflected by the parity of its index so that
        # shared faces get the same diagonal (conforming) and the mesh is mirror-symmetric about grid planes
        pi, pj, pk = i % 2, j % 2, k % 2
        c = np.stack(
            [
                vid(i + (dx ^ pi), j + (dy ^ pj), k + (dz ^ pk))
                for dx in (0, 1)
                for dy in (0, 1)
                for dz in (0, 1)
            ],
            axis=1,
        )
        # Kuhn split along the main diagonal c0 -> c7: one tet per permutation of the axes
        paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
        tets = np.concatenate([np.stack([c[:, 0], c[:, a], c[:, b], c[:, 7]], axis=1) for a, b in paths])
        return cls.oriented(points, tets, name=name)

    @classmethod
    def from_meshio(cls, mesh, name: str | None = None) -> TetMesh:
        """Build from a :class:`meshio.Mesh` holding ``tetra`` cells (other cell types are ignored)."""
        tets = [c.data for c in mesh.cells if c.type == "tetra"]
        if not tets:
            raise MeshError(f"{name or 'mesh'}: no tetra cells (found {[c.type for c in mesh.cells]})")
        return cls.compacted(mesh.points[:, :3], np.concatenate(tets), name=name or "mesh")

    @classmethod
    def load(cls, path: str | Path, name: str | None = None) -> TetMesh:
        """Read any tetrahedral format meshio understands (.vtu, .msh, .mesh, .xdmf, ...)."""
        import meshio

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"tet mesh file not found: {path}")
        if not path.is_file():
            raise MeshError(f"{path}: not a file (a tet mesh file such as .vtu or .msh was expected)")
        try:
            data = meshio.read(path)
        except (Exception, SystemExit) as e:  # meshio's XML readers call sys.exit on a malformed file
            detail = f"{type(e).__name__}: {e}" if not isinstance(e, SystemExit) else "malformed file"
            raise MeshError(f"{path}: not a readable tet mesh file ({detail})") from e
        return cls.from_meshio(data, name=name or path.stem)

    def to_meshio(self, point_data: dict | None = None, cell_data: dict | None = None, points=None):
        """A :class:`meshio.Mesh` (optionally at deformed ``points``) with per-vertex/per-tet fields."""
        import meshio

        cd = {k: [np.asarray(v)] for k, v in (cell_data or {}).items()}
        return meshio.Mesh(
            self.points if points is None else np.asarray(points),
            [("tetra", self.tets)],
            point_data={k: np.asarray(v) for k, v in (point_data or {}).items()},
            cell_data=cd,
        )

    def save(self, path: str | Path, **fields) -> None:
        """Write the mesh (and fields, see :meth:`to_meshio`) with meshio, e.g. to .vtu for ParaView."""
        self.to_meshio(**fields).write(str(path))

    # ------------------------------------------------------------------ geometry
    @property
    def num_vertices(self) -> int:
        return len(self.points)

    @property
    def num_tets(self) -> int:
        return len(self.tets)

    @cached_property
    def volumes_signed(self) -> np.ndarray:
        d = self.points[self.tets[:, 1:]] - self.points[self.tets[:, :1]]  # (M, 3 edges, 3 xyz)
        return np.linalg.det(d) / 6.0

    @property
    def volumes(self) -> np.ndarray:
        """(M,) rest volume of each tet [m^3]."""
        return self.volumes_signed

    @cached_property
    def volume(self) -> float:
        """Total rest volume [m^3]."""
        return float(self.volumes_signed.sum())

    @cached_property
    def rest_shape_inverse(self) -> np.ndarray:
        """(M, 3, 3) inverse rest shape matrices ``D_m^-1`` with ``D_m = [X1-X0, X2-X0, X3-X0]`` (columns)."""
        dm = np.transpose(self.points[self.tets[:, 1:]] - self.points[self.tets[:, :1]], (0, 2, 1))
        return np.linalg.inv(dm)

    def vertex_masses(self, density) -> np.ndarray:
        """(N,) lumped masses ``m_i = sum over adjacent tets of rho V_e / 4`` [kg]."""
        m = np.zeros(self.num_vertices)
        np.add.at(m, self.tets.ravel(), np.repeat(density * self.volumes_signed / 4.0, 4))
        return m

    def mass(self, density) -> float:
        return float(density * self.volume)

    def center_of_mass(self) -> np.ndarray:
        """Centroid of the (uniform density) volume [m]."""
        c = self.points[self.tets].mean(axis=1)
        return (c * self.volumes_signed[:, None]).sum(axis=0) / self.volume

    @cached_property
    def vertex_tet_volume(self) -> np.ndarray:
        """(N,) sum of the rest volumes of the tets adjacent to each vertex (stress averaging weights)."""
        w = np.zeros(self.num_vertices)
        np.add.at(w, self.tets.ravel(), np.repeat(self.volumes_signed, 4))
        return w

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) unique undirected edges, ``i < j``, sorted."""
        pairs = self.tets[:, [0, 0, 0, 1, 1, 2, 1, 2, 3, 2, 3, 3]].reshape(-1, 2, 6).transpose(0, 2, 1)
        e = np.sort(pairs.reshape(-1, 2), axis=1)
        return np.unique(e, axis=0)

    @cached_property
    def vertex_size(self) -> np.ndarray:
        """(N,) mean length of the edges at each vertex [m] (a local element size)."""
        e = self.edges
        length = np.linalg.norm(self.points[e[:, 0]] - self.points[e[:, 1]], axis=1)
        total = np.zeros(self.num_vertices)
        count = np.zeros(self.num_vertices)
        np.add.at(total, e.ravel(), np.repeat(length, 2))
        np.add.at(count, e.ravel(), 1.0)
        return total / count

    @cached_property
    def median_surface_edge_length(self) -> float:
        """Median length of the boundary triangles' edges [m]."""
        p, f = self.points, self.surface_faces
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        return float(np.median(np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1)))

    @cached_property
    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)

    @cached_property
    def diameter(self) -> float:
        """Length of the bounding-box diagonal [m]."""
        lo, hi = self.bounding_box
        return float(np.linalg.norm(hi - lo))

    # ------------------------------------------------------------------ boundary
    @cached_property
    def surface_faces(self) -> np.ndarray:
        """(F, 3) boundary triangles (faces of exactly one tet), oriented with outward normals."""
        faces = self.tets[:, _TET_FACES].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        boundary = counts[inverse.ravel()] == 1
        return np.ascontiguousarray(faces[boundary])

    @cached_property
    def surface_vertices(self) -> np.ndarray:
        """(S,) sorted indices of the vertices on the boundary surface."""
        return np.unique(self.surface_faces.ravel())

    @cached_property
    def is_surface_vertex(self) -> np.ndarray:
        mask = np.zeros(self.num_vertices, dtype=bool)
        mask[self.surface_vertices] = True
        return mask

    def surface_vertices_inside(self, points, tolerance: float = 1e-6, depth: float = 0.0) -> np.ndarray:
        """Sorted indices of the surface vertices that lie strictly inside a tet they are no vertex of, at
        the deformed ``points`` (N, 3): the object passes through itself there. Without self-contact
        (``SolverOptions.self_contact``) a collapsing hollow object (a thin ring squeezed flat) lets its walls
        pass through each other with no resistance; such a state is no physical answer. ``tolerance``:
        barycentric margin, so a vertex on another tet's face (flat faces pressed together, up to round-off)
        does not count. ``depth`` [m] > 0: nor does a vertex within ``depth`` of a surface triangle it is no
        vertex of (a self-contact penalty's penetration, which holds surface parts that touch within a small
        depth of each other)."""
        x = np.asarray(points, dtype=np.float64)
        if x.shape != self.points.shape:
            raise ValueError(f"points must be {self.points.shape}, got {x.shape}")
        from scipy.spatial import cKDTree

        T = self.tets
        corners = x[T]  # (M, 4, 3)
        centre = corners.mean(axis=1)
        radius = float(np.linalg.norm(corners - centre[:, None], axis=2).max())
        surf = self.surface_vertices
        hits = cKDTree(centre).query_ball_point(x[surf], radius)
        pairs = [(i, m) for i, cand in enumerate(hits) for m in cand]
        if not pairs:
            return np.zeros(0, dtype=np.int64)
        vi, tm = np.array(pairs, dtype=np.int64).T
        v = surf[vi]
        own = np.any(T[tm] == v[:, None], axis=1)
        v, tm = v[~own], tm[~own]
        edges = np.transpose(corners[tm, 1:] - corners[tm, :1], (0, 2, 1))  # (P, 3, 3) columns = edges
        with np.errstate(all="ignore"):
            lam = np.linalg.solve(edges, (x[v] - corners[tm, 0])[..., None])[..., 0]
        bary = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)
        inside = np.all(bary > tolerance, axis=1)
        found = np.unique(v[inside])
        if depth > 0 and found.size:
            found = found[self._surface_distance_beyond(x, found, float(depth))]
        return found

    def _surface_distance_beyond(self, x: np.ndarray, vertices: np.ndarray, depth: float) -> np.ndarray:
        """(len(vertices),) bool: vertex v (at deformed ``x``) is farther than ``depth`` from every surface
        triangle it is no vertex of."""
        from scipy.spatial import cKDTree
        from trimesh.triangles import closest_point

        f = self.surface_faces
        tri = x[f]
        centre = tri.mean(axis=1)
        reach = float(np.linalg.norm(tri - centre[:, None], axis=2).max()) + depth
        hits = cKDTree(centre).query_ball_point(x[vertices], reach)
        beyond = np.ones(len(vertices), dtype=bool)
        for i, (v, cand) in enumerate(zip(vertices.tolist(), hits)):
            cand = np.asarray(cand, dtype=np.int64)
            cand = cand[~np.any(f[cand] == v, axis=1)]
            if cand.size:
                c = closest_point(tri[cand], np.repeat(x[v][None], len(cand), axis=0))
                beyond[i] = np.linalg.norm(c - x[v], axis=1).min() > depth
        return beyond

    def face_normals(self, points=None) -> np.ndarray:
        """(F, 3) area vectors / |.|: unit outward normals of the surface faces (at ``points`` if given)."""
        p = self.points if points is None else np.asarray(points)
        f = self.surface_faces
        n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    @cached_property
    def face_areas(self) -> np.ndarray:
        p, f = self.points, self.surface_faces
        return 0.5 * np.linalg.norm(np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]), axis=1)

    @cached_property
    def vertex_areas(self) -> np.ndarray:
        """(N,) lumped boundary area per vertex (a third of each adjacent surface face) [m^2]; 0 inside."""
        a = np.zeros(self.num_vertices)
        np.add.at(a, self.surface_faces.ravel(), np.repeat(self.face_areas / 3.0, 3))
        return a

    def vertex_normals(self, points=None) -> np.ndarray:
        """(N, 3) area-weighted unit outward normals at surface vertices (zero for interior vertices)."""
        p = self.points if points is None else np.asarray(points)
        f = self.surface_faces
        area_vec = 0.5 * np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
        n = np.zeros_like(p)
        for k in range(3):
            np.add.at(n, f[:, k], area_vec)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def surface_trimesh(self, points=None):
        """The boundary as a :class:`trimesh.Trimesh` over all N vertices (interior ones unreferenced)."""
        import trimesh

        p = self.points if points is None else np.asarray(points)
        return trimesh.Trimesh(p, self.surface_faces, process=False)

    def __repr__(self) -> str:
        return f"TetMesh(name={self.name!r}, vertices={self.num_vertices}, tets={self.num_tets})"
