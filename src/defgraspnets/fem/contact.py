"""Frictional contact between object surface points and rigid bodies (Warp kernels).

Normal contact is a penalty on the signed distance g of each object surface vertex i (more generally,
each contact point: see the end of this docstring) to body k:

    E_n = k_i pen^3 / (6 delta_i)                          for pen < delta_i,
    E_n = k_i (pen^2 / 2 - delta_i pen / 2 + delta_i^2 / 6)  beyond,
    pen = max(0, -g),   k_i = kappa E A_i / h_i,   delta_i = zeta h_i,

with A_i the vertex's lumped surface area and h_i its element size. Beyond the onset width delta_i the
penalty is a contact *pressure* stiffness kappa E / h: a contact pressure p penetrates
p h / (kappa E) + delta / 2, i.e. a fraction (p / E) / kappa + zeta / 2 of the local element size. Within
the onset the stiffness rises linearly from zero, which makes E_n twice continuously differentiable: a
vertex that grazes the rim of a contact patch no longer switches Newton's Hessian between 0 and k_i
from one iteration to the next (with the plain quadratic penalty, grasps of coarse meshes needed
hundreds of Newton iterations; zeta = 1e-3 brought them to tens).

Friction is Coulomb's law in incremental (quasi-static) elastic-plastic form (penalty friction with
return mapping, as in Wriggers' Computational Contact Mechanics) with the normal force N_i and contact
normal n_i lagged from the latest iterate (as in IPC). The tangential stick-spring stretch is

    s = (I - n n^T) (x - y + s_0),

where x - y is the motion, since the last converged load step, of the vertex relative to the body's
material point it touched (y = the body's motion applied to the vertex's reference position), and s_0
is the elastic stretch stored at that step (zero for a new contact). At every converged step s_0 is
updated to s, returned onto the Coulomb cone |s_0| <= mu N / k_t if the contact slipped, so a stuck
contact keeps carrying its tangential force from one load step to the next.

and the friction potential is an elastic stick spring capped at the Coulomb force mu N:

    D(s) = k_t |s|^2 / 2                          for |s| <= eps = mu N / k_t   (stick)
    D(s) = mu N |s| - (mu N)^2 / (2 k_t)          otherwise                    (slip),

with k_t = k_i by default. Its force -dD/ds has magnitude min(k_t |s|, mu N). The stick zone eps is the
elastic tangential slip a contact tolerates before it slides (the role of IPC's eps_v); with k_t = k_i it
is mu N / k_i = mu (p / E) h / kappa for a contact pressure p: below 1e-3 h wherever p < E, micrometres.
``SolverOptions.friction_stick_slip`` = c > 0 widens it to at least c h_i, k_t = min(k_i, mu N / (c h_i)),
a regularisation on the scale of a Newton step. The Coulomb limit mu N, hence slip thresholds, stay as
they are (a pressed block pushed at 2 mu N slips at the same load fraction, 0.4995, with c = 0, 0.01,
0.05); stick gets softer: sticking vertices shift by up to c h_i before they slide (the block at 0.9 mu N:
0.007 h with c = 0, 0.049 h with c = 0.05), so c must stay small against the slips a study cares about.
Measured effect on Newton: that block needs 2-6x fewer iterations (34 -> 18, 41 -> 7), but the failing
soft-box squeeze ramps are limited by the penalty, not by friction (see ``squeeze_solver_options``), and
c = 0.05 does not make them converge; it does converge tilted 200 kPa grasps that stalled in friction
re-lags, at the price of fields that moved by 5-12 % of the displacement. Off (c = 0) by default.

Gradients of g are taken exactly; the Hessian keeps the Gauss-Newton term k n n^T (drops the curvature
of the body surface) and the PSD friction Hessian, so Newton directions always descend.

A body's placement is (R, t + travel a) with a its control axis in the object frame; the derivative
of the penetration with respect to travel is n . a.

Contact points (sub-vertex contact). The penalty and friction above act on *contact points*, each a
barycentric point x = sum_i w_i x_{v_i} of a surface triangle (v_0, v_1, v_2) with its own area A_p and
size h_p (:class:`ContactPoints`). By default (``SolverOptions.contact_subdivisions`` n = 1) they are the
surface vertices, (v, v, v; 1, 0, 0) with A_p = A_v: the vertex contact, bit for bit (a vertex point reads
its vertex's position as it is and skips its zero weights). With n > 1 they are the vertices of the
uniform n-subdivision of every surface triangle, each once (:func:`surface_contact_points`): the surface
vertices (area A_v / n^2), the n - 1 inner points of every edge (shared by its two faces) and the
(n - 1)(n - 2) / 2 interior points of every face, each with its lumped share of the subdivided surface
(a third of every sub-triangle of area A_f / n^2 it is a corner of), so the areas sum to the surface
area. The samples *replace* the vertex points rather than add to them: a vertex is itself a corner of the
grid of each of its triangles, and per-face samples with their corners (the fast membrane's
``contact_samples_per_face``) would hold every vertex and edge point once per adjacent face, each a
separate friction slot at the same place; the deduplicated grid is the vertex contact of the subdivided
surface, and n = 1 the vertex contact itself. Every point keeps the penalty length h of the whole mesh,
so the pressure stiffness kappa E / h and the penetration tolerance are those of the vertex contact.

A point's friction slot (lagged N and n, stick stretch s_0) is per (problem, point, body), its stick
anchor y the body's motion applied to the point's reference position sum_i w_i X_i. Its gradient goes to
vertex i with weight w_i; its Hessian is exact, the blocks w_i w_j H between the vertices of its triangle:
these pairs are tet edges, so they lie in the FEM's block pattern, and every linear solver (dense, banded,
dense_banded, direct, cg, amg) assembles from those same BSR values (no lumping needed; the travel couplings
of a force-controlled body go to the (dof, surface vertex) blocks with w_i). Results stay per surface
vertex: point forces lumped onto the vertices with the weights (sums over the surface unchanged).

Limits and cost (``benchmarks/fem_triangle_contact_cpu.md``): points are points; between them a body of
radius r dips into a triangle by up to about the sagitta r - sqrt(r^2 - R_c^2) of the largest empty circle
of the grid (R_c a sub-triangle's circumradius). And the FEM field is still linear across each element: a
body narrower than the elements that presses the middle of a face must move its three vertices, so it
meets a stiffer surface than one landing on a vertex. On the cap-8 membrane (vertices 9-10 mm apart) the
1 cm fingertip no longer passes between the vertices (vertex contact: no onset at an edge midpoint, contact
lost past 5 mm at a centroid), but landing on an edge or a centroid it pushes 32-50 % harder at 5 mm
depth than on a vertex (7-14 % at 25 mm), and even on a vertex the coarse membrane is 32-36 % stiffer than
the cap-16 one (the 20 mm sphere with vertex contact shows the same landing dependence: a mesh effect,
not a contact one). Cost: about n^2 times the contact slots of the vertex contact (cap 8: 642 -> 2562,
5762 for n = 2, 3); the membrane's contact kernels are a small part of a Newton iteration next to the
factorization, but the pokes took 2-4x the Newton iterations of vertex contact's pole pokes.
"""

