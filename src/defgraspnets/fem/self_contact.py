"""Self-contact of the object's surface (Warp kernels), ``SolverOptions.self_contact``; with the "barrier"
model optionally frictional (``SolverOptions.self_contact_friction``).

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

Model "barrier" (IPC: Li et al., "Incremental Potential Contact", SIGGRAPH 2020) sums a log barrier over
every candidate pair, with unsigned distances between closed primitives (no side, no prism, no depth):

    E_s = sum_(v, f) k_v b(d(x_v, f)) + sum_(e, g) k_eg b(d(e, g)),
    b(d) = -(d - d^)^2 log(d / d^) for 0 < d < d^, 0 beyond, +inf at d <= 0,

over the vertex-triangle pairs (v, f) (d the distance to the closed triangle: a continuous function of the
four points, its gradient the closest point's, as above with n = (x_v - c) / d) and the edge-edge pairs
(e, g) of the surface's edges (d between the segments' closest points, weights (1 - s, s, -(1 - t), -t)),
with d^ = ``SELF_CONTACT_GAP`` h, k_v as above and k_eg = s kappa E (l_e l_g / 8) / h (rest lengths: in
face-to-face contact the crossing edge pairs per unit area then carry about the vertex pairs' stiffness).
Every term is continuous, so the energy is (no candidate switches the acting triangle: all act), and it
is infinite where two parts touch. Near d^ the barrier rises as k (d^ - d)^3 / d^ (C2 at d^): with kappa =
1000 the parts rest a hair inside d^ (a pressure p closes (d^ - d) ~ h sqrt(p d^ / (3 kappa E h))), so
they meet d^ early, 0.05 h (the rigid contact's tolerance is ~1e-2 h the other way). The line search
never steps a pair through zero distance (where the energy would be finite again: tunnelling): each
Newton step is cut to the length at which no candidate pair's distance can have closed by more than
``SELF_CONTACT_STEP_FRACTION`` of itself (a pair's distance closes by at most max |dx_a - dx_b| over its
vertices per unit step, translation-invariant, as in additive CCD), nor any other pair, which lies beyond
the vertex's (edge's) clear radius (all nearer ones are candidates), by more than that fraction of it
(:meth:`SelfContact.step_bound`); the predictor's extrapolation is checked the same way
(``QuasiStaticSolver._start_increment``). Edge pairs closer to parallel than |e x g|^2 < eps l_e^2 l_g^2
(eps = ``SELF_CONTACT_PARALLEL``) are faded out by IPC's mollifier m = x (2 - x), x = |e x g|^2 / (eps
l_e^2 l_g^2) (their closest points jump along the edges; the vertex pairs of their ends hold them): the
energy is m k b(d), its gradient exact (m's too). Hessian per pair: c c^T (x) (k b'' n n^T + (f / d) P)
with c the pair's coefficients and P the directions in which the distance to the closest feature curves
(none for a face or two crossing edges, those normal to n and to the edge for an edge, all normal to n for
a point: exact for two points, the closest point's weights held otherwise; the mollifier's second
derivatives left out); PSD. That Hessian still jumps where a closest point moves between a face, an edge
and a corner, and full Newton steps can overshoot back and forth across such a boundary: with this model
the line search shortens an accepted full step to the minimum of the parabola through the energy, its slope
and the full step's energy where that lies below 0.8 of the step (``QuasiStaticSolver._refine_full_steps``).
Not IPC: no adaptive barrier stiffness (kappa is the rigid contact's), and duplicate pairs (a
vertex near an edge has both triangles' pairs, and the edge pairs through it) are summed, not merged: two
vertices meeting bring every pair of their fans' triangles and edges. Pair arrays:
``SELF_CONTACT_BARRIER_CANDIDATES`` per vertex and ``SELF_CONTACT_EDGE_CANDIDATES`` per edge (each edge pair
once, from its lower edge), their couplings 3 per vertex slot and 4 per edge slot. A list that overflows
within d^ leaves out acting pairs, and which ones can change between Newton iterations (with 4 edge slots
the ring's grasp 24 cycled on this: measured). The lists are kept from one pairing to the next (Verlet
lists) while every vertex's and edge's clear radius, less the surface's drift since their build, stays at or
above ``SELF_CONTACT_KEPT_CLEAR`` of its value at the build and above d^ (distances are 1-Lipschitz in the
moves: no left-out pair can act, and the reduced radius serves the step bound); the ring's ramps rebuild at
6-9 % of their pairings, which halved their CPU time (``benchmarks/fem_self_contact_kept_pairs_s51.md``).
Measured on the thin ring (``benchmarks/fem_self_contact_barrier_s50.md``): the squeeze ramps that the
prism model fails reach 15 N, with no surface vertex inside; refuses a surface within d^ of itself at rest
(away from the excluded neighbourhoods).

Friction (model "barrier", ``SolverOptions.self_contact_friction`` = mu > 0; IPC's lagged friction, with the
quasi-static slip in place of IPC's velocity times the time step). At the start of each load increment every
barrier pair closer than d^ becomes a friction pair, with its normal force lambda (the barrier's force,
mollified for edge pairs), unit normal n and closest points (weights w, parameters (s, t)) frozen, and the
positions X there as the reference. Its potential is

    D = mu lambda F(|(I - n n^T) u|),   u = sum_i c_i (x_i - X_i),
    F(y) = y^2 / eps - y^3 / (3 eps^2) for y < eps,   y - eps / 3 beyond,

with c the pair's coefficients (as the barrier's: (1, -w) or (1 - s, s, -(1 - t), -t)) and eps =
``SELF_CONTACT_FRICTION_SLIP`` h the stick zone: the friction force mu lambda F'(y) along the slip rises from
0 to Coulomb's mu lambda over eps, and is mu lambda beyond (sliding). Gradient exact; Hessian exact and PSD (c
c^T (x) mu lambda (F''(y) t t^T / y^2 + F'(y) / y (P - t t^T / y^2)) with P = I - n n^T, t = P u), its
couplings after the barrier's (4 per friction slot). The normal forces are re-lagged from the iterate (the
slips' reference kept) where the rigid contact's are (``_relag_friction``: the first
``friction_relag_iterations`` Newton iterations of an increment), and a converged state is accepted only once
its lagged forces are its own: every pair's capacity error mu (|lambda - lambda_lag| + lambda |n - n_lag|)
below the residual tolerance, or their sum below ``friction_rtol`` of the capacity
(``friction_lag_error_kernel``, with the rigid contact's check); else it is
re-lagged and Newton goes on (up to ``max_friction_relags``). Measured (tests): a cube pressed onto a slab
of one mesh and pushed sideways sticks (the lateral force grows with the push) and then slides at mu F_z
within 1.00-1.07 (the slab's dent under the leading edge tilts normals); the re-lags to consistency cost
Newton iterations (the cube's sideways moves to 2, 4, 5, 6 mm: 33, 174, 132, 390 against 17, 27, 28, 117
without the check). With the re-lags of the first iterations alone (no consistency check) the lagged normal
forces summed to 0.269 N against the converged state's 0.163 N (taken from a transient early iterate) and
the sliding force overshot mu F_z by 8 %. Pairs are matched by their features, not their list slots: a
batch re-pairs its other problems at every increment start, and a rebuilt list holds the same pairs in
another order. The thin ring (``benchmarks/fem_self_contact_friction_s52.md``, 2-core CPU, mu 0.5): its four
50-step ramps reach 15 N as without friction, at 17-27 % more time per Newton iteration; the 16-grasp data
path solves 14 of 16 (frictionless 13) in 405 s (312 s).

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
#: the neighbours across the edges that closest point lies on (continuous across triangle boundaries);
#: "barrier", a log barrier on the unsigned distances of every near vertex-triangle and edge-edge pair (no
#: penetration: the line search never lets a pair's distance reach zero)
SELF_CONTACT_MODELS = ("prism", "feature", "barrier")
#: model "barrier": the distance below which a pair's barrier acts (its activation distance), in units of h
SELF_CONTACT_GAP = 0.05
#: model "barrier": candidate triangles kept per surface vertex (every one within the activation distance
#: acts: a vertex against another one's fan, 6-10 triangles at one distance, fits)
SELF_CONTACT_BARRIER_CANDIDATES = 16
#: model "barrier": candidate edges kept per surface edge (edge-edge pairs; an edge against a vertex's fan of
#: edges fits)
SELF_CONTACT_EDGE_CANDIDATES = 8
#: model "barrier": edge pairs closer to parallel than |e x g|^2 < this l_e^2 l_g^2 (rest lengths) are faded
#: out by IPC's mollifier (their closest points jump along the edges; their ends' vertex pairs hold them)
SELF_CONTACT_PARALLEL = 1e-3
#: model "barrier": a line-search step may close at most this fraction of any pair's distance
SELF_CONTACT_STEP_FRACTION = 0.9
#: model "barrier": a problem's pair lists are kept from one pairing to the next (Verlet lists) while every
#: surface vertex's and edge's clear radius, less what the surface moved since the lists were built, stays
#: at or above this fraction of its value at the build, and at or above d^ (so every acting pair is listed);
#: they are rebuilt from the BVH otherwise
SELF_CONTACT_KEPT_CLEAR = 0.5
#: model "barrier" with friction (``SolverOptions.self_contact_friction`` > 0): the tangential slip over which
#: a pair's friction force rises to Coulomb's mu lambda (the stick zone; IPC's eps_v dt), in units of h
SELF_CONTACT_FRICTION_SLIP = 1e-2


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
    model: int  # 0: "prism", 1: "feature", 2: "barrier"
    # model "barrier" (the edge arrays are built for every model; the pair arrays hold one entry otherwise)
    gap: f64  # activation distance d^ [m]
    clear: wp.array(
        dtype=wp.float64
    )  # (B S,) distance within which every triangle of vertex s is a candidate
    edges: wp.array(dtype=wp.vec2i)  # (E,) surface edges' endpoints (surface indices)
    edge_length: wp.array(dtype=wp.float64)  # (E,) rest lengths [m]
    edge_blocks: wp.array2d(dtype=wp.int32)  # (E, 4) BSR blocks (a_i, a_j) of one problem at 2 i + j
    face_edges: wp.array2d(dtype=wp.int32)  # (F, 3) edge opposite corner k of each triangle
    edge_owner: wp.array(dtype=wp.int32)  # (E,) the first triangle of each edge
    edge_pair: wp.array(dtype=wp.int32)  # (B E KE,) candidate edges of each surface edge (of higher index)
    edge_pair_distance: wp.array(dtype=wp.float64)  # (B E KE,) their distances at the pairing
    edge_clear: wp.array(dtype=wp.float64)  # (B E,) as ``clear``, for the edges
    edge_candidates: int  # KE
    parallel: f64  # SELF_CONTACT_PARALLEL


@wp.struct
class PairLists:
    """Model "barrier": the state of each problem's pair lists at their last build (Verlet lists)."""

    points: wp.array(dtype=wp.vec3d)  # (B S,) surface positions at the build [m]
    clear: wp.array(dtype=wp.float64)  # (B S,) vertices' clear radii at the build [m]
    edge_clear: wp.array(dtype=wp.float64)  # (B E,) edges' clear radii at the build [m]
    drift: wp.array(dtype=wp.float64)  # (B S,) how far each vertex moved since [m]
    max_drift: wp.array(dtype=wp.float64)  # (B,) the largest drift of the problem [m]
    rebuild: wp.array(dtype=wp.int32)  # (B,) 1: build the problem's lists at this pairing


