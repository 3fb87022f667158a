"""Frictionless self-contact of the object's surface (Warp kernels), ``SolverOptions.self_contact``.

A soft object folds onto itself (a slab bent between the pads) or collapses (a thin ring squeezed flat);
without self-contact its surface parts pass through each other freely. This module adds a penalty between
every surface vertex v and the surface of the same object near it, with the law of the rigid contact
(``contact.py``):

    E_s = E_n(pen),   pen = |x_v - c| if c is inside f and (x_v - c) . n_f < 0 else 0,
    k_v = s kappa E (A_v / 2) / h,   delta = zeta h,

where f = (x_0, x_1, x_2) is the candidate triangle (deformed) that v has penetrated least deeply, c =
sum_i w_i x_i the closest point of f to x_v (w its barycentric weights), n_f its outward unit normal, E_n the
C2 penalty of contact.py with the onset width delta, A_v the vertex's lumped surface area, h the solver's
penalty length (median surface edge) and s = ``SolverOptions.self_contact`` (1: the rigid contact's
stiffness). A triangle counts only where x_v projects into its interior (all w_i > 0; "point in prism"),
so c - x_v is along n_f and pen is the depth below its plane: a vertex beside another part's edge or corner
is never taken for one behind it (a sign from pseudo-normals, tried first, switched from 0 to millimetres
under infinitesimal moves there, where the true nearest surface point is the vertex's own, excluded,
neighbourhood, and stalled Newton's line search). A contact interface is penalized from both sides (each
side's vertices against the other side's triangles), hence A_v / 2: an interface pressure p then
penetrates about (p / E) h / (s kappa) + delta / 2, the rigid contact's tolerance for s = 1.

Gradient (exact: the closest point is stationary, so only the distance's explicit dependence counts): with
the unit push-out direction n = -(x_v - c) / |x_v - c| (= n_f),

    dpen/dx_v = -n,   dpen/dx_i = w_i n,   force on v: f_n n, on the triangle's vertices: -w_i f_n n,

(f_n = dE_n/dpen) so a pair's forces sum to zero. Hessian: Gauss-Newton, k_g J^T J with J = (-n, w_0 n,
w_1 n, w_2 n) and k_g = d^2E_n/dpen^2 (PSD; the distance's curvature dropped, as for rigid contact). A vertex
and the triangle it touches are no mesh neighbours, so of these blocks the solver's fixed block pattern
holds only (v, v) and the triangle's (i, j) (tet edges); the (v, i) couplings are written to
``SelfContact.coupling`` and the "direct" and "dense" linear solvers add them to the matrix they factor
(``BatchedSystem.coupling``): the whole Gauss-Newton Hessian. The banded solver's block-tridiagonal
structure cannot hold couplings between distant vertices: it factors the pattern's blocks and solves the
whole Hessian by a low-rank (Woodbury) update of that factor's solutions (the couplings touch only the
pairs' unknowns: ``BatchedSystem._solve_coupled``). With the pattern's blocks alone (still PSD, so Newton's
direction still descends) Newton crawls: on two pressed blocks the banded and AMG solvers needed 4400
iterations for the first contact increment, not converged, against 46 for the whole press with the
couplings; so self-contact is refused with the CG and AMG solvers.

Models (``SolverOptions.self_contact_model``). The above is "prism" (the default). Its penalty is
discontinuous where a vertex passes between the prisms of two non-coplanar triangles: at a concave crease of
the other surface (a valley seen from the vertex) the two prisms diverge behind the surface, and a vertex in
the wedge between them gets no penalty however deep, the full one a step away (a jump of E_n(pen) that the
line search cannot cross). "feature" measures the penetration as the distance to the closed triangle (its
edges and corners included),

    pen = min |x_v - c_f| over the candidate triangles f that v lies behind at c_f,

where v lies behind f at c_f when (x_v - c_f) . n_f < 0 and, where c_f lies on an edge of f (a corner: two
edges), (x_v - c_f) . n_g < 0 for the triangle g across that edge (``adjacent_triangles``, from the surface's
topology). In a triangle's prism this is the "prism" depth (the same energy); in the wedge behind a concave
crease c_f is on the crease edge and pen the distance from it, equal to the depths of both triangles at their
prism boundaries: continuous. Beside a convex edge or rim the vertex is in front of the triangle across the
edge (outside the object): not held, as with "prism". The closest point is stationary, so the gradient and
the Gauss-Newton Hessian are those above with w the closed triangle's weights (some 0) and n = -(x_v - c_f) /
|x_v - c_f|. Where the acting triangle switches at an edge, both distances are equal or the other is the
smaller one, so for a vertex close to a surface whose triangles' planes describe it (the crease of the
tests) the energy is continuous, with kinks. It is not in general: the test extends single triangles'
planes to the vertex, and for a vertex a sizeable fraction of h from a curved or creased surface a plane's
side can flip while the distance is still large; also at a corner (c_f a vertex of f) only f's two edge
neighbours are tested, not the rest of the corner's fan; an edge without exactly one other triangle
(non-manifold) holds nothing beyond it; and, as for "prism", the candidate set changes between Newton
iterations and at the depth cap. There is no edge-edge term. Measured (``benchmarks/fem_self_contact_cpu.md``,
session 43): worse than "prism" where it matters, hence not the default: the flips occurred for vertices
0.4-0.5 h from the other surface (jumps of E_n(1-2 mm) that stalled the line search), and it failed the thin
ring's squeeze where the walls meet (2.4 N; "prism": 15 N); on the soft cuboid neither carries the fold past
the force maximum.

Candidates. Once per Newton iteration (at assembly, from the deformed state) each surface vertex gets up to
``SELF_CONTACT_CANDIDATES`` nearest triangles, kept for that iteration's line search, so the energies
compared there and the gradient belong to one function (the penalty acts on the one penetrated least deeply at
every state). They are the triangles

- within r = ``SELF_CONTACT_RADIUS`` h of x_v (one ``wp.Mesh`` BVH per problem over the surface
  triangles, refit from the deformed positions each iteration, queried with the box of half width r: O(S
  log S) per iteration, not O(S^2)),
- that are not excluded for v: those incident to v, to its surface 1-ring or to any surface vertex within
  ``SELF_CONTACT_EXCLUSION`` h of v *along the rest surface* (shortest paths over surface edges: the surface
  around v bends but does not touch itself; parts near in space but far apart along the surface, two blocks
  of one mesh, a slot's walls, still contact; a fold sharper than that radius is not resolved).

Depth cap: a triangle that a vertex lies ``SELF_CONTACT_DEPTH`` h or deeper behind at the pairing is no
candidate of it (:func:`self_contact_depth`): the vertex lies inside a wall of the object, not in contact
with it (the outer surface of a thin wall against its own inner surface). Within a Newton iteration a paired
vertex is held however deep it goes (no cap inside the line search: capping the energy there made it drop
to zero at the cap, and a vertex just beyond it that the Newton step moved back jumped to the full penalty:
measured, the line search stalled). This is the tunnelling caveat: a vertex carried deeper than the cap in
one Newton step before it was paired, or pressed that deep, is let through (the squeeze path's step cap,
1 % of the object's size, is below it on the measured meshes; converged penetrations are ~1e-2 h). Where a
vertex passes from the prism of one triangle into that of the next, the penalty is continuous on flat and
convex parts of the other surface; at a concave crease it can drop to zero in the wedge between the two
prisms (a jump bounded by the penetration; "feature" holds it there, see above).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import contact as ck

f64 = wp.float64

#: search radius r of the vertex-triangle pairs, in units of the penalty length h
SELF_CONTACT_RADIUS = 0.5
#: depth cap: a vertex found deeper than this behind a triangle is not paired with it, in units of h
SELF_CONTACT_DEPTH = 0.25
#: candidate triangles kept per surface vertex (the penalty acts on the one penetrated least deeply)
SELF_CONTACT_CANDIDATES = 8
#: rest radius of the surface around a vertex that it does not contact, in units of h
SELF_CONTACT_EXCLUSION = 2.0
#: how a vertex's penetration is measured (``SolverOptions.self_contact_model``): "prism", the depth below
#: the least deep triangle whose prism holds the vertex; "feature", the distance to the least distant
#: triangle (closed: its edges and corners too) that the vertex lies behind at its closest point, and behind
#: the neighbours across the edges that closest point lies on (continuous across triangle boundaries)
SELF_CONTACT_MODELS = ("prism", "feature")


@wp.func
def closest_point_weights(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """Barycentric weights (w_a, w_b, w_c) of the closest point to p on triangle abc (Ericson 5.1.5)."""
    zero = f64(0.0)
    one = f64(1.0)
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return wp.vec3d(one, zero, zero)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.vec3d(zero, one, zero)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        t = d1 / (d1 - d3)
        return wp.vec3d(one - t, t, zero)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.vec3d(zero, zero, one)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        t = d2 / (d2 - d6)
        return wp.vec3d(one - t, zero, t)
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3d(zero, one - t, t)
    denom = one / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3d(one - v - w, v, w)


@wp.struct
class SelfContactArrays:
    """The surface and the pairs, for the kernels (per problem b: vertex rows b N, pair slots b S)."""

    surface: wp.array(dtype=wp.int32)  # (S,) mesh vertex of each surface vertex
    faces: wp.array(dtype=wp.vec3i)  # (F,) surface triangles (outward)
    face_blocks: wp.array2d(dtype=wp.int32)  # (F, 9) BSR block (f_i, f_j) of one problem at 3 i + j
    vertex_block: wp.array(dtype=wp.int32)  # (S,) BSR block (v, v)
    area: wp.array(dtype=wp.float64)  # (S,) lumped surface area A_v [m^2]
    excluded_start: wp.array(dtype=wp.int32)  # (S + 1,) CSR rows of the excluded triangles
    excluded: wp.array(dtype=wp.int32)  # sorted triangle indices per row
    adjacent: wp.array2d(dtype=wp.int32)  # (F, 3) triangle across the edge opposite corner k, -1: none
    pair: wp.array(dtype=wp.int32)  # (B S K,) candidate triangles of each surface vertex, -1: none
    pair_distance: wp.array(dtype=wp.float64)  # (B S K,) their distances at the pairing (scratch)
    candidates: int  # K
    size: f64  # penalty length h [m]
    depth: f64  # depth cap [m]
    num_vertices: int
    model: int  # 0: "prism", 1: "feature"


@wp.func
def is_excluded(sc: SelfContactArrays, s: int, f: int) -> bool:
    """Whether triangle f is in surface vertex s's sorted exclusion row (binary search)."""
    lo = sc.excluded_start[s]
    hi = sc.excluded_start[s + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        e = sc.excluded[mid]
        if e == f:
            return True
        if e < f:
            lo = mid + 1
        else:
            hi = mid
    return False


@wp.func
def face_normal(x0: wp.vec3d, x1: wp.vec3d, x2: wp.vec3d) -> wp.vec3d:
    """Outward unit normal of a surface triangle."""
    return wp.normalize(wp.cross(x1 - x0, x2 - x0))


@wp.kernel
def surface_points_kernel(positions: wp.array(dtype=wp.vec3d), points: wp.array(dtype=wp.vec3)):
    """float32 copies of the deformed positions (the BVHs' points)."""
    i = wp.tid()
    x = positions[i]
    points[i] = wp.vec3(float(x[0]), float(x[1]), float(x[2]))


@wp.func
def feature_behind(
    sc: SelfContactArrays, positions: wp.array(dtype=wp.vec3d), o: int, f: int, r: wp.vec3d, w: wp.vec3d
) -> bool:
    """Model "feature": whether r = x_v - c (c the closest point of triangle f, weights w) points behind f,
    and, where c lies on an edge (w_k = 0: the edge opposite corner k; a corner: two edges), behind the
    triangle across that edge too. In the wedge behind a concave crease (outside both triangles' prisms,
    behind both) the vertex is held at its distance from the crease; beside a convex edge or rim it is in
    front of the triangle across it (outside the object) and free; an edge without a neighbour holds nothing
    beyond it."""
    ids = sc.faces[f]
    x0 = positions[o + ids[0]]
    if wp.dot(r, face_normal(x0, positions[o + ids[1]], positions[o + ids[2]])) >= f64(0.0):
        return False
    for k in range(3):
        if w[k] <= f64(0.0):
            g = sc.adjacent[f, k]
            if g < 0:
                return False
            jd = sc.faces[g]
            ng = face_normal(positions[o + jd[0]], positions[o + jd[1]], positions[o + jd[2]])
            if wp.dot(r, ng) >= f64(0.0):
                return False
    return True


@wp.func
def nearest_penetration(sc: SelfContactArrays, positions: wp.array(dtype=wp.vec3d), o: int, b: int, s: int):
    """The candidate triangle f of surface vertex s (positions of the state at offset o, of problem b) that
    the vertex has penetrated least deeply, -1 if none: x_v projects into its interior (all closest-point
    weights > 0) and lies behind it, (x_v - c) . n_f < 0. Returns f, the penetration pen = |x_v - c| (0 if
    none), the push-out direction n = n_f and the weights w."""
    zero = f64(0.0)
    K = sc.candidates
    first = (b * sc.surface.shape[0] + s) * K
    x = positions[o + sc.surface[s]]
    f = int(-1)  # noqa: UP018
    pen = zero
    n = wp.vec3d()
    w = wp.vec3d()
    for k in range(K):
        g = sc.pair[first + k]
        if g >= 0:
            ids = sc.faces[g]
            x0 = positions[o + ids[0]]
            x1 = positions[o + ids[1]]
            x2 = positions[o + ids[2]]
            wg = closest_point_weights(x, x0, x1, x2)
            if sc.model == 1:
                r = x - (wg[0] * x0 + wg[1] * x1 + wg[2] * x2)
                d = wp.length(r)
                if (f < 0 or d < pen) and feature_behind(sc, positions, o, g, r, wg):
                    f = g
                    pen = d
                    n = face_normal(x0, x1, x2)
                    if d > f64(1e-15):
                        n = -r / d
                    w = wg
            elif wg[0] > zero and wg[1] > zero and wg[2] > zero:
                nf = face_normal(x0, x1, x2)
                r = x - (wg[0] * x0 + wg[1] * x1 + wg[2] * x2)
                d = wp.length(r)
                if wp.dot(r, nf) < zero and (f < 0 or d < pen):
                    f = g
                    pen = d
                    n = nf
                    if d > f64(1e-15):
                        n = -r / d
                    w = wg
    return f, pen, n, w


@wp.func
def pair_stiffness(sc: SelfContactArrays, kappa: f64, youngs: f64, s: int) -> f64:
    """k_v = kappa E (A_v / 2) / h of surface vertex s: an interface is penalized from both sides."""
    return ck.contact_stiffness(kappa, youngs, f64(0.5) * sc.area[s], sc.size)


@wp.kernel
def pair_kernel(
    positions: wp.array(dtype=wp.vec3d),
    meshes: wp.array(dtype=wp.uint64),
    radius: f64,
    sc: SelfContactArrays,
):
    """The K nearest non-excluded triangles within ``radius`` of each surface vertex (-1: none), leaving out
    those the vertex lies in the prism of and the depth cap or deeper behind (in a wall, not in contact)."""
    b, s = wp.tid()
    o = b * sc.num_vertices
    x = positions[o + sc.surface[s]]
    K = sc.candidates
    first = (b * sc.surface.shape[0] + s) * K
    for k in range(K):
        sc.pair[first + k] = -1
    r = float(radius) * 1.0001
    lo = wp.vec3(float(x[0]) - r, float(x[1]) - r, float(x[2]) - r)
    hi = wp.vec3(float(x[0]) + r, float(x[1]) + r, float(x[2]) + r)
    query = wp.mesh_query_aabb(meshes[b], lo, hi)
    f = int(0)  # noqa: UP018 (a Warp variable, not a constant)
    count = int(0)  # noqa: UP018
    while wp.mesh_query_aabb_next(query, f):
        if not is_excluded(sc, s, f):
            ids = sc.faces[f]
            x0 = positions[o + ids[0]]
            x1 = positions[o + ids[1]]
            x2 = positions[o + ids[2]]
            w = closest_point_weights(x, x0, x1, x2)
            r_vec = x - (w[0] * x0 + w[1] * x1 + w[2] * x2)
            d = wp.length(r_vec)
            inside = w[0] > f64(0.0) and w[1] > f64(0.0) and w[2] > f64(0.0)
            # a vertex as deep as the cap behind a triangle is in a wall of the object: not paired with it
            deep = inside and wp.dot(r_vec, face_normal(x0, x1, x2)) < f64(0.0) and d >= sc.depth
            if sc.model == 1:  # "feature": as far behind the triangle or its crease
                deep = d >= sc.depth and feature_behind(sc, positions, o, f, r_vec, w)
            if d < radius and not deep:
                slot = count
                if count < K:
                    count += 1
                else:  # replace the farthest kept candidate if this one is nearer
                    far = int(0)  # noqa: UP018
                    for k in range(1, K):
                        if sc.pair_distance[first + k] > sc.pair_distance[first + far]:
                            far = k
                    slot = -1
                    if d < sc.pair_distance[first + far]:
                        slot = far
                if slot >= 0:
                    sc.pair[first + slot] = f
                    sc.pair_distance[first + slot] = d


@wp.kernel
def self_contact_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += self-contact penalty of trial state p = t B + b of problem b (pairs of problem b)."""
    p, s = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    f, pen, n, w = nearest_penetration(sc, positions, p * sc.num_vertices, b, s)
    if pen > f64(0.0):
        kn = pair_stiffness(sc, kappa, youngs[b], s)
        wp.atomic_add(energy, p, ck.penalty_energy(pen, kn, smoothing * sc.size))


@wp.kernel
def self_contact_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    rows_per_problem: int,
    blocks_per_problem: int,
    active: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    gradient: wp.array(dtype=wp.vec3d),
    hessian: wp.array(dtype=wp.mat33d),
    coupling_rows: wp.array(dtype=wp.int32),
    coupling_cols: wp.array(dtype=wp.int32),
    coupling: wp.array(dtype=wp.mat33d),
):
    """Add the self-contact gradient and the pattern's blocks of its Gauss-Newton Hessian; write the
    (vertex, triangle vertex) blocks -k_g w_i n n^T, outside the pattern, to ``coupling`` (3 per pair slot,
    zero rows and columns of fixed components; the caller zeroes it)."""
    b, s = wp.tid()
    if active[b] == 0:
        return
    slot = b * sc.surface.shape[0] + s
    f, pen, n, w = nearest_penetration(sc, positions, b * sc.num_vertices, b, s)
    if pen <= f64(0.0):
        return
    kn = pair_stiffness(sc, kappa, youngs[b], s)
    delta = smoothing * sc.size
    fn = ck.penalty_force(pen, kn, delta)
    nn = ck.penalty_stiffness(pen, kn, delta) * wp.outer(n, n)
    row = b * rows_per_problem
    ob = b * blocks_per_problem
    wp.atomic_add(gradient, row + sc.surface[s], -fn * n)
    wp.atomic_add(hessian, ob + sc.vertex_block[s], nn)
    ids = sc.faces[f]
    v = sc.surface[s]
    fv = free[v]
    for i in range(3):
        wp.atomic_add(gradient, row + ids[i], (w[i] * fn) * n)
        for j in range(3):
            wp.atomic_add(hessian, ob + sc.face_blocks[f, 3 * i + j], (w[i] * w[j]) * nn)
        fi = free[ids[i]]
        c = -w[i] * nn
        masked = wp.mat33d()
        for a in range(3):
            for k in range(3):
                masked[a, k] = fv[a] * c[a, k] * fi[k]
        coupling_rows[3 * slot + i] = v
        coupling_cols[3 * slot + i] = ids[i]
        coupling[3 * slot + i] = masked


@wp.kernel
def self_contact_force_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    force: wp.array(dtype=wp.vec3d),
    penetration: wp.array(dtype=wp.float64),
):
    """Self-contact force on every vertex (b N + v) and each pair slot's penetration [m]."""
    b, s = wp.tid()
    slot = b * sc.surface.shape[0] + s
    f, pen, n, w = nearest_penetration(sc, positions, b * sc.num_vertices, b, s)
    penetration[slot] = pen
    if pen <= f64(0.0):
        return
    kn = pair_stiffness(sc, kappa, youngs[b], s)
    fn = ck.penalty_force(pen, kn, smoothing * sc.size)
    o = b * sc.num_vertices
    wp.atomic_add(force, o + sc.surface[s], fn * n)
    ids = sc.faces[f]
    for i in range(3):
        wp.atomic_add(force, o + ids[i], (-w[i] * fn) * n)


# ---------------------------------------------------------------- host
def self_contact_depth(mesh) -> float:
    """Depth [m] up to which self-contact holds a surface vertex behind another part of the surface (the
    pairs' depth cap, ``SELF_CONTACT_DEPTH`` h with h the median surface edge): a vertex deeper inside the
    object has passed through it (``TetMesh.surface_vertices_inside(..., depth=)``)."""
    return SELF_CONTACT_DEPTH * mesh.median_surface_edge_length


def adjacent_triangles(faces: np.ndarray) -> np.ndarray:
    """(F, 3): the triangle across the edge opposite corner k of each triangle (the edge's other triangle),
    -1 where the edge has no other triangle or more than one (non-manifold)."""
    F = len(faces)
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.minimum(a, b).astype(np.int64) * (int(faces.max()) + 1) + np.maximum(a, b)
    slot = np.arange(3 * F)  # k F + f: the edge opposite corner k of triangle f
    order = np.argsort(key, kind="stable")
    _, start, count = np.unique(key[order], return_index=True, return_counts=True)
    out = np.full(3 * F, -1, dtype=np.int32)
    pairs = start[count == 2]
    e0, e1 = slot[order[pairs]], slot[order[pairs + 1]]
    out[e0] = e1 % F
    out[e1] = e0 % F
    return out.reshape(3, F).T.copy()


def excluded_triangles(mesh, radius: float, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """CSR (start (S + 1,), sorted triangle indices) of the surface triangles each surface vertex v
    (``mesh.surface_vertices`` order) never pairs with: those incident to v, to its surface 1-ring, or to
    any surface vertex within ``radius`` [m] of v along the rest surface (shortest paths over surface
    edges). Along the surface, not through space: parts of the object that are near at rest but apart on its
    surface (two blocks, a slot's walls) still contact each other."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    faces = mesh.surface_faces
    surface = mesh.surface_vertices
    S = len(surface)
    local = np.searchsorted(surface, faces)  # (F, 3) surface indices
    edges = np.concatenate([local[:, [0, 1]], local[:, [1, 2]], local[:, [2, 0]]])
    x = mesh.points[surface]
    length = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
    graph = coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(S, S)).tocsr()
    order = np.argsort(local.ravel(), kind="stable")
    tri_of = (order // 3).astype(np.int64)  # triangles incident to each surface vertex, in runs
    start = np.searchsorted(local.ravel()[order], np.arange(S + 1))
    rows = []
    for c0 in range(0, S, chunk):
        dist = dijkstra(graph, directed=False, indices=np.arange(c0, min(c0 + chunk, S)), limit=radius)
        for k, s in enumerate(range(c0, min(c0 + chunk, S))):
            ring = local[tri_of[start[s] : start[s + 1]]].ravel()
            verts = np.union1d(ring, np.flatnonzero(np.isfinite(dist[k])))
            rows.append(np.unique(np.concatenate([tri_of[start[u] : start[u + 1]] for u in verts])))
    csr = np.zeros(S + 1, dtype=np.int32)
    csr[1:] = np.cumsum([len(r) for r in rows])
    return csr, (np.concatenate(rows) if rows else np.zeros(1)).astype(np.int32)


class SelfContact:
    """Self-contact of a :class:`QuasiStaticSolver`'s object: the surface data on the device, one BVH per
    problem over the deformed surface, the vertex-triangle pairs, and the launches of the kernels above."""

    def __init__(self, mesh, pattern, batch_size: int, size: float, device, model: str = "prism"):
        if model not in SELF_CONTACT_MODELS:
            raise ValueError(f"self-contact model must be one of {SELF_CONTACT_MODELS}, got {model!r}")
        self.model = model
        self.batch_size = B = int(batch_size)
        self.device = dev = device
        N = mesh.num_vertices
        faces = mesh.surface_faces.astype(np.int32)
        surface = mesh.surface_vertices.astype(np.int32)
        self.num_surface = S = len(surface)
        self.num_faces = F = len(faces)
        self.radius = SELF_CONTACT_RADIUS * size
        self.depth = SELF_CONTACT_DEPTH * size
        pairs = np.arange(9)
        face_blocks = pattern.block_index(faces[:, pairs // 3].ravel(), faces[:, pairs % 3].ravel())
        if np.any(face_blocks < 0):
            raise ValueError("surface triangles must be tet faces (their edges in the block pattern)")
        start, excluded = excluded_triangles(mesh, SELF_CONTACT_EXCLUSION * size)
        sc = SelfContactArrays()
        sc.surface = wp.array(surface, dtype=wp.int32, device=dev)
        sc.faces = wp.array(faces, dtype=wp.vec3i, device=dev)
        sc.face_blocks = wp.array(face_blocks.reshape(F, 9), dtype=wp.int32, device=dev)
        sc.vertex_block = wp.array(pattern.vertex_diag[surface], dtype=wp.int32, device=dev)
        sc.area = wp.array(mesh.vertex_areas[surface], dtype=wp.float64, device=dev)
        sc.excluded_start = wp.array(start, dtype=wp.int32, device=dev)
        sc.excluded = wp.array(excluded, dtype=wp.int32, device=dev)
        sc.adjacent = wp.array(adjacent_triangles(faces), dtype=wp.int32, device=dev)
        sc.candidates = K = SELF_CONTACT_CANDIDATES
        sc.pair = wp.full(B * S * K, -1, dtype=wp.int32, device=dev)
        sc.pair_distance = wp.zeros(B * S * K, dtype=wp.float64, device=dev)
        sc.size = float(size)
        sc.depth = float(self.depth)
        sc.num_vertices = N
        sc.model = SELF_CONTACT_MODELS.index(model)
        self.arrays = sc
        self._points = wp.zeros(B * N, dtype=wp.vec3, device=dev)
        indices = wp.array(faces.ravel(), dtype=wp.int32, device=dev)
        self._meshes = [wp.Mesh(points=self._points[b * N : (b + 1) * N], indices=indices) for b in range(B)]
        self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=dev)
        self._force = wp.zeros(B * N, dtype=wp.vec3d, device=dev)
        #: the (vertex, triangle vertex) Hessian blocks of the last assembly, outside the block pattern
        self.coupling = (
            wp.zeros(3 * B * S, dtype=wp.int32, device=dev),
            wp.zeros(3 * B * S, dtype=wp.int32, device=dev),
            wp.zeros(3 * B * S, dtype=wp.mat33d, device=dev),
        )
        self._penetration = wp.zeros(B * S, dtype=wp.float64, device=dev)

    def update_pairs(self, positions) -> None:
        """Refit the BVHs to ``positions`` (B N, one state per problem) and pair every surface vertex."""
        B, dev, sc = self.batch_size, self.device, self.arrays
        wp.launch(
            surface_points_kernel, dim=B * sc.num_vertices, inputs=[positions, self._points], device=dev
        )
        for m in self._meshes:
            m.refit()
        wp.launch(
            pair_kernel,
            dim=(B, self.num_surface),
            inputs=[positions, self._mesh_ids, float(self.radius), sc],
            device=dev,
        )

    def add_energy(self, positions, states: int, youngs, kappa, smoothing, active, energy) -> None:
        """energy[p] += the penalty of each of the ``states`` packed states (trial-major) with the pairs."""
        wp.launch(
            self_contact_energy_kernel,
            dim=(states, self.num_surface),
            inputs=[positions, self.arrays, youngs, float(kappa), float(smoothing), active, energy],
            device=self.device,
        )

    def add_gradient_hessian(
        self, positions, youngs, kappa, smoothing, rows, blocks, active, free, gradient, hessian
    ):
        """Add the gradient and the pattern's Hessian blocks; the couplings outside it into
        :attr:`coupling` (rows, cols, blocks; see ``BatchedSystem.coupling``)."""
        for a in self.coupling:
            a.zero_()
        wp.launch(
            self_contact_gradient_hessian_kernel,
            dim=(self.batch_size, self.num_surface),
            inputs=[
                positions,
                self.arrays,
                youngs,
                float(kappa),
                float(smoothing),
                rows,
                blocks,
                active,
                free,
            ],
            outputs=[gradient, hessian, *self.coupling],
            device=self.device,
        )

    def _evaluate(self, positions, youngs, kappa, smoothing) -> None:
        """Pairs at ``positions``, then every vertex's self-contact force and penetration (on the device)."""
        self.update_pairs(positions)
        self._force.zero_()
        self._penetration.zero_()
        wp.launch(
            self_contact_force_kernel,
            dim=(self.batch_size, self.num_surface),
            inputs=[positions, self.arrays, youngs, float(kappa), float(smoothing)],
            outputs=[self._force, self._penetration],
            device=self.device,
        )

    def penetration(self, positions, youngs, kappa, smoothing) -> np.ndarray:
        """(B, S) penetration of each surface vertex behind its paired triangle [m] (0: none), at
        ``positions`` with freshly found pairs (the forces stay on the device)."""
        self._evaluate(positions, youngs, kappa, smoothing)
        return self._penetration.numpy().reshape(self.batch_size, self.num_surface).copy()

    def forces(self, positions, youngs, kappa, smoothing) -> tuple[np.ndarray, np.ndarray]:
        """(B, N, 3) self-contact force on every vertex [N] and (B, S) penetration of each surface vertex
        behind its paired triangle [m] (0: none), at ``positions`` with freshly found pairs."""
        self._evaluate(positions, youngs, kappa, smoothing)
        B = self.batch_size
        return (
            self._force.numpy().reshape(B, -1, 3).copy(),
            self._penetration.numpy().reshape(B, self.num_surface).copy(),
        )
