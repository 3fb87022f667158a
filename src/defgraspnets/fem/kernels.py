"""Small per-problem vector kernels used by the Newton solver (state packing, masked reductions)."""

from __future__ import annotations

import warp as wp

f64 = wp.float64


@wp.func
def max_abs_component(v: wp.vec3d) -> wp.float64:
    """max(|v_x|, |v_y|, |v_z|): the force scales of the convergence test are per component."""
    return wp.max(wp.abs(v[0]), wp.max(wp.abs(v[1]), wp.abs(v[2])))


@wp.kernel
def unpack_state_kernel(
    q: wp.array(dtype=wp.vec3d),
    rest_points: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    num_dofs: int,
    positions: wp.array(dtype=wp.vec3d),
    travel: wp.array(dtype=wp.float64),
):
    """positions = X + u and travel = q[dof rows].x from the packed unknowns q (B * R rows)."""
    b, r = wp.tid()
    R = num_vertices + num_dofs
    if r < num_vertices:
        positions[b * num_vertices + r] = rest_points[r] + q[b * R + r]
    else:
        travel[b * num_dofs + r - num_vertices] = q[b * R + r][0]


@wp.kernel
def trial_state_kernel(
    q: wp.array(dtype=wp.vec3d),
    dq: wp.array(dtype=wp.vec3d),
    step: wp.array(dtype=wp.float64),
    rows_per_problem: int,
    num_problems: int,
    out: wp.array(dtype=wp.vec3d),
):
    """out = q + step[p] dq for trial p = t B + b of problem b (launched over T B trials: T step lengths
    per problem side by side, trial-major; T = 1: one state per problem)."""
    p, r = wp.tid()
    i = (p % num_problems) * rows_per_problem + r
    out[p * rows_per_problem + r] = q[i] + step[p] * dq[i]


@wp.kernel
def predicted_state_kernel(
    q_ref: wp.array(dtype=wp.vec3d),
    increment: wp.array(dtype=wp.vec3d),
    ratio: wp.array(dtype=wp.float64),
    mask: wp.array(dtype=wp.int32),
    rows_per_problem: int,
    q: wp.array(dtype=wp.vec3d),
):
    """q = q_ref + ratio[b] increment for the rows of problems with mask[b] != 0 (the load-step
    predictor; the other problems' states are left as they are)."""
    b, r = wp.tid()
    if mask[b] != 0:
        i = b * rows_per_problem + r
        q[i] = q_ref[i] + ratio[b] * increment[i]


@wp.kernel
def masked_difference_kernel(
    a: wp.array(dtype=wp.vec3d),
    b: wp.array(dtype=wp.vec3d),
    mask: wp.array(dtype=wp.int32),
    rows_per_problem: int,
    out: wp.array(dtype=wp.vec3d),
):
    """out = a - b for the rows of problems with mask[b] != 0."""
    p, r = wp.tid()
    if mask[p] != 0:
        i = p * rows_per_problem + r
        out[i] = a[i] - b[i]


@wp.kernel
def copy_problems_kernel(
    src: wp.array(dtype=wp.vec3d),
    mask: wp.array(dtype=wp.int32),
    rows_per_problem: int,
    dst: wp.array(dtype=wp.vec3d),
):
    """dst = src for the rows of problems with mask[b] != 0."""
    b, r = wp.tid()
    if mask[b] != 0:
        i = b * rows_per_problem + r
        dst[i] = src[i]


@wp.kernel
def newton_rhs_kernel(
    gradient: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
    rows_per_problem: int,
    rhs: wp.array(dtype=wp.vec3d),
    residual: wp.array(dtype=wp.float64),
):
    """rhs = -gradient on free components of active problems (0 elsewhere); residual[b] = max |rhs|."""
    b, r = wp.tid()
    i = b * rows_per_problem + r
    fr = free[r]
    g = gradient[i]
    v = wp.vec3d(-g[0] * fr[0], -g[1] * fr[1], -g[2] * fr[2])
    if active[b] == 0:
        v = wp.vec3d()
    rhs[i] = v
    wp.atomic_max(residual, b, max_abs_component(v))