from __future__ import annotations

import numpy as np
import warp as wp

f64 = wp.float64

PLANE = wp.constant(0)
SPHERE = wp.constant(1)
CAPSULE = wp.constant(2)
MESH = wp.constant(3)
ROUNDED_BOX = wp.constant(4)


@wp.func
def closest_point_on_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= f64(0.0) and d2 <= f64(0.0):
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= f64(0.0) and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= f64(0.0) and d1 >= f64(0.0) and d3 <= f64(0.0):
        return a + (d1 / (d1 - d3)) * ab
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= f64(0.0) and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= f64(0.0) and d2 >= f64(0.0) and d6 <= f64(0.0):
        return a + (d2 / (d2 - d6)) * ac
    va = d3 * d6 - d5 * d4
    if va <= f64(0.0) and (d4 - d3) >= f64(0.0) and (d5 - d6) >= f64(0.0):
        return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
    denom = f64(1.0) / (va + vb + vc)
    return a + ab * (vb * denom) + ac * (vc * denom)


@wp.func
def shape_signed_distance(
    kind: int,
    p: wp.vec3d,
    radius: f64,
    half_length: f64,
    half_extents: wp.vec3d,
    mesh: wp.uint64,
    mesh_points: wp.array(dtype=wp.vec3d),
    mesh_point_offset: int,
    query_distance: float,
):
    """Signed distance g [m] of shape-frame point p to the shape, and the unit normal (shape frame)
    pointing from the shape toward p (the direction in which g grows)."""
    zero = f64(0.0)
    ez = wp.vec3d(zero, zero, f64(1.0))
    if kind == PLANE:
        return p[2], ez
    if kind == ROUNDED_BOX:
        # box of half extents b with edges rounded by r (outer half extents b + r): exact C1 distance
        q = wp.vec3d(
            wp.abs(p[0]) - half_extents[0], wp.abs(p[1]) - half_extents[1], wp.abs(p[2]) - half_extents[2]
        )
        outside = wp.vec3d(wp.max(q[0], zero), wp.max(q[1], zero), wp.max(q[2], zero))
        d_out = wp.length(outside)
        inner = wp.min(wp.max(q[0], wp.max(q[1], q[2])), zero)
        sgn = wp.vec3d(wp.sign(p[0]), wp.sign(p[1]), wp.sign(p[2]))
        n = ez
        if d_out > f64(1e-15):
            n = wp.cw_mul(outside / d_out, sgn)
        else:  # deeper than r inside: the nearest face of the inner box
            if q[0] >= q[1] and q[0] >= q[2]:
                n = wp.vec3d(sgn[0], zero, zero)
            elif q[1] >= q[2]:
                n = wp.vec3d(zero, sgn[1], zero)
            else:
                n = wp.vec3d(zero, zero, sgn[2])
        return d_out + inner - radius, n
    if kind == SPHERE or kind == CAPSULE:
        q = wp.vec3d(zero, zero, zero)
        if kind == CAPSULE:
            q = wp.vec3d(zero, zero, wp.clamp(p[2], -half_length, half_length))
        v = p - q
        d = wp.length(v)
        n = ez
        if d > f64(1e-15):
            n = v / d
        return d - radius, n
    # triangle mesh: nearest face from the BVH (float32), exact distance in float64
    pf = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    query = wp.mesh_query_point_sign_winding_number(mesh, pf, query_distance)
    if not query.result:
        return f64(1.0e30), ez
    i0 = wp.mesh_get_index(mesh, query.face * 3 + 0)
    i1 = wp.mesh_get_index(mesh, query.face * 3 + 1)
    i2 = wp.mesh_get_index(mesh, query.face * 3 + 2)
    a = mesh_points[mesh_point_offset + i0]
    b = mesh_points[mesh_point_offset + i1]
    c = mesh_points[mesh_point_offset + i2]
    cp = closest_point_on_triangle(p, a, b, c)
    v = p - cp
    d = wp.length(v)
    sign = f64(query.sign)
    face_normal = wp.normalize(wp.cross(b - a, c - a))
    n = face_normal
    if d > f64(1e-12):
        n = sign * v / d
        # on a face interior the exact normal is the face normal (avoids noise for tiny distances)
        if wp.abs(wp.dot(n, face_normal)) > f64(0.999999):
            n = face_normal
    return sign * d, n


