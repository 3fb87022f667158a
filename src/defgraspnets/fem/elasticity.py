"""Fixed co-rotated elasticity on linear tetrahedra: energy, forces, Hessian and stress (Warp kernels).

Per tet e with rest volume V_e and inverse rest shape matrix B = D_m^-1, the deformation gradient is
F = D_s B with D_s = [x1 - x0, x2 - x0, x3 - x0]. With the signed SVD F = U diag(sigma) V^T
(U, V rotations; sigma_3 < 0 for an inverted element) the energy density is

    Psi = mu * sum_i (sigma_i - 1)^2 + lambda/2 (J - 1)^2,          J = sigma_1 sigma_2 sigma_3,

its first Piola-Kirchhoff stress P = dPsi/dF = U diag(Psi_i) V^T with
Psi_i = 2 mu (sigma_i - 1) + lambda (J - 1) J / sigma_i, and the Cauchy stress is P F^T / J.

The vertex forces follow from dF_ij/dx_a,m = delta_im beta_a,j, with beta_a the rows of B for
a = 1..3 and beta_0 = -(beta_1 + beta_2 + beta_3): grad_a = V_e P beta_a.

The Hessian d2Psi/dF2 of an isotropic energy has a closed-form eigensystem (Smith et al. 2019,
"Analytic eigensystems for isotropic distortion energies"): three scaling modes U diag(z_k) V^T from
the 3x3 matrix A_ij = d2Psi/dsigma_i dsigma_j, and for each pair (i, j), with k the third index,
a twist mode U (e_i e_j^T - e_j e_i^T) V^T / sqrt2 with eigenvalue
(Psi_i + Psi_j)/(sigma_i + sigma_j) = 2 mu (1 - 2/(sigma_i + sigma_j)) + lambda (J - 1) sigma_k and a
flip mode U (e_i e_j^T + e_j e_i^T) V^T / sqrt2 with eigenvalue
(Psi_i - Psi_j)/(sigma_i - sigma_j) = 2 mu - lambda (J - 1) sigma_k. Replacing the nine eigenvalues by
their absolute values gives a positive semi-definite Hessian (the "abs" projection of Chen et al. 2024,
"Trust-region eigenvalue filtering for projected Newton", which converges faster than clamping at zero),
so every Newton direction descends. Close to an equilibrium the projection costs Newton its quadratic
convergence wherever elements are compressed (the twist eigenvalue 2 mu (1 - 2 / (sigma_i + sigma_j)) < 0:
a dimpled membrane, the object under a finger), so the solver may ask for the *exact* Hessian (signed
eigenvalues, ``exact[b] = 1``) once its steps are trusted; see :class:`~defgraspnets.fem.QuasiStaticSolver`.
Element blocks are K_ac = V_e sum_k s_k |lambda_k| (Q_k beta_a)(Q_k beta_c)^T, s_k = sign(lambda_k) or 1.
"""

from __future__ import annotations

import warp as wp

from .kernels import max_abs_component

f64 = wp.float64


@wp.func
def tet_deformation_gradient(
    positions: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    offset: int,
    e: int,
    rest_inverse: wp.mat33d,
) -> wp.mat33d:
    """F = [x1-x0, x2-x0, x3-x0] D_m^-1 of tet e, its vertices read at positions[offset + vertex]."""
    x0 = positions[offset + tets[e, 0]]
    ds = wp.matrix_from_cols(
        positions[offset + tets[e, 1]] - x0,
        positions[offset + tets[e, 2]] - x0,
        positions[offset + tets[e, 3]] - x0,
    )
    return ds * rest_inverse


@wp.func
def principal_stretches(F: wp.mat33d):
    """SVD F = U diag(s) V^T (U, V rotations; s may have a negative last entry when det F < 0)."""
    U = wp.mat33d()
    s = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, s, V)
    return U, s, V


