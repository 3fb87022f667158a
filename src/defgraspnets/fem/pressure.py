"""Gas pressure on a set of surface triangles: a conservative follower load (Warp kernels).

A gas at gauge pressure p (absolute minus ambient) fills a cavity bounded by oriented surface
triangles of the object (``faces``, each oriented with the *solid's* outward normal n, i.e. pointing
into the gas) and by planar walls of a rigid container that pass through a reference point c (the
clamped rim disk of a membrane, or the symmetry planes of a symmetric model). Its force on each
triangle of the deformed configuration is the follower load

    f_face = -p A n,        lumped 1/3 to each of its three vertices,

which is conservative: it is minus the gradient of -G(V), with V the cavity volume by the
divergence theorem,

    V(x) = -(1/6) sum_faces (a - c) . ((b - c) x (d - c))        (faces (a, b, d)),

exact as long as every closing wall is planar and contains c (its own cone from c has zero volume;
the walls' boundary vertices must stay in their planes: clamped or symmetry-constrained).

Gas law, per problem: p(V) = p0 + C / (V + V_h), with V_h the container's gas volume outside the
mesh (e.g. a rigid housing) and

    p0 = p, C = 0                 fixed gauge pressure (cavity open to a pressure regulator),
    p0 = -P_atm, C = P V          closed cavity of isothermal ideal gas, P (V + V_h) = const (Boyle),

whose potential is the (Gibbs) work of the gas, G(V) = int_V0^V p dV'
= p0 (V - V0) + C log((V + V_h) / (V0 + V_h)), V0 the rest volume. The potential added to the
solver's incremental potential is Pi_gas = -G(V), with

    grad Pi_gas = -p(V) grad V,
    hess Pi_gas = -p(V) d2V/dx2 + C / (V + V_h)^2  grad V grad V^T.

The first Hessian term is exactly symmetric: per face, with T = (a - c) . ((b - c) x (d - c)),
d2T/da db = -[d - c]x (and cyclically), [w]x the cross-product matrix, so its blocks are skew and
(a, b) is the transpose of (b, a). It is assembled into the sparse Hessian (face edges are tet edges).
The second term is a dense, positive semi-definite rank-one update (the gas stiffness of a closed
cavity, -p'(V) = C / (V + V_h)^2); the solver applies it matrix-free by the Sherman-Morrison formula
(two solves with the sparse part per Newton step), see :meth:`QuasiStaticSolver._gas_rank_one`.

grad V is evaluated in the lumped form dV/dx_v = -(1/3) sum_{faces at v} A n, which equals the
derivative of the formula above at every vertex whose faces close around it (all free vertices of a
clamped cavity), and in the in-plane components of vertices sliding on a closing plane; at clamped
vertices it gives the physical lumped load, so reaction forces include the true gas force on the
clamp (its resultant over an open cavity is p times the vector area of the closing walls).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import max_abs_component

__all__ = ["PressureLoad", "PressureSurface", "STANDARD_ATMOSPHERE"]

f64 = wp.float64

#: ISO 2533 sea-level atmospheric pressure [Pa], the ambient pressure of :meth:`PressureLoad.isothermal`.
STANDARD_ATMOSPHERE = 101_325.0


# --------------------------------------------------------------------------- host-side descriptions
@dataclass(frozen=True, eq=False)
class PressureSurface:
    """The pressurized boundary of the object: which triangles the gas touches, and how V is closed.

    Args:
        faces: (F, 3) vertex indices of the wetted triangles, oriented with the solid's outward normal
            (pointing into the gas), e.g. a subset of ``TetMesh.surface_faces``.
        reference_point: c [m], a point on every planar wall that closes the cavity (rest frame).
        external_volume: V_h [m^3] >= 0, gas volume of the rigid container outside the mesh (enters only
            the isothermal law).
    """

    faces: np.ndarray
    reference_point: object = (0.0, 0.0, 0.0)
    external_volume: float = 0.0

    def __post_init__(self):
        f = np.asarray(self.faces)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(
                f"PressureSurface.faces must be an integer (F >= 1, 3) array, got {f.dtype} {f.shape}"
            )
        c = np.asarray(self.reference_point, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(
                f"PressureSurface.reference_point must be a finite (3,) point, got {self.reference_point!r}"
            )
        vh = float(self.external_volume)
        if not np.isfinite(vh) or vh < 0:
            raise ValueError(
                f"PressureSurface.external_volume must be finite and >= 0 m^3, got {self.external_volume!r}"
            )
        object.__setattr__(self, "faces", np.ascontiguousarray(f, dtype=np.int32))
        object.__setattr__(self, "reference_point", c)
        object.__setattr__(self, "external_volume", vh)

    def volume(self, points: np.ndarray) -> float:
        """V = -(1/6) sum (a - c) . ((b - c) x (d - c)) [m^3] for vertex positions ``points`` (NumPy)."""
        p = np.asarray(points, dtype=np.float64) - self.reference_point
        a, b, d = (p[self.faces[:, k]] for k in range(3))
        return float(-np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0)


def _per_problem(value, batch_size: int, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(batch_size, float(v))
    if v.shape != (batch_size,):
        raise ValueError(f"PressureLoad.{name} must be a scalar or have shape ({batch_size},), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"PressureLoad.{name} must be finite, got {value!r}")
    return np.array(v)


@dataclass(frozen=True)
class PressureLoad:
    """Gas law p(V) = p0 + C / (V + V_h) of the cavity, per problem (scalars or (B,) arrays).

    Args:
        gauge_pressure: p0 [Pa], the constant part of the gauge pressure.
        pv: C = P (V + V_h) [J] >= 0, the isothermal gas constant (0: fixed pressure).

    Use :meth:`fixed` (pressure regulated, or the cavity open to the air: p = 0) or :meth:`isothermal`
    (closed cavity, Boyle's law).
    """

    gauge_pressure: object = 0.0
    pv: object = 0.0

    @classmethod
    def fixed(cls, gauge_pressure) -> PressureLoad:
        """Constant gauge pressure p [Pa] (scalar or (B,))."""
        return cls(gauge_pressure=gauge_pressure, pv=0.0)

    @classmethod
    def isothermal(cls, pv, ambient_pressure: float = STANDARD_ATMOSPHERE) -> PressureLoad:
        """Closed cavity of ideal gas at constant temperature: absolute P = pv / (V + V_h), gauge
        p = pv / (V + V_h) - P_ambient. ``pv`` [J] scalar or (B,)."""
        if not (np.isfinite(ambient_pressure) and ambient_pressure >= 0):
            raise ValueError(f"ambient_pressure must be finite and >= 0 Pa, got {ambient_pressure!r}")
        return cls(gauge_pressure=-float(ambient_pressure), pv=pv)

    def arrays(self, batch_size: int) -> np.ndarray:
        """(B, 2) columns p0 [Pa] and C [J]."""
        p0 = _per_problem(self.gauge_pressure, batch_size, "gauge_pressure")
        c = _per_problem(self.pv, batch_size, "pv")
        if np.any(c < 0):
            raise ValueError(f"PressureLoad.pv must be >= 0, got {self.pv!r}")
        return np.stack([p0, c], axis=1)


def gas_pressure(law: np.ndarray, volume: np.ndarray, external_volume: float) -> np.ndarray:
    """p(V) = p0 + C / (V + V_h) [Pa] per problem (``law``: (B, 2) columns p0, C)."""
    return law[:, 0] + law[:, 1] / (volume + external_volume)


def gas_work(
    law: np.ndarray, volume_change: np.ndarray, rest_volume: float, external_volume: float
) -> np.ndarray:
    """G = int_V0^V p dV = p0 (V - V0) + C log(1 + (V - V0) / (V0 + V_h)) [J] per problem."""
    return law[:, 0] * volume_change + law[:, 1] * np.log1p(volume_change / (rest_volume + external_volume))


def gas_stiffness(law: np.ndarray, volume: np.ndarray, external_volume: float) -> np.ndarray:
    """-dp/dV = C / (V + V_h)^2 [Pa/m^3] per problem (the rank-one Hessian coefficient)."""
    return law[:, 1] / (volume + external_volume) ** 2


# --------------------------------------------------------------------------- Warp functions
@wp.func
def face_vector_area(a: wp.vec3d, b: wp.vec3d, d: wp.vec3d) -> wp.vec3d:
    """A n = (1/2) (b - a) x (d - a): area times unit normal of face (a, b, d) [m^2]."""
    return f64(0.5) * wp.cross(b - a, d - a)


@wp.func
def cross_matrix(w: wp.vec3d) -> wp.mat33d:
    """[w]x, the matrix of v -> w x v."""
    z = f64(0.0)
    return wp.mat33d(z, -w[2], w[1], w[2], z, -w[0], -w[1], w[0], z)


# --------------------------------------------------------------------------- kernels
@wp.func
def face_cone_volume_change(
    a: wp.vec3d, b: wp.vec3d, d: wp.vec3d, ua: wp.vec3d, ub: wp.vec3d, ud: wp.vec3d
) -> f64:
    """Cone volume of face (a + ua, b + ub, d + ud) minus that of (a, b, d), both from c (a, b, d given
    relative to c), expanded in the displacements so no large rest volumes cancel [m^3]:
    det[a+ua, b+ub, d+ud] - det[a, b, d] = sum of the seven determinants with at least one u column."""
    t = wp.dot(ua, wp.cross(b, d)) + wp.dot(a, wp.cross(ub, d)) + wp.dot(a, wp.cross(b, ud))
    t += wp.dot(ua, wp.cross(ub, d)) + wp.dot(ua, wp.cross(b, ud)) + wp.dot(a, wp.cross(ub, ud))
    t += wp.dot(ua, wp.cross(ub, ud))
    return -t / f64(6.0)


@wp.kernel
def cavity_volume_change_kernel(
    positions: wp.array(dtype=wp.vec3d),
    rest_points: wp.array(dtype=wp.vec3d),
    faces: wp.array2d(dtype=wp.int32),
    reference_point: wp.vec3d,
    num_vertices: int,
    volume_change: wp.array(dtype=wp.float64),
):
    """volume_change[b] += V_f(x) - V_f(X) of face f: the cavity's volume change V - V0 of problem b.

    (Computing V - V0 directly keeps the gas work p0 (V - V0) free of the round-off of p0 V, which
    would otherwise swamp the energy decrease the line search tests near convergence.)"""
    b, f = wp.tid()
    o = b * num_vertices
    i0 = faces[f, 0]
    i1 = faces[f, 1]
    i2 = faces[f, 2]
    a = rest_points[i0] - reference_point
    bb = rest_points[i1] - reference_point
    d = rest_points[i2] - reference_point
    ua = positions[o + i0] - rest_points[i0]
    ub = positions[o + i1] - rest_points[i1]
    ud = positions[o + i2] - rest_points[i2]
    wp.atomic_add(volume_change, b, face_cone_volume_change(a, bb, d, ua, ub, ud))


@wp.kernel
def volume_gradient_kernel(
    positions: wp.array(dtype=wp.vec3d),
    faces: wp.array2d(dtype=wp.int32),
    num_vertices: int,
    rows_per_problem: int,
    volume_gradient: wp.array(dtype=wp.vec3d),
):
    """dV/dx_v += -(1/3) A n for each vertex v of face f (lumped; rows b * rows_per_problem + v)."""
    b, f = wp.tid()
    o = b * num_vertices
    a = positions[o + faces[f, 0]]
    bb = positions[o + faces[f, 1]]
    d = positions[o + faces[f, 2]]
    g = -face_vector_area(a, bb, d) / f64(3.0)
    for k in range(3):
        wp.atomic_add(volume_gradient, b * rows_per_problem + faces[f, k], g)


@wp.kernel
def pressure_gradient_kernel(
    volume_gradient: wp.array(dtype=wp.vec3d),
    pressure: wp.array(dtype=wp.float64),
    rows_per_problem: int,
    active: wp.array(dtype=wp.int32),
    gradient: wp.array(dtype=wp.vec3d),
    load_scale: wp.array(dtype=wp.float64),
):
    """gradient -= p dV/dx (the gas force p dV/dx on each vertex); load_scale[b] = max |force component|."""
    b, v = wp.tid()
    if active[b] == 0:
        return
    i = b * rows_per_problem + v
    f = pressure[b] * volume_gradient[i]
    gradient[i] = gradient[i] - f
    wp.atomic_max(load_scale, b, max_abs_component(f))


@wp.kernel
def pressure_hessian_kernel(
    positions: wp.array(dtype=wp.vec3d),
    faces: wp.array2d(dtype=wp.int32),
    reference_point: wp.vec3d,
    pressure: wp.array(dtype=wp.float64),
    face_blocks: wp.array2d(dtype=wp.int32),
    num_vertices: int,
    blocks_per_problem: int,
    active: wp.array(dtype=wp.int32),
    hessian: wp.array(dtype=wp.mat33d),
):
    """Add -p d2V_f/dx2 of face f: block (a, b) = -(p/6) [d - c]x, (b, a) its transpose, cyclically.

    ``face_blocks[f, 3 i + j]`` is the BSR block of (faces[f, i], faces[f, j]) within one problem."""
    b, f = wp.tid()
    if active[b] == 0:
        return
    o = b * num_vertices
    p = pressure[b]
    ob = b * blocks_per_problem
    for i in range(3):
        j = (i + 1) % 3
        k = (i + 2) % 3
        opposite = positions[o + faces[f, k]] - reference_point
        K = (-p / f64(6.0)) * cross_matrix(opposite)
        wp.atomic_add(hessian, ob + face_blocks[f, 3 * i + j], K)
        wp.atomic_add(hessian, ob + face_blocks[f, 3 * j + i], wp.transpose(K))