@wp.func
def shape_distance_hessian(
    kind: int, p: wp.vec3d, n: wp.vec3d, radius: f64, half_length: f64, half_extents: wp.vec3d
) -> wp.mat33d:
    """Hessian of the signed distance g (shape frame) at p, n its gradient from :func:`shape_signed_distance`:
    the rate at which the contact normal turns as p moves, ``d n / d p``. Planes, flat faces and a rounded
    box's inside have none; a sphere's normal turns as (I - n n^T) / d, d the distance from its centre (a
    capsule's side also leaves its axis out), and a rounded box's edge or corner as (P_A - n n^T) / d_out,
    P_A the axes along which p lies outside the inner box and d_out the distance from it.
    Triangle meshes are left at zero (their closest feature would be needed)."""
    zero = f64(0.0)
    H = wp.mat33d()
    eye = wp.identity(n=3, dtype=wp.float64)
    if kind == SPHERE or kind == CAPSULE:
        d = wp.length(p)
        P = eye
        if kind == CAPSULE:
            q = wp.vec3d(zero, zero, wp.clamp(p[2], -half_length, half_length))
            d = wp.length(p - q)
            if wp.abs(p[2]) < half_length:
                P = eye - wp.outer(wp.vec3d(zero, zero, f64(1.0)), wp.vec3d(zero, zero, f64(1.0)))
        if d > f64(1e-15):
            H = (P - wp.outer(n, n)) / d
    elif kind == ROUNDED_BOX:
        q = wp.vec3d(
            wp.abs(p[0]) - half_extents[0], wp.abs(p[1]) - half_extents[1], wp.abs(p[2]) - half_extents[2]
        )
        outside = wp.vec3d(wp.max(q[0], zero), wp.max(q[1], zero), wp.max(q[2], zero))
        d_out = wp.length(outside)
        if d_out > f64(1e-15):
            P = wp.mat33d()
            for i in range(3):
                if q[i] > zero:
                    P[i, i] = f64(1.0)
            H = (P - wp.outer(n, n)) / d_out
    return H


@wp.func
def body_index(b: int, k: int, num_bodies: int) -> int:
    return b * num_bodies + k


