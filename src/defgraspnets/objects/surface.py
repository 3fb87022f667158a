"""Closed triangle surfaces of solid objects: validation, repair and a content hash.

Every object that enters the pipeline is a *closed, oriented 2-manifold*: each edge is shared by
exactly two triangles with opposite orientation, the surface has one connected component, and the
triangle normals ``(b - a) x (c - a)`` point out of the solid, so that the enclosed volume

    V = 1/6 * sum_f  a_f . (b_f x c_f)

is positive. Tetrahedralization, inside/outside tests and the grasp sampler all rely on this.

:func:`repair_surface` fixes what can be fixed without changing the shape (duplicate vertices
along texture seams, degenerate and duplicate triangles, unreferenced vertices, inconsistent or
inverted winding, small planar holes closed by a fan around the hole centroid) and
:func:`check_surface` raises :class:`ObjectMeshError` naming what is still wrong.
Self-intersections are not detected here; the tetrahedralizer reports them as a volume mismatch.
"""

from __future__ import annotations

import hashlib

import numpy as np
import trimesh

__all__ = [
    "ObjectMeshError",
    "as_trimesh",
    "boundary_loops",
    "check_surface",
    "repair_surface",
    "surface_hash",
]


class ObjectMeshError(ValueError):
    """An object surface is unusable: non-finite, open, non-manifold, several bodies, zero volume."""


def as_trimesh(surface, name: str = "object") -> trimesh.Trimesh:
    """A :class:`trimesh.Trimesh` from a Trimesh or a ``(vertices (V,3), faces (F,3))`` pair (no processing).

    Raises:
        ObjectMeshError: for arrays of the wrong shape or non-finite coordinates.
    """
    if isinstance(surface, trimesh.Trimesh):
        vertices, faces = surface.vertices, surface.faces
    elif isinstance(surface, trimesh.Scene):
        raise ObjectMeshError(
            f"{name}: got a trimesh.Scene; load with force='mesh' or concatenate its geometry"
        )
    else:
        try:
            vertices, faces = surface
        except (TypeError, ValueError) as exc:
            raise ObjectMeshError(
                f"{name}: expected a trimesh.Trimesh or a (vertices, faces) pair, "
                f"got {type(surface).__name__}"
            ) from exc
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ObjectMeshError(f"{name}: vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ObjectMeshError(f"{name}: faces must be integer triangles of shape (F, 3), got {faces.shape}")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise ObjectMeshError(
            f"{name}: {int(bad.sum())} vertices have non-finite (NaN or inf) coordinates, "
            f"first at index {int(np.nonzero(bad)[0][0])}"
        )
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ObjectMeshError(f"{name}: face indices outside [0, {len(vertices)})")
    return trimesh.Trimesh(vertices, faces, process=False, validate=False)