@wp.func
def shape_gradient(rest_inverse: wp.mat33d, a: int) -> wp.vec3d:
    """beta_a: d(F_ij)/d(x_a,i) = beta_a,j for local vertex a of the tet."""
    if a == 0:
        return -(rest_inverse[0] + rest_inverse[1] + rest_inverse[2])
    return rest_inverse[a - 1]


@wp.func
def corotated_energy_density(sigma: wp.vec3d, mu: f64, lam: f64) -> f64:
    """Psi = mu sum (sigma_i - 1)^2 + lambda/2 (J - 1)^2 [J/m^3]."""
    one = f64(1.0)
    j = sigma[0] * sigma[1] * sigma[2]
    d = sigma - wp.vec3d(one, one, one)
    return mu * wp.dot(d, d) + f64(0.5) * lam * (j - one) * (j - one)


@wp.func
def corotated_principal_stress(sigma: wp.vec3d, mu: f64, lam: f64) -> wp.vec3d:
    """Psi_i = dPsi/dsigma_i = 2 mu (sigma_i - 1) + lambda (J - 1) prod_{k != i} sigma_k [Pa]."""
    one = f64(1.0)
    two = f64(2.0)
    jm1 = sigma[0] * sigma[1] * sigma[2] - one
    return wp.vec3d(
        two * mu * (sigma[0] - one) + lam * jm1 * sigma[1] * sigma[2],
        two * mu * (sigma[1] - one) + lam * jm1 * sigma[0] * sigma[2],
        two * mu * (sigma[2] - one) + lam * jm1 * sigma[0] * sigma[1],
    )


NEO_HOOKEAN = 1  # constitutive model codes of the kernels (see Material.model)


@wp.func
def neohookean_energy_density(sigma: wp.vec3d, mu: f64, lam: f64) -> f64:
    """Psi = mu/2 (I1 - 3) - mu log J + lambda/2 (log J)^2 [J/m^3], +inf for J <= 0 (inverted)."""
    j = sigma[0] * sigma[1] * sigma[2]
    if j <= f64(0.0):
        return f64(wp.inf)
    lj = wp.log(j)
    return f64(0.5) * mu * (wp.dot(sigma, sigma) - f64(3.0)) - mu * lj + f64(0.5) * lam * lj * lj


@wp.func
def neohookean_principal_stress(sigma: wp.vec3d, mu: f64, lam: f64) -> wp.vec3d:
    """Psi_i = mu sigma_i + (lambda log J - mu) / sigma_i [Pa] (J clamped to > 0 for inverted input)."""
    j = wp.max(sigma[0] * sigma[1] * sigma[2], f64(1e-300))
    c = lam * wp.log(j) - mu
    return wp.vec3d(
        mu * sigma[0] + c / sigma[0],
        mu * sigma[1] + c / sigma[1],
        mu * sigma[2] + c / sigma[2],
    )


@wp.func
def energy_density(model: int, sigma: wp.vec3d, mu: f64, lam: f64) -> f64:
    if model == NEO_HOOKEAN:
        return neohookean_energy_density(sigma, mu, lam)
    return corotated_energy_density(sigma, mu, lam)


@wp.func
def principal_stress(model: int, sigma: wp.vec3d, mu: f64, lam: f64) -> wp.vec3d:
    if model == NEO_HOOKEAN:
        return neohookean_principal_stress(sigma, mu, lam)
    return corotated_principal_stress(sigma, mu, lam)