@wp.struct
class BodyArrays:
    """Rigid-body data for the kernels; per (problem b, body k) arrays are indexed b * num_bodies + k."""

    kind: wp.array(dtype=wp.int32)  # (K,)
    radius: wp.array(dtype=wp.float64)  # (B*K,) sphere / capsule / rounded-box radius, per problem
    half_length: wp.array(dtype=wp.float64)  # (K,)
    half_extents: wp.array(dtype=wp.vec3d)  # (K,) rounded box: half extents of the inner (unrounded) box
    mesh: wp.array(dtype=wp.uint64)  # (K,) Warp mesh id (0 if not a mesh)
    mesh_point_offset: wp.array(dtype=wp.int32)  # (K,) first vertex in mesh_points
    mesh_points: wp.array(dtype=wp.vec3d)  # float64 copies of all mesh vertices (shape frames)
    dof: wp.array(dtype=wp.int32)  # (K,) travel dof index, -1 if fixed
    rotation: wp.array(dtype=wp.mat33d)  # (B*K,) shape frame -> object frame
    translation: wp.array(dtype=wp.vec3d)  # (B*K,) shape origin at travel 0
    axis: wp.array(dtype=wp.vec3d)  # (B*K,) unit control axis in the object frame
    friction: wp.array(dtype=wp.float64)  # (B*K,) Coulomb coefficient
    ref_rotation: wp.array(dtype=wp.mat33d)  # (B*K,) placement at the last converged step
    ref_translation: wp.array(dtype=wp.vec3d)  # (B*K,) (includes that step's travel)
    num_bodies: int
    query_distance: float


@wp.func
def body_travel(bodies: BodyArrays, travel: wp.array(dtype=wp.float64), b: int, k: int, num_dofs: int) -> f64:
    """Travel of body k of problem b along its control axis (0 for a fixed body)."""
    d = bodies.dof[k]
    if d >= 0:
        return travel[b * num_dofs + d]
    return f64(0.0)


@wp.func
def body_gap(bodies: BodyArrays, b: int, k: int, x: wp.vec3d, travel: f64):
    """Signed distance g and object-frame normal of point x to body k of problem b at ``travel``."""
    bk = b * bodies.num_bodies + k
    R = bodies.rotation[bk]
    origin = bodies.translation[bk] + travel * bodies.axis[bk]
    p = wp.transpose(R) * (x - origin)
    g, n_local = shape_signed_distance(
        bodies.kind[k],
        p,
        bodies.radius[bk],
        bodies.half_length[k],
        bodies.half_extents[k],
        bodies.mesh[k],
        bodies.mesh_points,
        bodies.mesh_point_offset[k],
        bodies.query_distance,
    )
    return g, R * n_local


@wp.func
def body_gap_hessian(bodies: BodyArrays, b: int, k: int, x: wp.vec3d, travel: f64, n: wp.vec3d) -> wp.mat33d:
    """World-frame Hessian d^2 g / dx^2 of body k's signed distance at x (n: the world normal of body_gap)."""
    bk = b * bodies.num_bodies + k
    R = bodies.rotation[bk]
    origin = bodies.translation[bk] + travel * bodies.axis[bk]
    p = wp.transpose(R) * (x - origin)
    n_local = wp.transpose(R) * n
    H = shape_distance_hessian(
        bodies.kind[k], p, n_local, bodies.radius[bk], bodies.half_length[k], bodies.half_extents[k]
    )
    return R * H * wp.transpose(R)


@wp.func
def body_slip(
    bodies: BodyArrays, b: int, k: int, x: wp.vec3d, x_ref: wp.vec3d, travel: f64, n: wp.vec3d, s0: wp.vec3d
):
    """Stick-spring stretch s = (I - n n^T)(x - y + s_0) of the vertex relative to the body."""
    bk = b * bodies.num_bodies + k
    R = bodies.rotation[bk]
    origin = bodies.translation[bk] + travel * bodies.axis[bk]
    y = R * (wp.transpose(bodies.ref_rotation[bk]) * (x_ref - bodies.ref_translation[bk])) + origin
    w = x - y + s0
    return w - wp.dot(w, n) * n


@wp.struct
class ContactPoints:
    """The object's contact points (see :func:`surface_contact_points`): barycentric points
    x = sum_i w_i x_{v_i} of surface triangles; a surface vertex is the point (v, v, v; 1, 0, 0)."""

    vertex: wp.array(dtype=wp.vec3i)  # (P,) mesh vertices v_0, v_1, v_2
    weight: wp.array(dtype=wp.vec3d)  # (P,) barycentric weights w_i (sum 1; a zero weight is skipped)
    surface: wp.array(dtype=wp.vec3i)  # (P,) indices of v_i among the surface vertices (dof columns)
    area: wp.array(dtype=wp.float64)  # (P,) lumped surface area A of the point [m^2]
    size: wp.array(dtype=wp.float64)  # (P,) penalty length h [m]
    blocks: wp.array2d(dtype=wp.int32)  # (P, 9) BSR block (v_i, v_j) of one problem at 3 i + j


@wp.func
def point_position(
    points: ContactPoints, positions: wp.array(dtype=wp.vec3d), offset: int, p: int
) -> wp.vec3d:
    """x = sum_i w_i x_{v_i} of contact point p (positions of one state start at ``offset``); a vertex
    point reads its vertex's position as it is (no arithmetic, so vertex contact is bit for bit unchanged)."""
    ids = points.vertex[p]
    w = points.weight[p]
    x = positions[offset + ids[0]]
    if w[1] != f64(0.0) or w[2] != f64(0.0):
        x = w[0] * x + w[1] * positions[offset + ids[1]] + w[2] * positions[offset + ids[2]]
    return x