@wp.struct
class FrictionPairs:
    """Model "barrier" with friction: each problem's friction pairs, lagged at the start of its load increment
    (IPC's lagged friction): the barrier pairs active there (slots numbered as in :func:`barrier_pair`), with
    their normal force, normal and coefficients, and the positions they slip from."""

    reference: wp.array(dtype=wp.vec3d)  # (B N,) positions at the lag [m]
    other: wp.array(dtype=wp.int32)  # (B P,) the pair's triangle or other edge, -1: no friction pair
    coefficients: wp.array(dtype=wp.vec4d)  # (B P,) c of its four points (closest points' weights)
    normal: wp.array(dtype=wp.vec3d)  # (B P,) unit normal, from the second group to the first
    force: wp.array(dtype=wp.float64)  # (B P,) normal force lambda [N]
    slots: int  # P = S K + E KE
    mu: f64  # friction coefficient
    slip: f64  # stick zone eps [m]


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


# ---------------------------------------------------------------- model "barrier"
@wp.func
def barrier_energy(d: f64, kn: f64, gap: f64) -> f64:
    """k b(d) with b(d) = -(d - d^)^2 log(d / d^) for 0 < d < d^ (IPC's barrier, C2 at d^), 0 beyond, +inf
    at d <= 0."""
    if d <= f64(0.0):
        return f64(wp.inf)
    if d >= gap:
        return f64(0.0)
    e = d - gap
    return -kn * e * e * wp.log(d / gap)


@wp.func
def barrier_force(d: f64, kn: f64, gap: f64) -> f64:
    """-k b'(d) >= 0 [N]: the pair's repulsion."""
    if d <= f64(0.0) or d >= gap:
        return f64(0.0)
    e = d - gap
    return kn * (f64(2.0) * e * wp.log(d / gap) + e * e / d)


@wp.func
def barrier_stiffness(d: f64, kn: f64, gap: f64) -> f64:
    """k b''(d) >= 0 [N/m]."""
    if d <= f64(0.0) or d >= gap:
        return f64(0.0)
    e = d - gap
    return kn * (-f64(2.0) * wp.log(d / gap) - f64(4.0) * e / d + e * e / (d * d))


@wp.func
def segment_closest_parameters(a0: wp.vec3d, a1: wp.vec3d, b0: wp.vec3d, b1: wp.vec3d) -> wp.vec2d:
    """Parameters (s, t) in [0, 1]^2 of the closest points a0 + s (a1 - a0), b0 + t (b1 - b0) of two
    segments (Ericson 5.1.9; parallel segments: one of the closest pairs)."""
    zero = f64(0.0)
    one = f64(1.0)
    d1 = a1 - a0
    d2 = b1 - b0
    r = a0 - b0
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    c = wp.dot(d1, r)
    b = wp.dot(d1, d2)
    denom = a * e - b * b
    s = zero
    if denom > f64(1e-12) * a * e:
        s = wp.clamp((b * f - c * e) / denom, zero, one)
    t = (b * s + f) / e
    if t < zero:
        t = zero
        s = wp.clamp(-c / a, zero, one)
    elif t > one:
        t = one
        s = wp.clamp((b - c) / a, zero, one)
    return wp.vec2d(s, t)


@wp.func
def vertex_triangle_distance(
    sc: SelfContactArrays, positions: wp.array(dtype=wp.vec3d), o: int, s: int, f: int
):
    """Distance of surface vertex s from the closed triangle f (state at offset o), r = x_v - c (c its
    closest point) and c's barycentric weights w."""
    ids = sc.faces[f]
    x = positions[o + sc.surface[s]]
    x0 = positions[o + ids[0]]
    x1 = positions[o + ids[1]]
    x2 = positions[o + ids[2]]
    w = closest_point_weights(x, x0, x1, x2)
    r = x - (w[0] * x0 + w[1] * x1 + w[2] * x2)
    return wp.length(r), r, w


@wp.func
def edge_edge_distance(sc: SelfContactArrays, positions: wp.array(dtype=wp.vec3d), o: int, e: int, g: int):
    """Distance of surface edges e and g (state at offset o), r = p - q between their closest points
    p = a0 + s (a1 - a0) on e and q = b0 + t (b1 - b0) on g, and (s, t)."""
    ea = sc.edges[e]
    eb = sc.edges[g]
    a0 = positions[o + sc.surface[ea[0]]]
    a1 = positions[o + sc.surface[ea[1]]]
    b0 = positions[o + sc.surface[eb[0]]]
    b1 = positions[o + sc.surface[eb[1]]]
    st = segment_closest_parameters(a0, a1, b0, b1)
    r = (a0 + st[0] * (a1 - a0)) - (b0 + st[1] * (b1 - b0))
    return wp.length(r), r, st


@wp.func
def edge_pair_stiffness(sc: SelfContactArrays, kappa: f64, youngs: f64, e: int, g: int) -> f64:
    """k_eg = kappa E (l_e l_g / 8) / h of an edge-edge pair (rest lengths): in face-to-face contact the
    edge pairs crossing per unit area then carry about the vertex pairs' stiffness."""
    area = sc.edge_length[e] * sc.edge_length[g] / f64(8.0)
    return ck.contact_stiffness(kappa, youngs, area, sc.size)


@wp.func
def edge_mollifier(sc: SelfContactArrays, positions: wp.array(dtype=wp.vec3d), o: int, e: int, g: int):
    """IPC's mollifier of edge pair (e, g): m = x (2 - x) with x = |a x b|^2 / (eps l_e^2 l_g^2) below 1,
    else 1 (a, b the edges' vectors, l their rest lengths, eps ``SELF_CONTACT_PARALLEL``), and its
    gradients with respect to a and b (the ends: -/+ them)."""
    ea = sc.edges[e]
    eb = sc.edges[g]
    a = positions[o + sc.surface[ea[1]]] - positions[o + sc.surface[ea[0]]]
    b = positions[o + sc.surface[eb[1]]] - positions[o + sc.surface[eb[0]]]
    la = sc.edge_length[e]
    lb = sc.edge_length[g]
    threshold = sc.parallel * la * la * lb * lb
    c = wp.length_sq(wp.cross(a, b))
    if c >= threshold:
        return f64(1.0), wp.vec3d(), wp.vec3d()
    x = c / threshold
    slope = f64(2.0) * (f64(1.0) - x) / threshold  # dm/dc
    ab = wp.dot(a, b)
    dm_da = (slope * f64(2.0)) * (wp.dot(b, b) * a - ab * b)
    dm_db = (slope * f64(2.0)) * (wp.dot(a, a) * b - ab * a)
    return x * (f64(2.0) - x), dm_da, dm_db