@wp.func
def stretch_hessian(model: int, s: wp.vec3d, mu: f64, lam: f64) -> wp.mat33d:
    """A_ij = d2Psi / dsigma_i dsigma_j.

    Co-rotated: A_ii = 2 mu + lambda c_i^2, A_ij = lambda (c_i c_j + (J - 1) sigma_k), c_i = J / sigma_i.
    Neo-Hookean: A_ii = mu + (mu + lambda (1 - log J)) / sigma_i^2, A_ij = lambda / (sigma_i sigma_j)."""
    one = f64(1.0)
    two = f64(2.0)
    if model == NEO_HOOKEAN:
        lj = wp.log(wp.max(s[0] * s[1] * s[2], f64(1e-300)))
        d = mu + lam * (one - lj)
        return wp.mat33d(
            mu + d / (s[0] * s[0]),
            lam / (s[0] * s[1]),
            lam / (s[0] * s[2]),
            lam / (s[1] * s[0]),
            mu + d / (s[1] * s[1]),
            lam / (s[1] * s[2]),
            lam / (s[2] * s[0]),
            lam / (s[2] * s[1]),
            mu + d / (s[2] * s[2]),
        )
    jm1 = s[0] * s[1] * s[2] - one
    c = wp.vec3d(s[1] * s[2], s[0] * s[2], s[0] * s[1])
    return wp.mat33d(
        two * mu + lam * c[0] * c[0],
        lam * (c[0] * c[1] + jm1 * s[2]),
        lam * (c[0] * c[2] + jm1 * s[1]),
        lam * (c[1] * c[0] + jm1 * s[2]),
        two * mu + lam * c[1] * c[1],
        lam * (c[1] * c[2] + jm1 * s[0]),
        lam * (c[2] * c[0] + jm1 * s[1]),
        lam * (c[2] * c[1] + jm1 * s[0]),
        two * mu + lam * c[2] * c[2],
    )


@wp.func
def pair_eigenvalues(model: int, s: wp.vec3d, i: int, j: int, k: int, mu: f64, lam: f64) -> wp.vec2d:
    """(twist, flip) eigenvalues of the pair (i, j), k the third index: (Psi_i + Psi_j) / (sigma_i + sigma_j)
    and (Psi_i - Psi_j) / (sigma_i - sigma_j) in closed form (no division by sigma_i - sigma_j).

    Co-rotated: 2 mu (1 - 2 / (sigma_i + sigma_j)) + lambda (J - 1) sigma_k and 2 mu - lambda (J - 1) sigma_k.
    Neo-Hookean: mu + c and mu - c, c = (lambda log J - mu) / (sigma_i sigma_j).
    """
    one = f64(1.0)
    two = f64(2.0)
    if model == NEO_HOOKEAN:
        c = (lam * wp.log(wp.max(s[0] * s[1] * s[2], f64(1e-300))) - mu) / (s[i] * s[j])
        return wp.vec2d(mu + c, mu - c)
    jm1 = s[0] * s[1] * s[2] - one
    denom = s[i] + s[j]
    if wp.abs(denom) < f64(1e-6):
        denom = wp.where(denom < f64(0.0), f64(-1e-6), f64(1e-6))
    return wp.vec2d(two * mu * (one - two / denom) + lam * jm1 * s[k], two * mu - lam * jm1 * s[k])


@wp.func
def von_mises(s: wp.mat33d) -> f64:
    """Von Mises equivalent stress sqrt(3/2 s_dev : s_dev) of a symmetric stress tensor [Pa]."""
    d01 = s[0, 0] - s[1, 1]
    d12 = s[1, 1] - s[2, 2]
    d20 = s[2, 2] - s[0, 0]
    shear = s[0, 1] * s[0, 1] + s[1, 2] * s[1, 2] + s[0, 2] * s[0, 2]
    return wp.sqrt(f64(0.5) * (d01 * d01 + d12 * d12 + d20 * d20) + f64(3.0) * shear)


@wp.func
def pair_mode(U: wp.mat33d, V: wp.mat33d, i: int, j: int, sign: f64) -> wp.mat33d:
    """U (e_i e_j^T + sign e_j e_i^T) V^T / sqrt(2): flip (sign = +1) or twist (sign = -1) mode."""
    m = wp.mat33d()
    c = f64(0.7071067811865476)
    m[i, j] = c
    m[j, i] = sign * c
    return U * m * wp.transpose(V)