@wp.func
def contact_stiffness(kappa: f64, youngs: f64, area: f64, size: f64) -> f64:
    """k_i = kappa E A_i / h_i [N/m]."""
    return kappa * youngs * area / size


@wp.func
def penalty_energy(pen: f64, kn: f64, delta: f64) -> f64:
    """C2 penalty potential of the penetration pen: k pen^3 / (6 delta) up to pen = delta, then
    k (pen^2 / 2 - delta pen / 2 + delta^2 / 6)."""
    if pen <= f64(0.0):
        return f64(0.0)
    if pen < delta:
        return kn * pen * pen * pen / (f64(6.0) * delta)
    return kn * (f64(0.5) * pen * pen - f64(0.5) * delta * pen + delta * delta / f64(6.0))


@wp.func
def penalty_force(pen: f64, kn: f64, delta: f64) -> f64:
    """Normal contact force dE/dpen >= 0 [N]."""
    if pen <= f64(0.0):
        return f64(0.0)
    if pen < delta:
        return f64(0.5) * kn * pen * pen / delta
    return kn * (pen - f64(0.5) * delta)


@wp.func
def penalty_stiffness(pen: f64, kn: f64, delta: f64) -> f64:
    """d^2E/dpen^2 [N/m]: rises linearly from 0 to k over the onset width delta."""
    if pen <= f64(0.0):
        return f64(0.0)
    if pen < delta:
        return kn * pen / delta
    return kn


@wp.func
def stick_stiffness(mu_n: f64, kn: f64, stick_slip: f64, size: f64) -> f64:
    """Tangential stick stiffness k_t [N/m]: the penalty stiffness k_i, softened where needed to make the
    stick zone eps = mu N / k_t at least ``stick_slip`` h_i wide: k_t = min(k_i, mu N / (stick_slip h_i))."""
    if stick_slip > f64(0.0):
        return wp.min(kn, mu_n / (stick_slip * size))
    return kn


@wp.func
def friction_energy(s: wp.vec3d, mu_n: f64, k_t: f64) -> f64:
    sn = wp.length(s)
    eps = mu_n / k_t
    if sn <= eps:
        return f64(0.5) * k_t * sn * sn
    return mu_n * sn - f64(0.5) * mu_n * eps


@wp.kernel
def contact_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    ref_positions: wp.array(dtype=wp.vec3d),
    travel: wp.array(dtype=wp.float64),
    points: ContactPoints,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    stick_slip: f64,
    bodies: BodyArrays,
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    stick_stretch: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    num_dofs: int,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += penalty + friction potential of every (trial state p = t B + b of problem b, contact
    point, body); B = len(active), T = 1: the problems' states."""
    p, si, k = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    x = point_position(points, positions, p * num_vertices, si)
    t = body_travel(bodies, travel, p, k, num_dofs)
    size = points.size[si]
    kn = contact_stiffness(kappa, youngs[b], points.area[si], size)
    g, n = body_gap(bodies, b, k, x, t)
    e = penalty_energy(-g, kn, smoothing * size)
    c = (b * points.area.shape[0] + si) * bodies.num_bodies + k
    mu_n = bodies.friction[b * bodies.num_bodies + k] * lag_normal_force[c]
    if mu_n > f64(0.0):
        x_ref = point_position(points, ref_positions, b * num_vertices, si)
        s = body_slip(bodies, b, k, x, x_ref, t, lag_normal[c], stick_stretch[c])
        e += friction_energy(s, mu_n, stick_stiffness(mu_n, kn, stick_slip, size))
    wp.atomic_add(energy, p, e)


@wp.struct
class ContactBlocks:
    """BSR block indices (within one problem) of the contact couplings."""

    vertex_diag: wp.array(dtype=wp.int32)  # (N,) block (v, v)
    dof_diag: wp.array(dtype=wp.int32)  # (D,) block (N + d, N + d)
    dof_vertex: wp.array2d(dtype=wp.int32)  # (D, S) block (N + d, surface[s])
    vertex_dof: wp.array2d(dtype=wp.int32)  # (D, S) block (surface[s], N + d)
    blocks_per_problem: int
    rows_per_problem: int