@wp.func
def keep_nearest(
    pair: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.float64),
    first: int,
    K: int,
    count: int,
    f: int,
    d: f64,
    dropped: f64,
):
    """Offer candidate f at distance d to the K-slot list at ``first`` holding ``count``: kept if a slot is
    free or it is nearer than the farthest kept (which it replaces). Returns the new count and the least
    distance of any candidate not kept (``dropped``, updated)."""
    slot = count
    n = count
    least = dropped
    if count < K:
        n = count + 1
    else:
        far = int(0)  # noqa: UP018
        for k in range(1, K):
            if distance[first + k] > distance[first + far]:
                far = k
        slot = -1
        if d < distance[first + far]:
            slot = far
            least = wp.min(least, distance[first + far])
        else:
            least = wp.min(least, d)
    if slot >= 0:
        pair[first + slot] = f
        distance[first + slot] = d
    return n, least


@wp.func
def kept_vertex_clear(sc: SelfContactArrays, lists: PairLists, b: int, s: int) -> f64:
    """Surface vertex s's clear radius at its problem's list build, less its drift and the problem's
    largest drift since: no left-out triangle is nearer (distances are 1-Lipschitz in the moves)."""
    i = b * sc.surface.shape[0] + s
    return lists.clear[i] - lists.drift[i] - lists.max_drift[b]


@wp.func
def kept_edge_clear(sc: SelfContactArrays, lists: PairLists, b: int, e: int) -> f64:
    """As :func:`kept_vertex_clear` for surface edge e (the larger drift of its ends)."""
    S = sc.surface.shape[0]
    ends = sc.edges[e]
    drift = wp.max(lists.drift[b * S + ends[0]], lists.drift[b * S + ends[1]])
    return lists.edge_clear[b * sc.edges.shape[0] + e] - drift - lists.max_drift[b]


@wp.kernel
def barrier_pair_kernel(
    positions: wp.array(dtype=wp.vec3d),
    meshes: wp.array(dtype=wp.uint64),
    radius: f64,
    sc: SelfContactArrays,
    lists: PairLists,
):
    """The K nearest non-excluded triangles within ``radius`` of each surface vertex (unsigned distances,
    no depth cap) and the vertex's clear radius: every triangle nearer than it is a candidate. In a problem
    whose lists are kept (``lists.rebuild[b]`` 0) only the clear radius is updated: the one at the pairing
    less the vertex's drift and the problem's largest drift since (distances are 1-Lipschitz in the moves)."""
    b, s = wp.tid()
    i = b * sc.surface.shape[0] + s
    if lists.rebuild[b] == 0:
        sc.clear[i] = kept_vertex_clear(sc, lists, b, s)
        return
    x = positions[b * sc.num_vertices + sc.surface[s]]
    lists.points[i] = x
    K = sc.candidates
    first = i * K
    for k in range(K):
        sc.pair[first + k] = -1
    r = float(radius) * 1.0001
    lo = wp.vec3(float(x[0]) - r, float(x[1]) - r, float(x[2]) - r)
    hi = wp.vec3(float(x[0]) + r, float(x[1]) + r, float(x[2]) + r)
    query = wp.mesh_query_aabb(meshes[b], lo, hi)
    f = int(0)  # noqa: UP018
    count = int(0)  # noqa: UP018
    dropped = radius
    while wp.mesh_query_aabb_next(query, f):
        if not is_excluded(sc, s, f):
            d, rv, w = vertex_triangle_distance(sc, positions, b * sc.num_vertices, s, f)
            if d < radius:
                count, dropped = keep_nearest(sc.pair, sc.pair_distance, first, K, count, f, d, dropped)
    sc.clear[i] = dropped
    lists.clear[i] = dropped


@wp.kernel
def edge_pair_kernel(
    positions: wp.array(dtype=wp.vec3d),
    meshes: wp.array(dtype=wp.uint64),
    radius: f64,
    sc: SelfContactArrays,
    lists: PairLists,
):
    """The KE nearest surface edges within ``radius`` of each surface edge e, of higher index than e (each
    pair once), not on a triangle excluded for either end of e; and e's clear radius (kept lists: as in
    :func:`barrier_pair_kernel`, less the larger drift of e's ends)."""
    b, e = wp.tid()
    o = b * sc.num_vertices
    ends = sc.edges[e]
    E = sc.edges.shape[0]
    if lists.rebuild[b] == 0:
        sc.edge_clear[b * E + e] = kept_edge_clear(sc, lists, b, e)
        return
    xa = positions[o + sc.surface[ends[0]]]
    xb = positions[o + sc.surface[ends[1]]]
    K = sc.edge_candidates
    first = (b * E + e) * K
    for k in range(K):
        sc.edge_pair[first + k] = -1
    r = float(radius) * 1.0001
    lo = wp.vec3(
        float(wp.min(xa[0], xb[0])) - r, float(wp.min(xa[1], xb[1])) - r, float(wp.min(xa[2], xb[2])) - r
    )
    hi = wp.vec3(
        float(wp.max(xa[0], xb[0])) + r, float(wp.max(xa[1], xb[1])) + r, float(wp.max(xa[2], xb[2])) + r
    )
    query = wp.mesh_query_aabb(meshes[b], lo, hi)
    f = int(0)  # noqa: UP018
    count = int(0)  # noqa: UP018
    dropped = radius
    while wp.mesh_query_aabb_next(query, f):
        if not is_excluded(sc, ends[0], f) and not is_excluded(sc, ends[1], f):
            for k in range(3):
                g = sc.face_edges[f, k]
                if g > e and sc.edge_owner[g] == f:  # each edge once: through its first triangle
                    d, rv, st = edge_edge_distance(sc, positions, o, e, g)
                    if d < radius:
                        count, dropped = keep_nearest(
                            sc.edge_pair, sc.edge_pair_distance, first, K, count, g, d, dropped
                        )
    sc.edge_clear[b * E + e] = dropped
    lists.edge_clear[b * E + e] = dropped


@wp.kernel
def pair_list_drift_kernel(positions: wp.array(dtype=wp.vec3d), sc: SelfContactArrays, lists: PairLists):
    """How far each surface vertex moved since its problem's lists were built, and the problem's largest."""
    b, s = wp.tid()
    i = b * sc.surface.shape[0] + s
    d = wp.length(positions[b * sc.num_vertices + sc.surface[s]] - lists.points[i])
    lists.drift[i] = d
    wp.atomic_max(lists.max_drift, b, d)


@wp.kernel
def stale_vertex_lists_kernel(sc: SelfContactArrays, lists: PairLists, kept: f64):
    """Mark problem b's lists for a rebuild where a vertex's clear radius, less the drift, fell below
    ``kept`` of its value at the build or below d^."""
    b, s = wp.tid()
    c = lists.clear[b * sc.surface.shape[0] + s]
    if kept_vertex_clear(sc, lists, b, s) < wp.max(kept * c, sc.gap):
        lists.rebuild[b] = 1


@wp.kernel
def stale_edge_lists_kernel(sc: SelfContactArrays, lists: PairLists, kept: f64):
    """As :func:`stale_vertex_lists_kernel` for the edges (the larger drift of an edge's ends)."""
    b, e = wp.tid()
    c = lists.edge_clear[b * sc.edges.shape[0] + e]
    if kept_edge_clear(sc, lists, b, e) < wp.max(kept * c, sc.gap):
        lists.rebuild[b] = 1


@wp.kernel
def barrier_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += the barrier of every vertex-triangle pair of surface vertex s in trial state p."""
    p, s = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    K = sc.candidates
    first = (b * sc.surface.shape[0] + s) * K
    kn = pair_stiffness(sc, kappa, youngs[b], s)
    total = f64(0.0)
    for k in range(K):
        f = sc.pair[first + k]
        if f >= 0:
            d, r, w = vertex_triangle_distance(sc, positions, p * sc.num_vertices, s, f)
            total += barrier_energy(d, kn, sc.gap)
    if total > f64(0.0):
        wp.atomic_add(energy, p, total)


@wp.kernel
def edge_barrier_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += the barrier of every edge-edge pair of surface edge e in trial state p."""
    p, e = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    K = sc.edge_candidates
    first = (b * sc.edges.shape[0] + e) * K
    total = f64(0.0)
    for k in range(K):
        g = sc.edge_pair[first + k]
        if g >= 0:
            d, r, st = edge_edge_distance(sc, positions, p * sc.num_vertices, e, g)
            energy_g = barrier_energy(d, edge_pair_stiffness(sc, kappa, youngs[b], e, g), sc.gap)
            if d <= f64(0.0):
                total += energy_g  # +inf, even for parallel edges
            elif energy_g > f64(0.0):
                m, dm_da, dm_db = edge_mollifier(sc, positions, p * sc.num_vertices, e, g)
                total += m * energy_g
    if total > f64(0.0):
        wp.atomic_add(energy, p, total)


@wp.func
def masked_block(c: wp.mat33d, free_a: wp.vec3d, free_b: wp.vec3d) -> wp.mat33d:
    """Block c with the rows of a's and the columns of b's fixed components zeroed."""
    m = wp.mat33d()
    for i in range(3):
        for j in range(3):
            m[i, j] = free_a[i] * c[i, j] * free_b[j]
    return m