@wp.kernel
def step_stats_kernel(
    rhs: wp.array(dtype=wp.vec3d),
    dq: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    rows_per_problem: int,
    slope: wp.array(dtype=wp.float64),
    max_vertex_step: wp.array(dtype=wp.float64),
    max_dof_step: wp.array(dtype=wp.float64),
):
    """slope[b] = gradient . dq (= -rhs . dq); largest vertex and travel increments per problem."""
    b, r = wp.tid()
    i = b * rows_per_problem + r
    wp.atomic_add(slope, b, -wp.dot(rhs[i], dq[i]))
    if r < num_vertices:
        wp.atomic_max(max_vertex_step, b, wp.length(dq[i]))
    else:
        wp.atomic_max(max_dof_step, b, wp.abs(dq[i][0]))


@wp.kernel
def vertex_drift_kernel(
    q: wp.array(dtype=wp.vec3d),
    q_ref: wp.array(dtype=wp.vec3d),
    num_vertices: int,
    rows_per_problem: int,
    drift: wp.array(dtype=wp.float64),
):
    """drift[b] = max_i |u_i - u_ref_i| over the vertices of problem b."""
    b, v = wp.tid()
    i = b * rows_per_problem + v
    wp.atomic_max(drift, b, wp.length(q[i] - q_ref[i]))


@wp.kernel
def external_work_kernel(
    q: wp.array(dtype=wp.vec3d),
    nodal_force: wp.array(dtype=wp.vec3d),
    dof_force: wp.array(dtype=wp.float64),
    num_vertices: int,
    num_dofs: int,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] -= f_i . u_i (dead loads) and -= F_d travel_d (force-controlled dofs; 0 otherwise) for trial
    state p = t B + b of problem b (B = len(active); T = 1: the problems' states)."""
    p, r = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    R = num_vertices + num_dofs
    if r < num_vertices:
        wp.atomic_add(energy, p, -wp.dot(nodal_force[b * num_vertices + r], q[p * R + r]))
    else:
        d = r - num_vertices
        wp.atomic_add(energy, p, -dof_force[b * num_dofs + d] * q[p * R + r][0])


@wp.kernel
def external_gradient_kernel(
    nodal_force: wp.array(dtype=wp.vec3d),
    dof_force: wp.array(dtype=wp.float64),
    num_vertices: int,
    num_dofs: int,
    active: wp.array(dtype=wp.int32),
    gradient: wp.array(dtype=wp.vec3d),
    load_scale: wp.array(dtype=wp.float64),
):
    """gradient -= f_i (vertex rows) and -= F_d (dof rows); load_scale[b] = max external force component."""
    b, r = wp.tid()
    if active[b] == 0:
        return
    R = num_vertices + num_dofs
    if r < num_vertices:
        f = nodal_force[b * num_vertices + r]
        gradient[b * R + r] = gradient[b * R + r] - f
        wp.atomic_max(load_scale, b, max_abs_component(f))
    else:
        F = dof_force[b * num_dofs + r - num_vertices]
        gradient[b * R + r] = gradient[b * R + r] - wp.vec3d(F, f64(0.0), f64(0.0))
        wp.atomic_max(load_scale, b, wp.abs(F))


@wp.kernel
def stabilization_energy_kernel(
    q: wp.array(dtype=wp.vec3d),
    q_ref: wp.array(dtype=wp.vec3d),
    coefficient: wp.array(dtype=wp.float64),
    num_vertices: int,
    rows_per_problem: int,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += c_i |u_i - u_ref_i|^2 / 2: the increment stabilization spring of vertex i, for trial state
    p = t B + b of problem b (B = len(active))."""
    p, v = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    d = q[p * rows_per_problem + v] - q_ref[b * rows_per_problem + v]
    wp.atomic_add(energy, p, f64(0.5) * coefficient[b * num_vertices + v] * wp.dot(d, d))


@wp.kernel
def stabilization_gradient_kernel(
    q: wp.array(dtype=wp.vec3d),
    q_ref: wp.array(dtype=wp.vec3d),
    coefficient: wp.array(dtype=wp.float64),
    num_vertices: int,
    rows_per_problem: int,
    active: wp.array(dtype=wp.int32),
    gradient: wp.array(dtype=wp.vec3d),
    stabilization_force: wp.array(dtype=wp.float64),
):
    """gradient_i += c_i (u_i - u_ref_i); stabilization_force[b] = max_i |c_i (u_i - u_ref_i)|."""
    b, v = wp.tid()
    if active[b] == 0:
        return
    i = b * rows_per_problem + v
    f = coefficient[b * num_vertices + v] * (q[i] - q_ref[i])
    gradient[i] = gradient[i] + f
    wp.atomic_max(stabilization_force, b, wp.length(f))