mat912d = wp.types.matrix(shape=(9, 12), dtype=wp.float64)


@wp.func
def set_mode_row(W: mat912d, k: int, Q: wp.mat33d, eig: f64, B: wp.mat33d, volume: f64) -> mat912d:
    """Row k of W: sqrt(|eig| V_e) [Q beta_0, Q beta_1, Q beta_2, Q beta_3]."""
    c = wp.sqrt(wp.abs(eig) * volume)
    for a in range(4):
        w = c * (Q * shape_gradient(B, a))
        W[k, 3 * a + 0] = w[0]
        W[k, 3 * a + 1] = w[1]
        W[k, 3 * a + 2] = w[2]
    return W


@wp.kernel
def elastic_energy_kernel(
    positions: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    rest_inverse: wp.array(dtype=wp.mat33d),
    rest_volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    model: wp.array(dtype=wp.int32),
    num_vertices: int,
    active: wp.array(dtype=wp.int32),
    energy: wp.array(dtype=wp.float64),
):
    """energy[p] += V_e Psi(F_e) for every (trial state p = t B + b of problem b, tet e) (+inf where a
    Neo-Hookean tet is inverted); B = len(active), T = 1: the problems' states."""
    p, e = wp.tid()
    b = p % active.shape[0]
    if active[b] == 0:
        return
    o = p * num_vertices
    F = tet_deformation_gradient(positions, tets, o, e, rest_inverse[e])
    U, s, V = principal_stretches(F)
    wp.atomic_add(energy, p, rest_volume[e] * energy_density(model[b], s, mu[b], lam[b]))


@wp.kernel
def elastic_gradient_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    rest_inverse: wp.array(dtype=wp.mat33d),
    rest_volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    model: wp.array(dtype=wp.int32),
    tet_blocks: wp.array2d(dtype=wp.int32),
    num_vertices: int,
    rows_per_problem: int,
    blocks_per_problem: int,
    active: wp.array(dtype=wp.int32),
    exact: wp.array(dtype=wp.int32),
    gradient: wp.array(dtype=wp.vec3d),
    force_scale: wp.array(dtype=wp.float64),
    hessian: wp.array(dtype=wp.mat33d),
):
    """Add each tet's energy gradient to ``gradient`` (rows b * rows_per_problem + v) and its 12x12 Hessian
    to ``hessian``: PSD-projected (abs eigenvalues), or exact where ``exact[b] == 1``.

    ``tet_blocks[e, 4a + c]`` is the BSR block
    index (within one problem) of vertex pair (a, c). ``force_scale[b]`` tracks max |elastic force|.
    """
    b, e = wp.tid()
    if active[b] == 0:
        return
    o = b * num_vertices
    B = rest_inverse[e]
    vol = rest_volume[e]
    F = tet_deformation_gradient(positions, tets, o, e, B)
    U, s, V = principal_stretches(F)
    m = mu[b]
    l = lam[b]
    mat = model[b]
    one = f64(1.0)

    # forces: grad_a = V_e P beta_a
    P = U * wp.diag(principal_stress(mat, s, m, l)) * wp.transpose(V)
    for a in range(4):
        g = vol * (P * shape_gradient(B, a))
        wp.atomic_add(gradient, b * rows_per_problem + tets[e, a], g)
        wp.atomic_max(force_scale, b, max_abs_component(g))

    # scaling modes: eigenvectors z_k of A = d2Psi/dsigma2 give U diag(z_k) V^T
    A = stretch_hessian(mat, s, m, l)
    Z = wp.mat33d()
    d = wp.vec3d()
    wp.eig3(A, Z, d)
    W = mat912d()
    sign = wp.vector(length=9, dtype=wp.float64)
    for k in range(9):
        sign[k] = one
    signed = exact[b] == 1
    for k in range(3):
        z = wp.vec3d(Z[0, k], Z[1, k], Z[2, k])
        W = set_mode_row(W, k, U * wp.diag(z) * wp.transpose(V), d[k], B, vol)
        if signed and d[k] < f64(0.0):
            sign[k] = -one

    # twist and flip modes of the pairs (0,1), (0,2), (1,2) with third index k = 2, 1, 0
    for p in range(3):
        i = 0
        jj = 1
        k3 = 2
        if p == 1:
            jj = 2
            k3 = 1
        elif p == 2:
            i = 1
            jj = 2
            k3 = 0
        tf = pair_eigenvalues(mat, s, i, jj, k3, m, l)
        twist = tf[0]
        flip = tf[1]
        W = set_mode_row(W, 3 + 2 * p, pair_mode(U, V, i, jj, f64(-1.0)), twist, B, vol)
        W = set_mode_row(W, 4 + 2 * p, pair_mode(U, V, i, jj, f64(1.0)), flip, B, vol)
        if signed and twist < f64(0.0):
            sign[3 + 2 * p] = -one
        if signed and flip < f64(0.0):
            sign[4 + 2 * p] = -one

    # K_ac = sum_k W[k, 3a:3a+3] W[k, 3c:3c+3]^T
    ob = b * blocks_per_problem
    for a in range(4):
        for cc in range(4):
            K = wp.mat33d()
            for k in range(9):
                wa = wp.vec3d(W[k, 3 * a], W[k, 3 * a + 1], W[k, 3 * a + 2])
                wc = wp.vec3d(W[k, 3 * cc], W[k, 3 * cc + 1], W[k, 3 * cc + 2])
                K += sign[k] * wp.outer(wa, wc)
            wp.atomic_add(hessian, ob + tet_blocks[e, 4 * a + cc], K)