@wp.kernel
def contact_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    ref_positions: wp.array(dtype=wp.vec3d),
    travel: wp.array(dtype=wp.float64),
    points: ContactPoints,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    stick_slip: f64,
    bodies: BodyArrays,
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    stick_stretch: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    num_dofs: int,
    blocks: ContactBlocks,
    active: wp.array(dtype=wp.int32),
    exact: wp.array(dtype=wp.int32),
    gradient: wp.array(dtype=wp.vec3d),
    hessian: wp.array(dtype=wp.mat33d),
):
    """Add contact and friction gradients (vertex rows and travel-dof rows, component 0) and Hessians.

    The penalty's Hessian is ``k_g n n^T - f_n d^2g/dx^2`` (and its travel couplings): the second term, the
    normal turning under a vertex that slides over a curved part of the body (a pad's rounded rim, a sphere),
    is negative semi-definite and is added only where ``exact[b]`` asks for the exact Hessian. It is as
    stiff as the tangential elastic support of a slipping contact, so leaving it out costs Newton its
    quadratic convergence (measured: residual halving per iteration on a tilted Franka grasp)."""
    b, si, k = wp.tid()
    if active[b] == 0:
        return
    x = point_position(points, positions, b * num_vertices, si)
    d = bodies.dof[k]
    t = body_travel(bodies, travel, b, k, num_dofs)
    size = points.size[si]
    kn = contact_stiffness(kappa, youngs[b], points.area[si], size)
    bk = b * bodies.num_bodies + k
    a = bodies.axis[bk]
    g, n = body_gap(bodies, b, k, x, t)

    grad_x = wp.vec3d()
    grad_t = f64(0.0)
    H_xx = wp.mat33d()
    H_xt = wp.vec3d()
    H_tt = f64(0.0)
    c = (b * points.area.shape[0] + si) * bodies.num_bodies + k
    na = wp.dot(n, a)
    if g < f64(0.0):
        delta = smoothing * size
        fn = penalty_force(-g, kn, delta)
        kg = penalty_stiffness(-g, kn, delta)
        grad_x = -fn * n
        grad_t = fn * na
        H_xx = kg * wp.outer(n, n)
        H_xt = -kg * na * n
        H_tt = kg * na * na
        if exact[b] != 0:
            Hg = body_gap_hessian(bodies, b, k, x, t, n)
            Hga = Hg * a
            H_xx -= fn * Hg
            H_xt += fn * Hga
            H_tt -= fn * wp.dot(a, Hga)

    mu_n = bodies.friction[bk] * lag_normal_force[c]
    if mu_n > f64(0.0):
        nl = lag_normal[c]
        x_ref = point_position(points, ref_positions, b * num_vertices, si)
        s = body_slip(bodies, b, k, x, x_ref, t, nl, stick_stretch[c])
        sn = wp.length(s)
        tangent = wp.identity(n=3, dtype=wp.float64) - wp.outer(nl, nl)
        Hf = wp.mat33d()
        fs = wp.vec3d()  # dD/ds
        kt = stick_stiffness(mu_n, kn, stick_slip, size)
        if sn <= mu_n / kt:
            fs = kt * s
            Hf = kt * tangent
        else:
            sh = s / sn
            fs = mu_n * sh
            Hf = (mu_n / sn) * (tangent - wp.outer(sh, sh))
        grad_x += fs
        grad_t -= wp.dot(fs, a)
        H_xx += Hf
        Ha = Hf * a
        H_xt -= Ha
        H_tt += wp.dot(a, Ha)

    if g >= f64(0.0) and mu_n <= f64(0.0):
        return
    # scatter to the point's vertices with its weights: x = sum_i w_i x_i, so the gradient of vertex i is
    # w_i grad_x and its Hessian blocks (i, j) w_i w_j H_xx (a vertex point: w = (1, 0, 0), the blocks of
    # its zero weights skipped, so vertex contact adds exactly what it always did)
    ids = points.vertex[si]
    w = points.weight[si]
    surf = points.surface[si]
    ob = b * blocks.blocks_per_problem
    zero = f64(0.0)
    for i in range(3):
        wi = w[i]
        if wi != zero:
            wp.atomic_add(gradient, b * blocks.rows_per_problem + ids[i], wi * grad_x)
            for j in range(3):
                wj = w[j]
                if wj != zero:
                    wp.atomic_add(hessian, ob + points.blocks[si, 3 * i + j], (wi * wj) * H_xx)
            if d >= 0:
                Hi = wi * H_xt
                wp.atomic_add(
                    hessian,
                    ob + blocks.dof_vertex[d, surf[i]],
                    wp.mat33d(Hi[0], Hi[1], Hi[2], zero, zero, zero, zero, zero, zero),
                )
                wp.atomic_add(
                    hessian,
                    ob + blocks.vertex_dof[d, surf[i]],
                    wp.mat33d(Hi[0], zero, zero, Hi[1], zero, zero, Hi[2], zero, zero),
                )
    if d >= 0:
        row = b * blocks.rows_per_problem + num_vertices + d
        wp.atomic_add(gradient, row, wp.vec3d(grad_t, f64(0.0), f64(0.0)))
        wp.atomic_add(
            hessian, ob + blocks.dof_diag[d], wp.mat33d(H_tt, zero, zero, zero, zero, zero, zero, zero, zero)
        )