@wp.func
def curvature_projector(n: wp.vec3d, t: wp.vec3d, feature: int) -> wp.mat33d:
    """Directions in which the distance to the closest feature curves, per unit 1 / d: none for a face
    (feature 2), those normal to n and to the edge direction t for an edge (1), all normal to n for a point
    (0)."""
    identity = wp.identity(n=3, dtype=f64)
    if feature == 2:
        return wp.mat33d()
    if feature == 1:
        return identity - wp.outer(n, n) - wp.outer(t, t)
    return identity - wp.outer(n, n)


@wp.func
def pair_hessian(d: f64, n: wp.vec3d, fn: f64, kg: f64, t: wp.vec3d, feature: int) -> wp.mat33d:
    """The 3 x 3 factor M of a pair's Hessian c c^T (x) M (c its coefficients): k b'' n n^T along the normal
    and the distance's own curvature, f_n / d times :func:`curvature_projector` (exact for two points; for a
    point and an edge with the edge's direction held), both PSD."""
    return kg * wp.outer(n, n) + (fn / d) * curvature_projector(n, t, feature)


@wp.kernel
def barrier_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    rows_per_problem: int,
    blocks_per_problem: int,
    couplings_per_problem: int,
    active: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    gradient: wp.array(dtype=wp.vec3d),
    hessian: wp.array(dtype=wp.mat33d),
    coupling_rows: wp.array(dtype=wp.int32),
    coupling_cols: wp.array(dtype=wp.int32),
    coupling: wp.array(dtype=wp.mat33d),
):
    """Gradient and Gauss-Newton Hessian k b''(d) J^T J of every active vertex-triangle pair of surface
    vertex s, J = (n, -w_0 n, -w_1 n, -w_2 n), n = (x_v - c) / d; the (vertex, corner) blocks to the
    couplings (3 per candidate slot)."""
    b, s = wp.tid()
    if active[b] == 0:
        return
    K = sc.candidates
    S = sc.surface.shape[0]
    first = (b * S + s) * K
    o = b * sc.num_vertices
    kn = pair_stiffness(sc, kappa, youngs[b], s)
    row = b * rows_per_problem
    ob = b * blocks_per_problem
    v = sc.surface[s]
    fv = free[v]
    for k in range(K):
        f = sc.pair[first + k]
        if f >= 0:
            d, r, w = vertex_triangle_distance(sc, positions, o, s, f)
            if d > f64(0.0) and d < sc.gap:
                n = r / d
                fn = barrier_force(d, kn, sc.gap)
                ids = sc.faces[f]
                # the closest feature: the face (no weight 0), an edge (one: t along it) or a corner (two)
                feature = int(0)  # noqa: UP018
                t = wp.vec3d()
                for i in range(3):
                    if w[i] > f64(0.0):
                        feature += 1
                    elif w[(i + 1) % 3] > f64(0.0) and w[(i + 2) % 3] > f64(0.0):
                        t = wp.normalize(positions[o + ids[(i + 2) % 3]] - positions[o + ids[(i + 1) % 3]])
                nn = pair_hessian(d, n, fn, barrier_stiffness(d, kn, sc.gap), t, feature - 1)
                wp.atomic_add(gradient, row + v, -fn * n)
                wp.atomic_add(hessian, ob + sc.vertex_block[s], nn)
                slot = b * couplings_per_problem + 3 * (s * K + k)
                for i in range(3):
                    wp.atomic_add(gradient, row + ids[i], (w[i] * fn) * n)
                    for j in range(3):
                        wp.atomic_add(hessian, ob + sc.face_blocks[f, 3 * i + j], (w[i] * w[j]) * nn)
                    coupling_rows[slot + i] = v
                    coupling_cols[slot + i] = ids[i]
                    coupling[slot + i] = masked_block(-w[i] * nn, fv, free[ids[i]])


@wp.kernel
def edge_barrier_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    rows_per_problem: int,
    blocks_per_problem: int,
    couplings_per_problem: int,
    active: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    gradient: wp.array(dtype=wp.vec3d),
    hessian: wp.array(dtype=wp.mat33d),
    coupling_rows: wp.array(dtype=wp.int32),
    coupling_cols: wp.array(dtype=wp.int32),
    coupling: wp.array(dtype=wp.mat33d),
):
    """Gradient and Gauss-Newton Hessian of every active edge-edge pair (e, g) of surface edge e:
    J = (1 - s, s, -(1 - t), -t) (x) n with n = (p - q) / d; the (e's end, g's end) blocks to the couplings
    (4 per candidate slot, after the vertex pairs' 3 S K)."""
    b, e = wp.tid()
    if active[b] == 0:
        return
    K = sc.edge_candidates
    E = sc.edges.shape[0]
    S = sc.surface.shape[0]
    first = (b * E + e) * K
    o = b * sc.num_vertices
    row = b * rows_per_problem
    ob = b * blocks_per_problem
    ea = sc.edges[e]
    for k in range(K):
        g = sc.edge_pair[first + k]
        if g >= 0:
            d, r, st = edge_edge_distance(sc, positions, o, e, g)
            if d > f64(0.0) and d < sc.gap:
                kn = edge_pair_stiffness(sc, kappa, youngs[b], e, g)
                n = r / d
                m, dm_da, dm_db = edge_mollifier(sc, positions, o, e, g)
                fn = m * barrier_force(d, kn, sc.gap)
                energy_g = barrier_energy(d, kn, sc.gap)
                eb = sc.edges[g]
                # the mollifier's gradient: d(m E_g) = m dE_g + E_g dm (its Hessian terms are left out)
                wp.atomic_add(gradient, row + sc.surface[ea[1]], energy_g * dm_da)
                wp.atomic_add(gradient, row + sc.surface[ea[0]], -energy_g * dm_da)
                wp.atomic_add(gradient, row + sc.surface[eb[1]], energy_g * dm_db)
                wp.atomic_add(gradient, row + sc.surface[eb[0]], -energy_g * dm_db)
                # closest points: two interior ones (crossing lines: no curvature held), an end against the
                # other edge's interior (t along that edge) or two ends
                a_end = st[0] <= f64(0.0) or st[0] >= f64(1.0)
                b_end = st[1] <= f64(0.0) or st[1] >= f64(1.0)
                feature = int(2)  # noqa: UP018
                t = wp.vec3d()
                if a_end and b_end:
                    feature = 0
                elif a_end:
                    feature = 1
                    t = wp.normalize(positions[o + sc.surface[eb[1]]] - positions[o + sc.surface[eb[0]]])
                elif b_end:
                    feature = 1
                    t = wp.normalize(positions[o + sc.surface[ea[1]]] - positions[o + sc.surface[ea[0]]])
                nn = pair_hessian(d, n, fn, m * barrier_stiffness(d, kn, sc.gap), t, feature)
                ca = wp.vec2d(f64(1.0) - st[0], st[0])
                cb = wp.vec2d(-(f64(1.0) - st[1]), -st[1])
                slot = b * couplings_per_problem + 3 * S * sc.candidates + 4 * (e * K + k)
                for i in range(2):
                    va = sc.surface[ea[i]]
                    vb = sc.surface[eb[i]]
                    wp.atomic_add(gradient, row + va, (-fn * ca[i]) * n)
                    wp.atomic_add(gradient, row + vb, (-fn * cb[i]) * n)
                    for j in range(2):
                        wp.atomic_add(hessian, ob + sc.edge_blocks[e, 2 * i + j], (ca[i] * ca[j]) * nn)
                        wp.atomic_add(hessian, ob + sc.edge_blocks[g, 2 * i + j], (cb[i] * cb[j]) * nn)
                        wj = sc.surface[eb[j]]
                        coupling_rows[slot + 2 * i + j] = va
                        coupling_cols[slot + 2 * i + j] = wj
                        coupling[slot + 2 * i + j] = masked_block((ca[i] * cb[j]) * nn, free[va], free[wj])


@wp.kernel
def barrier_force_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    force: wp.array(dtype=wp.vec3d),
):
    """Barrier force of the vertex-triangle pairs of surface vertex s on every vertex (b N + v)."""
    b, s = wp.tid()
    K = sc.candidates
    first = (b * sc.surface.shape[0] + s) * K
    o = b * sc.num_vertices
    kn = pair_stiffness(sc, kappa, youngs[b], s)
    for k in range(K):
        f = sc.pair[first + k]
        if f >= 0:
            d, r, w = vertex_triangle_distance(sc, positions, o, s, f)
            if d > f64(0.0) and d < sc.gap:
                fn = barrier_force(d, kn, sc.gap) / d
                wp.atomic_add(force, o + sc.surface[s], fn * r)
                ids = sc.faces[f]
                for i in range(3):
                    wp.atomic_add(force, o + ids[i], (-w[i] * fn) * r)