def _edge_use_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique, counts


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops of boundary edges (edges used by one triangle), each as an ordered vertex cycle.

    The loops follow the orientation of the adjacent triangles (directed edge a->b of a triangle), so
    a fan ``(centroid, b, a)`` closes a loop with matching winding. Loops that are not simple cycles
    (a vertex touching two holes) are returned in pieces and will fail :func:`check_surface` later.
    """
    faces = np.asarray(faces, dtype=np.int64)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.ravel()] == 1]
    nxt: dict[int, int] = {}
    for a, b in boundary:
        nxt.setdefault(int(a), int(b))
    loops, seen = [], set()
    for start in list(nxt):
        if start in seen:
            continue
        loop, v = [], start
        while v in nxt and v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        if len(loop) >= 3 and v == start:
            loops.append(np.array(loop, dtype=np.int64))
    return loops


def check_surface(mesh: trimesh.Trimesh, name: str = "object", allow_multiple_bodies: bool = False) -> None:
    """Raise :class:`ObjectMeshError` unless ``mesh`` is a closed, consistently outward-oriented 2-manifold.

    Checks, in order: finite coordinates, at least 4 vertices and 4 faces, no degenerate (zero-area)
    triangles, every edge shared by exactly two triangles (no holes, no non-manifold edges),
    consistent winding, a single connected component (unless ``allow_multiple_bodies``) and a
    positive enclosed volume (outward normals).
    """
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if not np.isfinite(v).all():
        raise ObjectMeshError(f"{name}: non-finite (NaN or inf) vertex coordinates")
    if len(v) < 4 or len(f) < 4:
        raise ObjectMeshError(
            f"{name}: a closed surface needs at least 4 vertices and 4 faces, got {len(v)}, {len(f)}"
        )
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1) / 2
    scale = max(float(np.ptp(v, axis=0).max()), 1e-300)
    degenerate = area <= 1e-14 * scale**2
    if degenerate.any():
        raise ObjectMeshError(f"{name}: {int(degenerate.sum())} degenerate (zero-area) triangles")
    _, counts = _edge_use_counts(f)
    open_edges, nonmanifold = int((counts == 1).sum()), int((counts > 2).sum())
    if nonmanifold:
        raise ObjectMeshError(
            f"{name}: {nonmanifold} non-manifold edges (shared by more than two triangles); "
            "the surface does not bound a single solid"
        )
    if open_edges:
        raise ObjectMeshError(
            f"{name}: not watertight: {open_edges} boundary edges in {len(boundary_loops(f))} holes "
            "(repair_surface fills small holes; larger openings need a closed model)"
        )
    if not mesh.is_winding_consistent:
        raise ObjectMeshError(f"{name}: inconsistent triangle winding (neighbouring normals disagree)")
    bodies = mesh.body_count
    if bodies != 1 and not allow_multiple_bodies:
        raise ObjectMeshError(
            f"{name}: {bodies} disconnected bodies; a deformable object must be one connected solid"
        )
    volume = float(mesh.volume)
    if not volume > 0:
        raise ObjectMeshError(
            f"{name}: enclosed volume {volume:.3g} m^3 is not positive (inward normals or flat surface)"
        )


def _flip_caps(
    faces: np.ndarray, vertices: np.ndarray, rel_tol: float = 1e-9, max_rounds: int = 10
) -> np.ndarray:
    """Remove zero-area "cap" triangles (a vertex b lying on the opposite edge a-c) by edge flips.

    A cap (a, b, c) and its neighbour (a, c, d) across the long edge a-c are replaced by (a, b, d) and
    (b, c, d): the same area, orientation and boundary, without the T-junction at b. A triangle is a cap
    if ``2 area / longest_edge^2 < rel_tol``.
    """
    f = np.array(faces, dtype=np.int64, copy=True)
    for _ in range(max_rounds):
        p = vertices[f]
        length = np.stack(
            [np.linalg.norm(p[:, (k + 2) % 3] - p[:, (k + 1) % 3], axis=1) for k in range(3)], 1
        )
        area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        longest = length.max(axis=1)
        caps = np.nonzero((area2 < rel_tol * longest**2) & (longest > 0))[0]
        if not len(caps):
            break
        edge_face = {}
        for fi, tri in enumerate(f):
            if tri[0] == tri[1] or tri[1] == tri[2] or tri[2] == tri[0]:
                continue  # a repeated vertex (left by merging): dropped later, never a flip partner
            for k in range(3):
                edge_face[(int(tri[k]), int(tri[(k + 1) % 3]))] = fi
        used, changed = set(), False
        for fi in caps:
            if fi in used:
                continue
            k = int(np.argmax(length[fi]))  # vertex opposite the longest edge
            b, c, a = (int(f[fi, (k + j) % 3]) for j in range(3))  # face (a, b, c), long edge c -> a
            gi = edge_face.get((a, c))
            if gi is None or gi in used:
                continue
            d = next((int(x) for x in f[gi] if x not in (a, c)), None)  # the neighbour's third vertex
            if d is None or d == b:
                continue
            f[fi], f[gi] = (a, b, d), (b, c, d)
            used.update((fi, gi))
            changed = True
        if not changed:
            break
    return f


def _fill_holes(mesh: trimesh.Trimesh, max_hole_area_fraction: float) -> trimesh.Trimesh:
    """Close each boundary loop with a fan around its centroid if its area is a small part of the surface."""
    loops = boundary_loops(mesh.faces)
    if not loops:
        return mesh
    v = np.asarray(mesh.vertices)
    total = float(mesh.area)
    new_v, new_f = [v], [np.asarray(mesh.faces)]
    count = len(v)
    for loop in loops:
        pts = v[loop]
        center = pts.mean(axis=0)
        a, b = pts, np.roll(pts, -1, axis=0)
        hole_area = 0.5 * np.linalg.norm(np.cross(a - center, b - center), axis=1).sum()
        if hole_area > max_hole_area_fraction * total:
            continue
        fan = np.stack([np.full(len(loop), count), np.roll(loop, -1), loop], axis=1)
        new_v.append(center[None])
        new_f.append(fan)
        count += 1
    return trimesh.Trimesh(np.concatenate(new_v), np.concatenate(new_f), process=False, validate=False)


def repair_surface(
    surface,
    name: str = "object",
    fill_holes: bool = True,
    max_hole_area_fraction: float = 0.05,
    allow_multiple_bodies: bool = False,
) -> trimesh.Trimesh:
    """Repair a triangle surface and return it validated by :func:`check_surface`.

    Steps: merge coincident vertices (also across texture/normal seams), flip away zero-area "cap"
    triangles (T-junctions), drop remaining degenerate and duplicate triangles and unreferenced
    vertices, close holes whose fan area is below ``max_hole_area_fraction`` of the surface area,
    make the winding consistent and outward.

    Raises:
        ObjectMeshError: naming what could not be repaired (holes too large, non-manifold edges,
            several bodies, non-finite coordinates, ...).
    """
    mesh = as_trimesh(surface, name).copy()
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh = trimesh.Trimesh(
        mesh.vertices, _flip_caps(mesh.faces, np.asarray(mesh.vertices)), process=False, validate=False
    )
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1) / 2
    scale = max(float(np.ptp(v, axis=0).max()) if len(v) else 0.0, 1e-300)
    keep = area > 1e-14 * scale**2
    keep &= f[:, 0] != f[:, 1]
    keep &= f[:, 1] != f[:, 2]
    keep &= f[:, 2] != f[:, 0]
    mesh.update_faces(keep)
    _, first = np.unique(np.sort(mesh.faces, axis=1), axis=0, return_index=True)
    mesh.update_faces(np.sort(first))
    mesh.remove_unreferenced_vertices()
    if fill_holes:
        mesh = _fill_holes(mesh, max_hole_area_fraction)
        mesh.merge_vertices()
    if len(mesh.faces) >= 4:
        trimesh.repair.fix_winding(mesh)
        if mesh.is_watertight and mesh.volume < 0:
            mesh.invert()
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    check_surface(mesh, name, allow_multiple_bodies=allow_multiple_bodies)
    return mesh


def surface_hash(mesh: trimesh.Trimesh, decimals: int = 12) -> str:
    """SHA-256 of the vertex coordinates (rounded to ``decimals`` metres) and triangle indices."""
    h = hashlib.sha256()
    v = np.ascontiguousarray(np.round(np.asarray(mesh.vertices, dtype=np.float64), decimals) + 0.0)
    f = np.ascontiguousarray(np.asarray(mesh.faces, dtype=np.int64))
    h.update(np.asarray(v.shape, dtype=np.int64).tobytes())
    h.update(v.tobytes())
    h.update(np.asarray(f.shape, dtype=np.int64).tobytes())
    h.update(f.tobytes())
    return h.hexdigest()