@wp.kernel
def contact_state_kernel(
    positions: wp.array(dtype=wp.vec3d),
    ref_positions: wp.array(dtype=wp.vec3d),
    travel: wp.array(dtype=wp.float64),
    points: ContactPoints,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    stick_slip: f64,
    bodies: BodyArrays,
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    stick_stretch: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    num_dofs: int,
    normal_force: wp.array(dtype=wp.float64),
    normal: wp.array(dtype=wp.vec3d),
    gap: wp.array(dtype=wp.float64),
    friction_force: wp.array(dtype=wp.vec3d),
    sticking: wp.array(dtype=wp.int32),
):
    """Per contact slot (b, point s, k): gap g, penalty normal force k pen >= 0 along the normal, and the
    friction force on the object point (-dD/ds, with the lagged normal force), sticking = |s| <= eps."""
    b, si, k = wp.tid()
    x = point_position(points, positions, b * num_vertices, si)
    t = body_travel(bodies, travel, b, k, num_dofs)
    size = points.size[si]
    kn = contact_stiffness(kappa, youngs[b], points.area[si], size)
    g, n = body_gap(bodies, b, k, x, t)
    c = (b * points.area.shape[0] + si) * bodies.num_bodies + k
    gap[c] = g
    normal[c] = n
    normal_force[c] = penalty_force(-g, kn, smoothing * size)
    mu_n = bodies.friction[b * bodies.num_bodies + k] * lag_normal_force[c]
    ff = wp.vec3d()
    stick = 0
    if mu_n > f64(0.0):
        x_ref = point_position(points, ref_positions, b * num_vertices, si)
        s = body_slip(bodies, b, k, x, x_ref, t, lag_normal[c], stick_stretch[c])
        sn = wp.length(s)
        kt = stick_stiffness(mu_n, kn, stick_slip, size)
        if sn <= mu_n / kt:
            ff = -kt * s
            stick = 1
        else:
            ff = -(mu_n / sn) * s
    friction_force[c] = ff
    sticking[c] = stick


@wp.kernel
def commit_stick_stretch_kernel(
    positions: wp.array(dtype=wp.vec3d),
    ref_positions: wp.array(dtype=wp.vec3d),
    travel: wp.array(dtype=wp.float64),
    points: ContactPoints,
    youngs: wp.array(dtype=wp.float64),
    kappa: f64,
    smoothing: f64,
    stick_slip: f64,
    bodies: BodyArrays,
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    stick_stretch: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    num_dofs: int,
    mask: wp.array(dtype=wp.int32),
):
    """At a converged step: s_0 <- s (in place), returned onto the cone |s_0| <= mu N / k_t (0 out of
    contact). Takes the arguments of the other contact kernels (``smoothing`` unused): one list serves all."""
    b, si, k = wp.tid()
    if mask[b] == 0:
        return
    c = (b * points.area.shape[0] + si) * bodies.num_bodies + k
    t = body_travel(bodies, travel, b, k, num_dofs)
    size = points.size[si]
    kn = contact_stiffness(kappa, youngs[b], points.area[si], size)
    mu_n = bodies.friction[b * bodies.num_bodies + k] * lag_normal_force[c]
    s0 = wp.vec3d()
    if mu_n > f64(0.0):
        x = point_position(points, positions, b * num_vertices, si)
        x_ref = point_position(points, ref_positions, b * num_vertices, si)
        s = body_slip(bodies, b, k, x, x_ref, t, lag_normal[c], stick_stretch[c])
        eps = mu_n / stick_stiffness(mu_n, kn, stick_slip, size)
        sn = wp.length(s)
        s0 = s
        if sn > eps:
            s0 = s * (eps / sn)
    stick_stretch[c] = s0


# ---------------------------------------------------------------- friction lag (per problem, on the device)
@wp.kernel
def friction_lag_error_kernel(
    normal_force: wp.array(dtype=wp.float64),
    normal: wp.array(dtype=wp.vec3d),
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    friction: wp.array(dtype=wp.float64),
    num_bodies: int,
    slots_per_problem: int,
    mask: wp.array(dtype=wp.int32),
    largest: wp.array(dtype=wp.float64),
    total: wp.array(dtype=wp.float64),
    capacity: wp.array(dtype=wp.float64),
):
    """Per problem: largest and summed friction-capacity error of the lagged normal forces,
    ``mu (|N - N_lag| + N |n - n_lag|)``, and the capacity ``sum mu N`` (outputs zeroed by the caller)."""
    b, j = wp.tid()
    if mask[b] == 0:
        return
    c = b * slots_per_problem + j
    mu = friction[b * num_bodies + j % num_bodies]
    n_force = normal_force[c]
    error = mu * (wp.abs(n_force - lag_normal_force[c]) + n_force * wp.length(normal[c] - lag_normal[c]))
    wp.atomic_max(largest, b, error)
    wp.atomic_add(total, b, error)
    wp.atomic_add(capacity, b, mu * n_force)