@wp.kernel
def edge_barrier_force_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    force: wp.array(dtype=wp.vec3d),
):
    """Barrier force of the edge-edge pairs of surface edge e on every vertex (b N + v)."""
    b, e = wp.tid()
    K = sc.edge_candidates
    first = (b * sc.edges.shape[0] + e) * K
    o = b * sc.num_vertices
    ea = sc.edges[e]
    for k in range(K):
        g = sc.edge_pair[first + k]
        if g >= 0:
            d, r, st = edge_edge_distance(sc, positions, o, e, g)
            if d > f64(0.0) and d < sc.gap:
                kn = edge_pair_stiffness(sc, kappa, youngs[b], e, g)
                m, dm_da, dm_db = edge_mollifier(sc, positions, o, e, g)
                fn = m * barrier_force(d, kn, sc.gap) / d
                energy_g = barrier_energy(d, kn, sc.gap)
                eb = sc.edges[g]
                wp.atomic_add(force, o + sc.surface[ea[1]], -energy_g * dm_da)
                wp.atomic_add(force, o + sc.surface[ea[0]], energy_g * dm_da)
                wp.atomic_add(force, o + sc.surface[eb[1]], -energy_g * dm_db)
                wp.atomic_add(force, o + sc.surface[eb[0]], energy_g * dm_db)
                wp.atomic_add(force, o + sc.surface[ea[0]], ((f64(1.0) - st[0]) * fn) * r)
                wp.atomic_add(force, o + sc.surface[ea[1]], (st[0] * fn) * r)
                wp.atomic_add(force, o + sc.surface[eb[0]], (-(f64(1.0) - st[1]) * fn) * r)
                wp.atomic_add(force, o + sc.surface[eb[1]], (-st[1] * fn) * r)


# ---------------------------------------------------------------- model "barrier": lagged friction
# A friction pair is one of the barrier's pair slots, both kinds in one numbering per problem: slot j < S K is
# vertex-triangle slot k of surface vertex s (j = s K + k), slot S K + e KE + k edge-edge slot k of surface
# edge e. Either way four points with coefficients c: (v, f_0, f_1, f_2; 1, -w) or (a_0, a_1, b_0, b_1;
# 1 - s, s, -(1 - t), -t), in two groups (v | f's corners, e's ends | g's ends): the Hessian blocks within a
# group lie in the FEM block pattern (tet edges), those across the groups are couplings.
@wp.func
def listed_pair(sc: SelfContactArrays, b: int, j: int) -> int:
    """The feature (triangle or edge; -1: none) in pair slot j of problem b's lists (the last pairing)."""
    SK = sc.surface.shape[0] * sc.candidates
    if j < SK:
        return sc.pair[b * SK + j]
    return sc.edge_pair[b * sc.edges.shape[0] * sc.edge_candidates + j - SK]


@wp.func
def barrier_pair(
    sc: SelfContactArrays,
    positions: wp.array(dtype=wp.vec3d),
    young: f64,
    kappa: f64,
    b: int,
    j: int,
    other: int,
):
    """The barrier pair of slot j's vertex (edge) with feature ``other`` (triangle or edge) at
    ``positions``: its normal force lambda (mollified for edges; 0 where the pair is farther than d^), unit
    normal and coefficients c."""
    SK = sc.surface.shape[0] * sc.candidates
    o = b * sc.num_vertices
    lam = f64(0.0)
    n = wp.vec3d()
    c = wp.vec4d()
    if j < SK:
        s = j // sc.candidates
        d, r, w = vertex_triangle_distance(sc, positions, o, s, other)
        if d > f64(0.0) and d < sc.gap:
            lam = barrier_force(d, pair_stiffness(sc, kappa, young, s), sc.gap)
            n = r / d
            c = wp.vec4d(f64(1.0), -w[0], -w[1], -w[2])
    else:
        e = (j - SK) // sc.edge_candidates
        d, r, st = edge_edge_distance(sc, positions, o, e, other)
        if d > f64(0.0) and d < sc.gap:
            m, dm_da, dm_db = edge_mollifier(sc, positions, o, e, other)
            lam = m * barrier_force(d, edge_pair_stiffness(sc, kappa, young, e, other), sc.gap)
            n = r / d
            c = wp.vec4d(f64(1.0) - st[0], st[0], -(f64(1.0) - st[1]), -st[1])
    return lam, n, c