@wp.kernel
def tet_stress_kernel(
    positions: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    rest_inverse: wp.array(dtype=wp.mat33d),
    rest_volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    model: wp.array(dtype=wp.int32),
    num_vertices: int,
    problems: wp.array(dtype=wp.int32),
    stress: wp.array(dtype=wp.mat33d),
    energy: wp.array(dtype=wp.float64),
    inverted: wp.array(dtype=wp.int32),
):
    """Per (listed problem i, tet): Cauchy stress, strain energy V_e Psi (summed per problem), inverted
    flag, of problem b = problems[i] (outputs indexed by i: only the listed problems are computed)."""
    i, e = wp.tid()
    b = problems[i]
    o = b * num_vertices
    F = tet_deformation_gradient(positions, tets, o, e, rest_inverse[e])
    U, s, V = principal_stretches(F)
    j = s[0] * s[1] * s[2]
    P = U * wp.diag(principal_stress(model[b], s, mu[b], lam[b])) * wp.transpose(V)
    sig = P * wp.transpose(F) / j
    stress[i * tets.shape[0] + e] = f64(0.5) * (sig + wp.transpose(sig))
    wp.atomic_add(energy, i, rest_volume[e] * energy_density(model[b], s, mu[b], lam[b]))
    if j <= f64(0.0):
        wp.atomic_add(inverted, i, 1)


@wp.kernel
def vertex_von_mises_kernel(
    tet_stress: wp.array(dtype=wp.mat33d),
    tets: wp.array2d(dtype=wp.int32),
    rest_volume: wp.array(dtype=wp.float64),
    vertex_weight: wp.array(dtype=wp.float64),
    num_vertices: int,
    vertex_stress: wp.array(dtype=wp.mat33d),
):
    """vertex_stress[v] += V_e sigma_e / sum(V_adjacent): the volume-weighted mean of adjacent tets."""
    b, e = wp.tid()
    sig = tet_stress[b * tets.shape[0] + e]
    for a in range(4):
        v = tets[e, a]
        wp.atomic_add(vertex_stress, b * num_vertices + v, sig * (rest_volume[e] / vertex_weight[v]))


@wp.kernel
def von_mises_kernel(stress: wp.array(dtype=wp.mat33d), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = von_mises(stress[i])