@wp.kernel
def friction_lag_residual_dots_kernel(
    normal_force: wp.array(dtype=wp.float64),
    lag_normal_force: wp.array(dtype=wp.float64),
    last_residual: wp.array(dtype=wp.float64),
    slots_per_problem: int,
    mask: wp.array(dtype=wp.int32),
    residual_dot_change: wp.array(dtype=wp.float64),
    change_dot_change: wp.array(dtype=wp.float64),
):
    """Aitken's dot products per problem: with the lag residual r = N - N_lag and its change
    dr = r - r_last, ``r_last . dr`` and ``dr . dr`` (outputs zeroed by the caller)."""
    b, j = wp.tid()
    if mask[b] == 0:
        return
    c = b * slots_per_problem + j
    r_last = last_residual[c]
    change = (normal_force[c] - lag_normal_force[c]) - r_last
    wp.atomic_add(residual_dot_change, b, r_last * change)
    wp.atomic_add(change_dot_change, b, change * change)


@wp.kernel
def friction_relag_kernel(
    normal_force: wp.array(dtype=wp.float64),
    normal: wp.array(dtype=wp.vec3d),
    lag_normal_force: wp.array(dtype=wp.float64),
    lag_normal: wp.array(dtype=wp.vec3d),
    last_residual: wp.array(dtype=wp.float64),
    slots_per_problem: int,
    mask: wp.array(dtype=wp.int32),
    accelerate: wp.array(dtype=wp.int32),
    relaxation: wp.array(dtype=wp.float64),
):
    """Re-lag the masked problems: N_lag <- N and n_lag <- n; where ``accelerate`` is set,
    N_lag <- max(N_lag + w (N - N_lag), 0) with the problem's Aitken factor w, and r_last <- N - N_lag."""
    b, j = wp.tid()
    if mask[b] == 0:
        return
    c = b * slots_per_problem + j
    n_force = normal_force[c]
    if accelerate[b] != 0:
        r = n_force - lag_normal_force[c]
        last_residual[c] = r
        lag_normal_force[c] = wp.max(lag_normal_force[c] + relaxation[b] * r, f64(0.0))
    else:
        lag_normal_force[c] = n_force
    lag_normal[c] = normal[c]


# ---------------------------------------------------------------- contact points (host)
def surface_contact_points(mesh, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The contact points of ``mesh``'s surface: the vertices of the uniform ``subdivisions``-subdivision
    (n) of every surface triangle, each point once.

    Returns (P, 3) mesh vertex indices, (P, 3) barycentric weights and (P,) lumped areas [m^2], points
    ordered as: the S surface vertices (``mesh.surface_vertices`` order, as ``(v, v, v; 1, 0, 0)``), then
    the n - 1 inner grid points of every surface edge ``(a, b, b; 1 - t, t, 0)``, then the (n - 1)(n - 2) / 2
    interior grid points of every face. The area of a point is its lumped share of the subdivided surface
    (a third of each sub-triangle of area A_f / n^2 it is a corner of): A_v / n^2 for a vertex (A_v the
    vertex's lumped area), (A_f + A_g) / n^2 for an edge point between faces f and g, 2 A_f / n^2 for an
    interior point; they sum to the surface area. n = 1: the surface vertices with their lumped areas.
    """
    n = int(subdivisions)
    if n < 1:
        raise ValueError(f"subdivisions must be >= 1, got {subdivisions!r}")
    surface = mesh.surface_vertices
    vertex = [np.repeat(surface[:, None], 3, axis=1)]
    weight = [np.tile([1.0, 0.0, 0.0], (len(surface), 1))]
    area = [mesh.vertex_areas[surface] / n**2]
    if n > 1:
        faces = mesh.surface_faces
        face_area = mesh.face_areas
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        edges, inverse = np.unique(edges, axis=0, return_inverse=True)
        edge_area = np.zeros(len(edges))
        np.add.at(edge_area, inverse.ravel(), np.tile(face_area, 3) / n**2)
        for t in range(1, n):
            vertex.append(edges[:, [0, 1, 1]])
            weight.append(np.tile([(n - t) / n, t / n, 0.0], (len(edges), 1)))
            area.append(edge_area)
        for i in range(1, n - 1):
            for j in range(1, n - i):
                vertex.append(faces)
                weight.append(np.tile([i / n, j / n, (n - i - j) / n], (len(faces), 1)))
                area.append(2.0 * face_area / n**2)
    return (
        np.concatenate(vertex).astype(np.int32),
        np.concatenate(weight),
        np.ascontiguousarray(np.concatenate(area), dtype=np.float64),
    )