@wp.func
def lagged_with(sc: SelfContactArrays, fr: FrictionPairs, b: int, j: int, other: int) -> bool:
    """Whether slot j's vertex (edge) has a friction pair with feature ``other`` (in any of its slots: a
    rebuilt list may hold its pairs in another order)."""
    SK = sc.surface.shape[0] * sc.candidates
    first = (j // sc.candidates) * sc.candidates
    K = sc.candidates
    if j >= SK:
        K = sc.edge_candidates
        first = SK + ((j - SK) // K) * K
    found = bool(False)  # noqa: UP018
    for k in range(K):
        if fr.other[b * fr.slots + first + k] == other:
            found = True
    return found


@wp.func
def pair_points(sc: SelfContactArrays, j: int, other: int) -> wp.vec4i:
    """Mesh vertices of friction slot j's four points (its pair with feature ``other``)."""
    SK = sc.surface.shape[0] * sc.candidates
    if j < SK:
        ids = sc.faces[other]
        return wp.vec4i(sc.surface[j // sc.candidates], ids[0], ids[1], ids[2])
    ea = sc.edges[(j - SK) // sc.edge_candidates]
    eb = sc.edges[other]
    return wp.vec4i(sc.surface[ea[0]], sc.surface[ea[1]], sc.surface[eb[0]], sc.surface[eb[1]])


@wp.func
def pair_block(sc: SelfContactArrays, j: int, other: int, i: int, l: int) -> int:
    """A problem's BSR block of points i and l of friction slot j, -1 for two points across its groups (a
    coupling)."""
    SK = sc.surface.shape[0] * sc.candidates
    if j < SK:
        if i == 0 and l == 0:
            return sc.vertex_block[j // sc.candidates]
        if i > 0 and l > 0:
            return sc.face_blocks[other, 3 * (i - 1) + l - 1]
        return -1
    if i < 2 and l < 2:
        return sc.edge_blocks[(j - SK) // sc.edge_candidates, 2 * i + l]
    if i > 1 and l > 1:
        return sc.edge_blocks[other, 2 * (i - 2) + l - 2]
    return -1


@wp.func
def friction_energy(u: wp.vec3d, n: wp.vec3d, mu_lambda: f64, eps: f64) -> f64:
    """D = mu lambda F(y) of a pair whose relative motion since the lag is u, y = |(I - n n^T) u| its
    tangential slip: F(y) = y^2 / eps - y^3 / (3 eps^2) below the stick zone eps, y - eps / 3 beyond (IPC's
    f0, less its value at 0: C1, F' = f1 rises from 0 to 1 over the stick zone)."""
    t = u - wp.dot(u, n) * n
    y = wp.length(t)
    if y < eps:
        return mu_lambda * (y * y / eps - y * y * y / (f64(3.0) * eps * eps))
    return mu_lambda * (y - eps / f64(3.0))


@wp.func
def friction_gradient(u: wp.vec3d, n: wp.vec3d, mu_lambda: f64, eps: f64) -> wp.vec3d:
    """dD/du = mu lambda f1(y) t / y, t = (I - n n^T) u: the friction force's magnitude rises with the slip
    to mu lambda at eps (Coulomb's), along the slip."""
    t = u - wp.dot(u, n) * n
    y = wp.length(t)
    if y < eps:
        return (mu_lambda * (f64(2.0) / eps - y / (eps * eps))) * t
    return (mu_lambda / y) * t


@wp.func
def friction_hessian(u: wp.vec3d, n: wp.vec3d, mu_lambda: f64, eps: f64) -> wp.mat33d:
    """d^2D/du^2 (exact, PSD): mu lambda ((2 / eps - y / eps^2) P - t t^T / (eps^2 y)) in the stick zone,
    mu lambda (P - t t^T / y^2) / y beyond, P = I - n n^T."""
    P = wp.identity(n=3, dtype=f64) - wp.outer(n, n)
    t = P * u
    y = wp.length(t)
    if y < eps:
        h = (f64(2.0) / eps - y / (eps * eps)) * P
        if y > f64(0.0):
            h = h - (f64(1.0) / (eps * eps * y)) * wp.outer(t, t)
        return mu_lambda * h
    return (mu_lambda / y) * (P - wp.outer(t, t) / (y * y))


@wp.func
def friction_slip(
    positions: wp.array(dtype=wp.vec3d), o: int, fr: FrictionPairs, ref: int, points: wp.vec4i, c: wp.vec4d
) -> wp.vec3d:
    """u = sum_i c_i (x_i - X_i): a pair's relative motion since the lag (state at offset o, its problem's
    reference at ref), with the lagged coefficients."""
    u = wp.vec3d()
    for i in range(4):
        u += c[i] * (positions[o + points[i]] - fr.reference[ref + points[i]])
    return u


@wp.kernel
def lag_friction_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    active: wp.array(dtype=wp.int32),
    fr: FrictionPairs,
):
    """Lag the friction of the active problems at ``positions``: slot j's listed barrier pair, if closer
    than d^, with its normal force, normal and coefficients; else none."""
    b, j = wp.tid()
    if active[b] == 0:
        return
    i = b * fr.slots + j
    fr.other[i] = -1
    other = listed_pair(sc, b, j)
    if other >= 0:
        lam, n, c = barrier_pair(sc, positions, youngs[b], kappa, b, j, other)
        if lam > f64(0.0):
            fr.other[i] = other
            fr.force[i] = lam
            fr.normal[i] = n
            fr.coefficients[i] = c


@wp.kernel
def lag_reference_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    active: wp.array(dtype=wp.int32),
    fr: FrictionPairs,
):
    """The active problems' positions at the lag: the pairs' slips are measured from them."""
    b, v = wp.tid()
    if active[b] == 0:
        return
    i = b * sc.num_vertices + v
    fr.reference[i] = positions[i]


@wp.kernel
def friction_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    fr: FrictionPairs,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += the friction potential of friction slot j in trial state p."""
    p, j = wp.tid()
    b = p % active.shape[0]
    i = b * fr.slots + j
    if active[b] == 0 or fr.other[i] < 0:
        return
    points = pair_points(sc, j, fr.other[i])
    u = friction_slip(positions, p * sc.num_vertices, fr, b * sc.num_vertices, points, fr.coefficients[i])
    wp.atomic_add(energy, p, friction_energy(u, fr.normal[i], fr.mu * fr.force[i], fr.slip))


@wp.kernel
def friction_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    fr: FrictionPairs,
    rows_per_problem: int,
    blocks_per_problem: int,
    couplings_per_problem: int,
    coupling_offset: int,
    active: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    gradient: wp.array(dtype=wp.vec3d),
    hessian: wp.array(dtype=wp.mat33d),
    coupling_rows: wp.array(dtype=wp.int32),
    coupling_cols: wp.array(dtype=wp.int32),
    coupling: wp.array(dtype=wp.mat33d),
):
    """Gradient c_i dD/du of friction slot j on its points and Hessian c c^T (x) M, M =
    :func:`friction_hessian`: the blocks within its groups into the pattern, those across them (3 or 4) to
    the couplings from ``coupling_offset`` (4 per slot)."""
    b, j = wp.tid()
    i = b * fr.slots + j
    if active[b] == 0 or fr.other[i] < 0:
        return
    o = b * sc.num_vertices
    points = pair_points(sc, j, fr.other[i])
    c = fr.coefficients[i]
    u = friction_slip(positions, o, fr, o, points, c)
    ml = fr.mu * fr.force[i]
    gu = friction_gradient(u, fr.normal[i], ml, fr.slip)
    mm = friction_hessian(u, fr.normal[i], ml, fr.slip)
    row = b * rows_per_problem
    ob = b * blocks_per_problem
    slot = b * couplings_per_problem + coupling_offset + 4 * j
    k = int(0)  # noqa: UP018
    for a in range(4):
        wp.atomic_add(gradient, row + points[a], c[a] * gu)
        for l in range(4):
            block = pair_block(sc, j, fr.other[i], a, l)
            if block >= 0:
                wp.atomic_add(hessian, ob + block, (c[a] * c[l]) * mm)
            elif a < l:
                coupling_rows[slot + k] = points[a]
                coupling_cols[slot + k] = points[l]
                coupling[slot + k] = masked_block((c[a] * c[l]) * mm, free[points[a]], free[points[l]])
                k += 1


@wp.kernel
def friction_force_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    fr: FrictionPairs,
    force: wp.array(dtype=wp.vec3d),
):
    """Friction force of friction slot j on its points (rows b N + v)."""
    b, j = wp.tid()
    i = b * fr.slots + j
    if fr.other[i] < 0:
        return
    o = b * sc.num_vertices
    points = pair_points(sc, j, fr.other[i])
    c = fr.coefficients[i]
    gu = friction_gradient(
        friction_slip(positions, o, fr, o, points, c), fr.normal[i], fr.mu * fr.force[i], fr.slip
    )
    for a in range(4):
        wp.atomic_add(force, o + points[a], -c[a] * gu)


@wp.kernel
def friction_lag_error_kernel(
    positions: wp.array(dtype=wp.vec3d),
    sc: SelfContactArrays,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    fr: FrictionPairs,
    active: wp.array(dtype=wp.int32),
    largest: wp.array(dtype=wp.float64),
    total: wp.array(dtype=wp.float64),
    capacity: wp.array(dtype=wp.float64),
):
    """Per problem: the largest and the summed friction capacity error, mu (|lambda - lambda_lag| + lambda
    |n - n_lag|) of the friction pair in slot j (its normal force and normal now against the lagged ones),
    and mu lambda of the listed pair in slot j where that acts now (closer than d^) but has no friction pair
    (lagged nowhere); and the summed capacity mu lambda of the acting listed pairs. Pairs are matched by
    their features, not their slots (a rebuilt list may hold them in another order)."""
    b, j = wp.tid()
    if active[b] == 0:
        return
    i = b * fr.slots + j
    err = f64(0.0)
    if fr.other[i] >= 0:
        lam, n, c = barrier_pair(sc, positions, youngs[b], kappa, b, j, fr.other[i])
        err = fr.mu * (wp.abs(lam - fr.force[i]) + lam * wp.length(n - fr.normal[i]))
    listed = listed_pair(sc, b, j)
    if listed >= 0:
        lam, n, c = barrier_pair(sc, positions, youngs[b], kappa, b, j, listed)
        if lam > f64(0.0):
            wp.atomic_add(capacity, b, fr.mu * lam)
            if not lagged_with(sc, fr, b, j, listed):
                err += fr.mu * lam
    if err > f64(0.0):
        wp.atomic_max(largest, b, err)
        wp.atomic_add(total, b, err)


@wp.kernel
def surface_move_kernel(
    direction: wp.array(dtype=wp.vec3d),
    rows_per_problem: int,
    sc: SelfContactArrays,
    active: wp.array(dtype=wp.int32),
    move: wp.array(dtype=wp.float64),
):
    """move[b] = the largest move |dx| of a surface vertex of problem b along ``direction`` (B R rows)."""
    b, s = wp.tid()
    if active[b] != 0:
        wp.atomic_max(move, b, wp.length(direction[b * rows_per_problem + sc.surface[s]]))


@wp.kernel
def vertex_step_bound_kernel(
    positions: wp.array(dtype=wp.vec3d),
    direction: wp.array(dtype=wp.vec3d),
    rows_per_problem: int,
    sc: SelfContactArrays,
    fraction: f64,
    move: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    bound: wp.array(dtype=wp.float64),
):
    """bound[b] <- min(bound[b], the step along ``direction`` that closes ``fraction`` of the distance of
    any pair of surface vertex s): per candidate |x_v - c| can shrink by at most max_i |dx_v - dx_i| per unit
    step (c on the triangle: translation-invariant, as additive CCD); any other triangle lies beyond the
    clear radius and closes by at most |dx_v| + move[b]."""
    b, s = wp.tid()
    if active[b] == 0:
        return
    R = rows_per_problem
    S = sc.surface.shape[0]
    o = b * sc.num_vertices
    dv = direction[b * R + sc.surface[s]]
    reach = wp.length(dv) + move[b]
    if reach > f64(0.0):
        wp.atomic_min(bound, b, fraction * sc.clear[b * S + s] / reach)
    K = sc.candidates
    first = (b * S + s) * K
    for k in range(K):
        f = sc.pair[first + k]
        if f >= 0:
            d, r, w = vertex_triangle_distance(sc, positions, o, s, f)
            ids = sc.faces[f]
            closing = f64(0.0)
            for i in range(3):
                closing = wp.max(closing, wp.length(dv - direction[b * R + ids[i]]))
            if closing > f64(0.0):
                wp.atomic_min(bound, b, fraction * d / closing)


@wp.kernel
def edge_step_bound_kernel(
    positions: wp.array(dtype=wp.vec3d),
    direction: wp.array(dtype=wp.vec3d),
    rows_per_problem: int,
    sc: SelfContactArrays,
    fraction: f64,
    move: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    bound: wp.array(dtype=wp.float64),
):
    """As :func:`vertex_step_bound_kernel` for the edge pairs of surface edge e: per candidate the distance
    closes by at most max_ij |da_i - db_j| per unit step."""
    b, e = wp.tid()
    if active[b] == 0:
        return
    R = rows_per_problem
    E = sc.edges.shape[0]
    o = b * sc.num_vertices
    ea = sc.edges[e]
    d0 = direction[b * R + sc.surface[ea[0]]]
    d1 = direction[b * R + sc.surface[ea[1]]]
    reach = wp.max(wp.length(d0), wp.length(d1)) + move[b]
    if reach > f64(0.0):
        wp.atomic_min(bound, b, fraction * sc.edge_clear[b * E + e] / reach)
    K = sc.edge_candidates
    first = (b * E + e) * K
    for k in range(K):
        g = sc.edge_pair[first + k]
        if g >= 0:
            d, r, st = edge_edge_distance(sc, positions, o, e, g)
            eb = sc.edges[g]
            c0 = direction[b * R + sc.surface[eb[0]]]
            c1 = direction[b * R + sc.surface[eb[1]]]
            closing = wp.max(
                wp.max(wp.length(d0 - c0), wp.length(d0 - c1)), wp.max(wp.length(d1 - c0), wp.length(d1 - c1))
            )
            if closing > f64(0.0):
                wp.atomic_min(bound, b, fraction * d / closing)


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


def surface_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface's unique edges (E, 2) (sorted ends, in ``faces``' vertex numbering), the edge opposite
    corner k of each triangle (F, 3), and each edge's first triangle (E,) (its owner: each edge is visited
    once, through it)."""
    F = len(faces)
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    ends = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    edges, inverse = np.unique(ends, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    face_edges = inverse.reshape(3, F).T.copy()
    owner = np.full(len(edges), F, dtype=np.int64)
    np.minimum.at(owner, inverse, np.tile(np.arange(F), 3))
    return edges, face_edges, owner


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
    problem over the deformed surface, the vertex-triangle pairs (and with model "barrier" the edge-edge
    pairs), and the launches of the kernels above."""

    def __init__(
        self, mesh, pattern, batch_size: int, size: float, device, model: str = "prism", friction: float = 0.0
    ):
        if model not in SELF_CONTACT_MODELS:
            raise ValueError(f"self-contact model must be one of {SELF_CONTACT_MODELS}, got {model!r}")
        if not (np.isfinite(friction) and friction >= 0):
            raise ValueError(f"self-contact friction coefficient must be finite and >= 0, got {friction!r}")
        if friction > 0 and model != "barrier":
            raise ValueError(f"self-contact friction needs self-contact model 'barrier', got {model!r}")
        #: friction coefficient mu of the surface on itself (model "barrier"; 0: frictionless)
        self.friction = float(friction)
        self.model = model
        self.barrier = barrier = model == "barrier"
        self.batch_size = B = int(batch_size)
        self.device = dev = device
        N = mesh.num_vertices
        faces = mesh.surface_faces.astype(np.int32)
        surface = mesh.surface_vertices.astype(np.int32)
        self.num_surface = S = len(surface)
        self.num_faces = F = len(faces)
        self.radius = SELF_CONTACT_RADIUS * size
        self.depth = SELF_CONTACT_DEPTH * size
        self.gap = SELF_CONTACT_GAP * size
        pairs = np.arange(9)
        face_blocks = pattern.block_index(faces[:, pairs // 3].ravel(), faces[:, pairs % 3].ravel())
        if np.any(face_blocks < 0):
            raise ValueError("surface triangles must be tet faces (their edges in the block pattern)")
        start, excluded = excluded_triangles(mesh, SELF_CONTACT_EXCLUSION * size)
        edges, face_edges, owner = surface_edges(np.searchsorted(surface, faces))
        self.num_edges = E = len(edges)
        ends = surface[edges]
        edge_blocks = pattern.block_index(ends[:, [0, 0, 1, 1]].ravel(), ends[:, [0, 1, 0, 1]].ravel())
        sc = SelfContactArrays()
        sc.surface = wp.array(surface, dtype=wp.int32, device=dev)
        sc.faces = wp.array(faces, dtype=wp.vec3i, device=dev)
        sc.face_blocks = wp.array(face_blocks.reshape(F, 9), dtype=wp.int32, device=dev)
        sc.vertex_block = wp.array(pattern.vertex_diag[surface], dtype=wp.int32, device=dev)
        sc.area = wp.array(mesh.vertex_areas[surface], dtype=wp.float64, device=dev)
        sc.excluded_start = wp.array(start, dtype=wp.int32, device=dev)
        sc.excluded = wp.array(excluded, dtype=wp.int32, device=dev)
        sc.adjacent = wp.array(adjacent_triangles(faces), dtype=wp.int32, device=dev)
        sc.candidates = K = SELF_CONTACT_BARRIER_CANDIDATES if barrier else SELF_CONTACT_CANDIDATES
        sc.pair = wp.full(B * S * K, -1, dtype=wp.int32, device=dev)
        sc.pair_distance = wp.zeros(B * S * K, dtype=wp.float64, device=dev)
        sc.size = float(size)
        sc.depth = float(self.depth)
        sc.num_vertices = N
        sc.model = SELF_CONTACT_MODELS.index(model)
        sc.gap = float(self.gap)
        sc.edges = wp.array(edges.astype(np.int32), dtype=wp.vec2i, device=dev)
        sc.edge_length = wp.array(
            np.linalg.norm(mesh.points[ends[:, 0]] - mesh.points[ends[:, 1]], axis=1),
            dtype=wp.float64,
            device=dev,
        )
        sc.edge_blocks = wp.array(edge_blocks.reshape(E, 4), dtype=wp.int32, device=dev)
        sc.face_edges = wp.array(face_edges.astype(np.int32), dtype=wp.int32, device=dev)
        sc.edge_owner = wp.array(owner.astype(np.int32), dtype=wp.int32, device=dev)
        sc.edge_candidates = KE = SELF_CONTACT_EDGE_CANDIDATES
        sc.parallel = SELF_CONTACT_PARALLEL
        # the barrier's own pair arrays (one entry for the other models)
        vertex_slots, edge_slots = (B * S, B * E) if barrier else (1, 1)
        sc.clear = wp.zeros(vertex_slots, dtype=wp.float64, device=dev)
        sc.edge_pair = wp.full(edge_slots * KE, -1, dtype=wp.int32, device=dev)
        sc.edge_pair_distance = wp.zeros(edge_slots * KE, dtype=wp.float64, device=dev)
        sc.edge_clear = wp.zeros(edge_slots, dtype=wp.float64, device=dev)
        self.arrays = sc
        lists = PairLists()
        lists.points = wp.zeros(vertex_slots, dtype=wp.vec3d, device=dev)
        lists.clear = wp.zeros(vertex_slots, dtype=wp.float64, device=dev)
        lists.edge_clear = wp.zeros(edge_slots, dtype=wp.float64, device=dev)
        lists.drift = wp.zeros(vertex_slots, dtype=wp.float64, device=dev)
        lists.max_drift = wp.zeros(B, dtype=wp.float64, device=dev)
        lists.rebuild = wp.ones(B, dtype=wp.int32, device=dev)  # none built yet
        self._lists = lists
        self._lists_built = False
        self._points = wp.zeros(B * N, dtype=wp.vec3, device=dev)
        indices = wp.array(faces.ravel(), dtype=wp.int32, device=dev)
        self._meshes = [wp.Mesh(points=self._points[b * N : (b + 1) * N], indices=indices) for b in range(B)]
        self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=dev)
        self._force = wp.zeros(B * N, dtype=wp.vec3d, device=dev)
        #: friction slots per problem (model "barrier" with friction): one per barrier pair slot, S K + E KE
        self.friction_slots = P = S * K + E * KE if friction > 0 else 0
        #: coupling blocks per problem: 3 per vertex pair slot (one slot per vertex; "barrier": K per vertex
        #: and 4 per edge pair slot, KE per edge; then 4 per friction slot)
        self.couplings_per_problem = C = 3 * S * K + 4 * E * KE + 4 * P if barrier else 3 * S
        fr = FrictionPairs()
        fr.reference = wp.zeros(max(B * N * (P > 0), 1), dtype=wp.vec3d, device=dev)
        fr.other = wp.full(max(B * P, 1), -1, dtype=wp.int32, device=dev)
        fr.coefficients = wp.zeros(max(B * P, 1), dtype=wp.vec4d, device=dev)
        fr.normal = wp.zeros(max(B * P, 1), dtype=wp.vec3d, device=dev)
        fr.force = wp.zeros(max(B * P, 1), dtype=wp.float64, device=dev)
        fr.slots = P
        fr.mu = self.friction
        #: the stick zone eps of the friction pairs [m] (``SELF_CONTACT_FRICTION_SLIP`` h)
        self.slip = fr.slip = SELF_CONTACT_FRICTION_SLIP * float(size)
        self._friction = fr
        #: the (vertex, vertex) Hessian blocks of the last assembly outside the block pattern (B C,)
        self.coupling = (
            wp.zeros(B * C, dtype=wp.int32, device=dev),
            wp.zeros(B * C, dtype=wp.int32, device=dev),
            wp.zeros(B * C, dtype=wp.mat33d, device=dev),
        )
        self._penetration = wp.zeros(B * S, dtype=wp.float64, device=dev)
        self._move = wp.zeros(B, dtype=wp.float64, device=dev)
        self._bound = wp.zeros(B, dtype=wp.float64, device=dev)
        if barrier:
            self._check_rest(mesh)

    def _check_rest(self, mesh) -> None:
        """Model "barrier": refuse a surface that comes within the activation distance d^ of itself at rest
        (away from the excluded neighbourhoods): its barrier would push it apart before any load, or be
        infinite where it touches or intersects itself."""
        x = np.tile(mesh.points, (self.batch_size, 1))
        self.update_pairs(wp.array(x, dtype=wp.vec3d, device=self.device))
        sc = self.arrays
        S, K, E, KE = self.num_surface, sc.candidates, self.num_edges, sc.edge_candidates
        pair = sc.pair.numpy()[: S * K].reshape(S, K)
        dist = np.where(pair >= 0, sc.pair_distance.numpy()[: S * K].reshape(S, K), np.inf)
        edge_pair = sc.edge_pair.numpy()[: E * KE].reshape(E, KE)
        edge_dist = np.where(edge_pair >= 0, sc.edge_pair_distance.numpy()[: E * KE].reshape(E, KE), np.inf)
        surface, faces = mesh.surface_vertices, mesh.surface_faces
        edges = surface[sc.edges.numpy()]
        if dist.size and dist.min() < self.gap:
            s, k = np.unravel_index(np.argmin(dist), dist.shape)
            raise ValueError(
                f"self-contact barrier: at rest surface vertex {surface[s]} lies {dist[s, k]:.3g} m from "
                f"surface triangle {faces[pair[s, k]].tolist()}, within the activation distance "
                f"{self.gap:.3g} m ({SELF_CONTACT_GAP} h): the surface (nearly) touches itself; separate "
                "those parts of the mesh or use self_contact_model 'prism'"
            )
        if edge_dist.size and edge_dist.min() < self.gap:
            e, k = np.unravel_index(np.argmin(edge_dist), edge_dist.shape)
            raise ValueError(
                f"self-contact barrier: at rest surface edges {edges[e].tolist()} and "
                f"{edges[edge_pair[e, k]].tolist()} lie {edge_dist[e, k]:.3g} m apart, within the activation "
                f"distance {self.gap:.3g} m ({SELF_CONTACT_GAP} h): the surface (nearly) touches itself"
            )

    def update_pairs(self, positions) -> None:
        """Refit the BVHs to ``positions`` (B N, one state per problem) and pair every surface vertex (and
        with model "barrier" every surface edge). Model "barrier" keeps a problem's lists while no pair
        left out of them can have closed more than 1 - ``SELF_CONTACT_KEPT_CLEAR`` of its vertex's (edge's)
        clear radius, nor come within d^ (every acting pair stays listed), and then only updates the clear
        radii."""
        B, dev, sc = self.batch_size, self.device, self.arrays
        wp.launch(
            surface_points_kernel, dim=B * sc.num_vertices, inputs=[positions, self._points], device=dev
        )
        for m in self._meshes:
            m.refit()
        inputs = [positions, self._mesh_ids, float(self.radius), sc]
        if self.barrier:
            lists = self._lists
            if self._lists_built:  # else every problem builds (rebuild starts at 1)
                lists.max_drift.zero_()
                lists.rebuild.zero_()
                S, E = self.num_surface, self.num_edges
                wp.launch(pair_list_drift_kernel, dim=(B, S), inputs=[positions, sc, lists], device=dev)
                kept = SELF_CONTACT_KEPT_CLEAR
                wp.launch(stale_vertex_lists_kernel, dim=(B, S), inputs=[sc, lists, kept], device=dev)
                wp.launch(stale_edge_lists_kernel, dim=(B, E), inputs=[sc, lists, kept], device=dev)
            self._lists_built = True
            wp.launch(barrier_pair_kernel, dim=(B, self.num_surface), inputs=[*inputs, lists], device=dev)
            wp.launch(edge_pair_kernel, dim=(B, self.num_edges), inputs=[*inputs, lists], device=dev)
        else:
            wp.launch(pair_kernel, dim=(B, self.num_surface), inputs=inputs, device=dev)

    def add_energy(self, positions, states: int, youngs, kappa, smoothing, active, energy) -> None:
        """energy[p] += the penalty of each of the ``states`` packed states (trial-major) with the pairs."""
        if self.barrier:
            inputs = [positions, self.arrays, youngs, float(kappa), active, energy]
            wp.launch(
                barrier_energy_kernel, dim=(states, self.num_surface), inputs=inputs, device=self.device
            )
            wp.launch(
                edge_barrier_energy_kernel, dim=(states, self.num_edges), inputs=inputs, device=self.device
            )
            if self.friction > 0:
                inputs = [positions, self.arrays, self._friction, active, energy]
                dim = (states, self.friction_slots)
                wp.launch(friction_energy_kernel, dim=dim, inputs=inputs, device=self.device)
            return
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
        if self.barrier:
            inputs = [positions, self.arrays, youngs, float(kappa), rows, blocks, self.couplings_per_problem]
            inputs += [active, free]
            outputs = [gradient, hessian, *self.coupling]
            dev = self.device
            wp.launch(
                barrier_gradient_hessian_kernel,
                dim=(self.batch_size, self.num_surface),
                inputs=inputs,
                outputs=outputs,
                device=dev,
            )
            wp.launch(
                edge_barrier_gradient_hessian_kernel,
                dim=(self.batch_size, self.num_edges),
                inputs=inputs,
                outputs=outputs,
                device=dev,
            )
            if self.friction > 0:
                C, P = self.couplings_per_problem, self.friction_slots
                inputs = [positions, self.arrays, self._friction, rows, blocks, C, C - 4 * P, active, free]
                wp.launch(
                    friction_gradient_hessian_kernel,
                    dim=(self.batch_size, P),
                    inputs=inputs,
                    outputs=outputs,
                    device=dev,
                )
            return
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

    def lag_friction(self, positions, youngs, kappa, active, reference: bool = True) -> None:
        """Model "barrier" with friction: lag the friction of the problems where ``active`` (B,) is 1 at
        ``positions`` (B N, with the pairs of the last :meth:`update_pairs` there): the barrier pairs closer
        than d^ become the friction pairs, with their normal forces, normals and closest points frozen
        (IPC's lagged friction). ``reference``: the slips are measured from ``positions`` on (the start of a
        load increment); else from the last reference (a re-lag at an iterate of the increment)."""
        if self.friction <= 0:
            return
        B, dev, sc, fr = self.batch_size, self.device, self.arrays, self._friction
        inputs = [positions, sc, youngs, float(kappa), active, fr]
        wp.launch(lag_friction_kernel, dim=(B, self.friction_slots), inputs=inputs, device=dev)
        if reference:
            inputs = [positions, sc, active, fr]
            wp.launch(lag_reference_kernel, dim=(B, sc.num_vertices), inputs=inputs, device=dev)

    def friction_lag_error(self, positions, youngs, kappa, active, stats) -> None:
        """Model "barrier" with friction: into ``stats`` (3, B), zeroed, per problem where ``active`` is 1:
        the largest and the summed friction capacity error of the lagged pairs against those at
        ``positions`` (their normal forces and normals; the pairs of the last :meth:`update_pairs`, which
        must be at ``positions``), and the current summed capacity mu lambda."""
        B, dev = self.batch_size, self.device
        inputs = [
            positions,
            self.arrays,
            youngs,
            float(kappa),
            self._friction,
            active,
            stats[0],
            stats[1],
            stats[2],
        ]
        wp.launch(friction_lag_error_kernel, dim=(B, self.friction_slots), inputs=inputs, device=dev)

    def step_bound(self, positions, direction, rows_per_problem: int, active) -> np.ndarray:
        """Model "barrier": (B,) the step length along ``direction`` (B R rows, the object's vertices first)
        from ``positions`` up to which no pair's distance can close by more than
        ``SELF_CONTACT_STEP_FRACTION`` of itself (with the pairs of the last :meth:`update_pairs`, which must
        be at ``positions``): the line search stays below it, so no pair passes through zero between two
        trial states (no tunnelling). inf where nothing moves."""
        B, dev, sc = self.batch_size, self.device, self.arrays
        self._move.zero_()
        self._bound.fill_(np.inf)
        wp.launch(
            surface_move_kernel,
            dim=(B, self.num_surface),
            inputs=[direction, rows_per_problem, sc, active, self._move],
            device=dev,
        )
        inputs = [positions, direction, rows_per_problem, sc, SELF_CONTACT_STEP_FRACTION, self._move, active]
        wp.launch(
            vertex_step_bound_kernel, dim=(B, self.num_surface), inputs=[*inputs, self._bound], device=dev
        )
        wp.launch(edge_step_bound_kernel, dim=(B, self.num_edges), inputs=[*inputs, self._bound], device=dev)
        return self._bound.numpy().copy()

    def _evaluate(self, positions, youngs, kappa, smoothing) -> None:
        """Pairs at ``positions``, then every vertex's self-contact force and penetration (on the device;
        "barrier": no penetration, 0)."""
        self.update_pairs(positions)
        self._force.zero_()
        self._penetration.zero_()
        B, dev = self.batch_size, self.device
        if self.barrier:
            inputs = [positions, self.arrays, youngs, float(kappa)]
            wp.launch(
                barrier_force_kernel,
                dim=(B, self.num_surface),
                inputs=inputs,
                outputs=[self._force],
                device=dev,
            )
            wp.launch(
                edge_barrier_force_kernel,
                dim=(B, self.num_edges),
                inputs=inputs,
                outputs=[self._force],
                device=dev,
            )
            if self.friction > 0:
                inputs = [positions, self.arrays, self._friction]
                dim = (B, self.friction_slots)
                wp.launch(friction_force_kernel, dim=dim, inputs=inputs, outputs=[self._force], device=dev)
            return
        wp.launch(
            self_contact_force_kernel,
            dim=(B, self.num_surface),
            inputs=[positions, self.arrays, youngs, float(kappa), float(smoothing)],
            outputs=[self._force, self._penetration],
            device=dev,
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
