"""Procedural primitive objects: watertight, edge-rounded triangle surfaces in metres.

DefGraspNets (thesis §7.4) trains on 60 primitives "grouped into geometric categories (e.g. cuboids,
cylinders, ellipsoids, annuli)" whose "instances within each category have different dimensions and
aspect ratios"; DefGraspSim (§6.3) smooths sharp edges "to avoid stress singularities". This module
builds such shapes directly as closed surfaces, with every convex edge replaced by a circular fillet:

- **cuboid**: a box of side lengths ``A = (A1, A2, A3)`` with edges rounded by radius ``r``, i.e. the
  Minkowski sum of the inner box ``A - 2r`` and a ball of radius ``r``. Steiner's formula gives
  ``V = A1'A2'A3' + 2r(A1'A2' + A2'A3' + A3'A1') + pi r^2 (A1' + A2' + A3') + 4/3 pi r^3``, ``Ai' = Ai - 2r``.
- **cylinder, cone, capsule, annulus, torus**: surfaces of revolution about z of a planar profile
  ``(rho(s), z(s))`` made of straight segments and circular arcs (the fillets). Their exact volume
  follows from Green's theorem applied to Pappus' integral ``V = int 2 pi rho dA = pi * oint rho^2 dz``
  (profile traversed counter-clockwise in the (rho, z) half-plane), evaluated in closed form for
  segments and arcs by :func:`profile_volume`.
- **ellipsoid**: an icosphere scaled by the semi-axes ``(a, b, c)``; ``V = 4/3 pi a b c``.

Conventions: object frame with the volume centroid at the origin, symmetry axis (if any) along z,
SI units (m). Tessellation aims at a uniform edge length ``edge_length`` (default 4 mm) with at
least a few segments on every fillet; the named instances in :data:`PRIMITIVES` are 2-12 cm objects
that a Franka hand (80 mm maximum opening) can grasp across at least one axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from .surface import ObjectMeshError, check_surface

__all__ = [
    "CATEGORIES",
    "PRIMITIVES",
    "PrimitiveSpec",
    "annulus",
    "build_primitive",
    "capsule",
    "cone",
    "cuboid",
    "cylinder",
    "ellipsoid",
    "profile_volume",
    "revolve",
    "rounded_box_volume",
    "rounded_profile",
    "torus",
]

CATEGORIES = ("cuboid", "cylinder", "ellipsoid", "annulus", "capsule", "cone", "torus")
DEFAULT_EDGE_LENGTH = 0.004  # [m] target surface edge length
DEFAULT_CHORD_ERROR = 5e-5  # [m] largest distance between a curved surface and its chords


def _arc_segments(
    radius: float, angle: float, edge_length: float, chord_error: float, minimum: int = 2
) -> int:
    """Segments for an arc: chord length <= edge_length and sagitta r (1 - cos(dtheta/2)) <= chord_error."""
    by_length = angle * radius / edge_length
    by_error = angle / (2 * math.acos(max(-1.0, 1 - chord_error / radius))) if radius > chord_error else 1
    return max(minimum, math.ceil(by_length), math.ceil(by_error))


# ----------------------------------------------------------------------------------------- profiles
@dataclass(frozen=True)
class _Arc:
    """Circular arc of a profile: centre (rho, z), radius, start and end angle [rad] (counter-clockwise)."""

    center: tuple[float, float]
    radius: float
    start: float
    end: float

    def points(self, n: int) -> np.ndarray:
        t = np.linspace(self.start, self.end, n + 1)
        return np.stack(
            [self.center[0] + self.radius * np.cos(t), self.center[1] + self.radius * np.sin(t)], 1
        )

    @property
    def length(self) -> float:
        return abs(self.end - self.start) * self.radius

    def integral_rho2_dz(self) -> float:
        """Exact ``int rho^2 dz`` along the arc: rho = c + r cos t, dz = r cos t dt."""
        c, r = self.center[0], self.radius

        def antiderivative(t):
            s = math.sin(t)
            return r * (c * c * s + 2 * c * r * (t / 2 + math.sin(2 * t) / 4) + r * r * (s - s**3 / 3))

        return antiderivative(self.end) - antiderivative(self.start)


@dataclass(frozen=True)
class _Segment:
    a: tuple[float, float]
    b: tuple[float, float]

    def points(self, n: int) -> np.ndarray:
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        return (1 - t) * np.asarray(self.a) + t * np.asarray(self.b)

    @property
    def length(self) -> float:
        return math.dist(self.a, self.b)

    def integral_rho2_dz(self) -> float:
        (r0, z0), (r1, z1) = self.a, self.b
        return (z1 - z0) * (r0 * r0 + r0 * r1 + r1 * r1) / 3.0


@dataclass(frozen=True)
class Profile:
    """A planar (rho, z) curve of segments and arcs, traversed counter-clockwise.

    ``closed=False``: an open curve from a point on the axis (rho = 0) to another point on the axis
    (a solid of revolution with two poles). ``closed=True``: a closed loop with rho > 0 (a ring).
    """

    pieces: tuple
    closed: bool

    @property
    def length(self) -> float:
        return sum(p.length for p in self.pieces)

    def sample(self, edge_length: float, chord_error: float = DEFAULT_CHORD_ERROR) -> np.ndarray:
        """(K, 2) points spaced <= ``edge_length``; arcs also keep the chord error <= ``chord_error``."""
        out = []
        for p in self.pieces:
            if isinstance(p, _Arc):
                n = _arc_segments(p.radius, abs(p.end - p.start), edge_length, chord_error)
            else:
                n = max(1, math.ceil(p.length / edge_length))
            pts = p.points(n)
            out.append(pts if not out else pts[1:])
        pts = np.concatenate(out)
        if self.closed:
            pts = pts[:-1]
        return pts


def profile_volume(profile: Profile) -> float:
    """Exact volume of the solid of revolution of ``profile``: ``V = pi * oint rho^2 dz`` [m^3]."""
    return math.pi * sum(p.integral_rho2_dz() for p in profile.pieces)


def rounded_profile(corners, radii, closed: bool = False) -> Profile:
    """Polyline through ``corners`` (rho, z) with a tangent circular fillet of ``radii[i]`` at corner i.

    For an open profile the first and last corners lie on the axis; a non-zero radius there rounds
    the pole (the fillet centre lies on the axis, e.g. a cone tip). The fillet at a corner P between
    edges with unit directions u (towards the previous corner) and v (towards the next) and interior
    half-angle alpha has tangent points ``P + t u`` and ``P + t v`` with ``t = r / tan(alpha)`` and
    centre on the bisector at distance ``r / sin(alpha)`` from P.

    Raises:
        ObjectMeshError: if two fillets overlap along an edge or a pole corner is not on the axis.
    """
    P = np.asarray(corners, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(P)
    if radii.shape != (n,):
        raise ObjectMeshError(f"rounded_profile: need one radius per corner, got {radii.shape} for {n}")
    if not closed and (abs(P[0, 0]) > 1e-15 or abs(P[-1, 0]) > 1e-15):
        raise ObjectMeshError("rounded_profile: an open profile must start and end on the axis (rho = 0)")

    def neighbours(i):
        if closed:
            return P[(i - 1) % n], P[(i + 1) % n]
        if i == 0:  # pole: mirror the next corner across the axis
            return P[1] * [-1, 1], P[1]
        if i == n - 1:
            return P[-2], P[-2] * [-1, 1]
        return P[i - 1], P[i + 1]

    fillets = []  # per corner: (tangent_in, tangent_out, arc or None, tangent distance)
    for i in range(n):
        prev, nxt = neighbours(i)
        r = radii[i]
        if r <= 0:
            fillets.append((P[i], P[i], None, 0.0))
            continue
        u = (prev - P[i]) / np.linalg.norm(prev - P[i])
        v = (nxt - P[i]) / np.linalg.norm(nxt - P[i])
        half = 0.5 * math.acos(float(np.clip(u @ v, -1.0, 1.0)))
        if half >= math.pi / 2 - 1e-9:  # straight continuation: nothing to round
            fillets.append((P[i], P[i], None, 0.0))
            continue
        t = r / math.tan(half)
        bis = (u + v) / np.linalg.norm(u + v)
        c = P[i] + bis * (r / math.sin(half))
        t_in, t_out = P[i] + t * u, P[i] + t * v
        a0 = math.atan2(t_in[1] - c[1], t_in[0] - c[0])
        a1 = math.atan2(t_out[1] - c[1], t_out[0] - c[0])
        # a counter-clockwise profile turns left at convex corners; the fillet runs clockwise about its
        # centre at concave (reflex) corners. Pick the short way round in the turning direction.
        turn = (P[i] - prev)[0] * (nxt - P[i])[1] - (P[i] - prev)[1] * (nxt - P[i])[0]
        if turn > 0:
            while a1 < a0:
                a1 += 2 * math.pi
        else:
            while a1 > a0:
                a1 -= 2 * math.pi
        fillets.append((t_in, t_out, _Arc((float(c[0]), float(c[1])), float(r), a0, a1), t))

    # edges i -> i+1 must have room for both tangent lengths
    edge_count = n if closed else n - 1
    for i in range(edge_count):
        j = (i + 1) % n
        length = float(np.linalg.norm(P[j] - P[i]))
        if fillets[i][3] + fillets[j][3] > length * (1 + 1e-9):
            raise ObjectMeshError(
                f"rounded_profile: fillets at corners {i} and {j} overlap on an edge of {length:.4g} m "
                f"(tangent lengths {fillets[i][3]:.4g} + {fillets[j][3]:.4g} m): reduce the edge radius"
            )

    pieces: list = []

    def add_segment(a, b):
        if np.linalg.norm(np.asarray(b) - np.asarray(a)) > 1e-12:
            pieces.append(_Segment((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))))

    if closed:
        for i in range(n):
            j = (i + 1) % n
            if fillets[i][2] is not None:
                pieces.append(fillets[i][2])
            add_segment(fillets[i][1], fillets[j][0])
        return Profile(tuple(pieces), closed=True)

    # open profile: start at the pole (or at the top of its fillet arc on the axis)
    for i in range(n):
        arc = fillets[i][2]
        if arc is not None:
            if i == 0:  # second half of a symmetric pole fillet: from the axis to the tangent point
                mid = -math.pi / 2 if arc.end > arc.start else math.pi * 1.5
                pieces.append(_Arc(arc.center, arc.radius, mid, arc.end))
            elif i == n - 1:
                mid = math.pi / 2 if arc.end > arc.start else -math.pi * 1.5
                pieces.append(_Arc(arc.center, arc.radius, arc.start, mid))
            else:
                pieces.append(arc)
        if i < n - 1:
            add_segment(fillets[i][1], fillets[i + 1][0])
    return Profile(tuple(pieces), closed=False)


def revolve(profile_points: np.ndarray, closed: bool, segments: int) -> trimesh.Trimesh:
    """Closed triangle surface of revolution of (rho, z) ``profile_points`` about the z axis.

    Open profiles must start and end on the axis (the poles get triangle fans); closed profiles are
    loops with rho > 0 (ring topology). The profile must be counter-clockwise in the (rho, z)
    half-plane so that the normals point outward.
    """
    pts = np.asarray(profile_points, dtype=np.float64)
    theta = 2 * np.pi * np.arange(segments) / segments
    cos, sin = np.cos(theta), np.sin(theta)
    if closed:
        rings = pts
        k = len(rings)
        verts = np.stack(
            [np.outer(rings[:, 0], cos), np.outer(rings[:, 0], sin), np.repeat(rings[:, 1:2], segments, 1)],
            -1,
        ).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(k), np.arange(segments), indexing="ij")
        a = i * segments + j
        b = ((i + 1) % k) * segments + j
        c = ((i + 1) % k) * segments + (j + 1) % segments
        d = i * segments + (j + 1) % segments
        faces = np.concatenate(
            [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
        )
        return trimesh.Trimesh(verts, faces, process=False)
    rings = pts[1:-1]
    k = len(rings)
    ring_v = np.stack(
        [np.outer(rings[:, 0], cos), np.outer(rings[:, 0], sin), np.repeat(rings[:, 1:2], segments, 1)], -1
    ).reshape(-1, 3)
    south, north = len(ring_v), len(ring_v) + 1
    verts = np.concatenate([ring_v, [[0.0, 0.0, pts[0, 1]], [0.0, 0.0, pts[-1, 1]]]])
    j = np.arange(segments)
    jn = (j + 1) % segments
    faces = [np.stack([np.full(segments, south), jn, j], -1)]
    if k > 1:
        i, jj = np.meshgrid(np.arange(k - 1), j, indexing="ij")
        a = i * segments + jj
        b = (i + 1) * segments + jj
        c = (i + 1) * segments + (jj + 1) % segments
        d = i * segments + (jj + 1) % segments
        faces += [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    top = (k - 1) * segments
    faces.append(np.stack([np.full(segments, north), top + j, top + jn], -1))
    return trimesh.Trimesh(verts, np.concatenate(faces), process=False)


def _segments_for(radius_max: float, edge_length: float, minimum: int = 24) -> int:
    n = max(minimum, _arc_segments(radius_max, 2 * math.pi, edge_length, DEFAULT_CHORD_ERROR))
    return n + (n % 2)  # even: the surface is symmetric under rotation by pi about z


def _finish(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """Merge the seam, centre the volume centroid at the origin and validate."""
    mesh.merge_vertices()
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    mesh.apply_translation(-mesh.center_mass)
    check_surface(mesh, name)
    return mesh


def _revolved(profile: Profile, edge_length: float, name: str) -> trimesh.Trimesh:
    pts = profile.sample(edge_length)
    segments = _segments_for(float(pts[:, 0].max()), edge_length)
    return _finish(revolve(pts, profile.closed, segments), name)


# ----------------------------------------------------------------------------------------- shapes
def cylinder(
    radius: float, height: float, edge_radius: float = 0.0, edge_length: float = DEFAULT_EDGE_LENGTH
):
    """Solid circular cylinder (axis z) with rim fillets of ``edge_radius`` [m]; returns (mesh, volume)."""
    _positive(radius=radius, height=height)
    prof = rounded_profile(
        [(0, 0), (radius, 0), (radius, height), (0, height)], [0, edge_radius, edge_radius, 0], closed=False
    )
    return _revolved(prof, edge_length, "cylinder"), profile_volume(prof)


def cone(
    bottom_radius: float,
    top_radius: float,
    height: float,
    edge_radius: float = 0.0,
    tip_radius: float = 0.0,
    edge_length: float = DEFAULT_EDGE_LENGTH,
):
    """Cone or frustum (axis z): base radius, top radius (0 for a cone with a tip rounded by
    ``tip_radius``), rims rounded by ``edge_radius``; returns (mesh, exact volume)."""
    _positive(bottom_radius=bottom_radius, height=height)
    if top_radius > 0:
        corners = [(0, 0), (bottom_radius, 0), (top_radius, height), (0, height)]
        radii = [0, edge_radius, edge_radius, 0]
    else:
        if tip_radius <= 0:
            raise ObjectMeshError(
                "cone: a pointed cone needs tip_radius > 0 (sharp tips are stress singularities)"
            )
        corners = [(0, 0), (bottom_radius, 0), (0, height)]
        radii = [0, edge_radius, tip_radius]
    prof = rounded_profile(corners, radii, closed=False)
    return _revolved(prof, edge_length, "cone"), profile_volume(prof)


def capsule(radius: float, length: float, edge_length: float = DEFAULT_EDGE_LENGTH):
    """Cylinder of ``length`` (axis z) capped by hemispheres of ``radius``: ``V = pi r^2 L + 4/3 pi r^3``."""
    _positive(radius=radius)
    if length < 0:
        raise ObjectMeshError(f"capsule: length must be >= 0, got {length}")
    top = length + 2 * radius
    prof = rounded_profile(
        [(0, 0), (radius, 0), (radius, top), (0, top)], [0, radius * (1 - 1e-12), radius * (1 - 1e-12), 0]
    )
    return _revolved(prof, edge_length, "capsule"), profile_volume(prof)


def annulus(
    outer_radius: float,
    inner_radius: float,
    height: float,
    edge_radius: float = 0.0,
    edge_length: float = DEFAULT_EDGE_LENGTH,
):
    """Hollow cylinder (ring, tube) about z with all four rims rounded by ``edge_radius``."""
    _positive(outer_radius=outer_radius, inner_radius=inner_radius, height=height)
    if inner_radius >= outer_radius:
        raise ObjectMeshError(
            f"annulus: inner radius {inner_radius} must be below outer radius {outer_radius}"
        )
    corners = [(inner_radius, 0), (outer_radius, 0), (outer_radius, height), (inner_radius, height)]
    prof = rounded_profile(corners, [edge_radius] * 4, closed=True)
    return _revolved(prof, edge_length, "annulus"), profile_volume(prof)


def torus(major_radius: float, minor_radius: float, edge_length: float = DEFAULT_EDGE_LENGTH):
    """Ring torus about z: tube radius ``minor_radius`` at distance ``major_radius``; ``V = 2 pi^2 R r^2``."""
    _positive(major_radius=major_radius, minor_radius=minor_radius)
    if minor_radius >= major_radius:
        raise ObjectMeshError(f"torus: minor radius {minor_radius} must be below major radius {major_radius}")
    prof = Profile((_Arc((major_radius, 0.0), minor_radius, -math.pi, math.pi),), closed=True)
    return _revolved(prof, edge_length, "torus"), profile_volume(prof)


def ellipsoid(semi_axes, edge_length: float = DEFAULT_EDGE_LENGTH):
    """Ellipsoid ``(x/a)^2 + (y/b)^2 + (z/c)^2 = 1`` from a scaled icosphere; ``V = 4/3 pi a b c``."""
    a, b, c = (float(s) for s in semi_axes)
    _positive(a=a, b=b, c=c)
    # icosphere edge length ~ 1.05 R / 2^k; pick k so that the longest edge is about edge_length
    k = int(np.clip(math.ceil(math.log2(1.05 * max(a, b, c) / edge_length)), 2, 6))
    mesh = trimesh.creation.icosphere(subdivisions=k, radius=1.0)
    mesh = trimesh.Trimesh(mesh.vertices * [a, b, c], mesh.faces, process=False)
    return _finish(mesh, "ellipsoid"), 4.0 / 3.0 * math.pi * a * b * c


def rounded_box_volume(size, radius: float) -> float:
    """Steiner's formula for a box of side lengths ``size`` with edges and corners rounded by ``radius``."""
    a = np.asarray(size, dtype=np.float64) - 2 * radius
    s = a[0] * a[1] + a[1] * a[2] + a[2] * a[0]
    return float(a.prod() + 2 * radius * s + math.pi * radius**2 * a.sum() + 4.0 / 3.0 * math.pi * radius**3)


def rounded_box_mesh(
    size, radius: float, edge_length: float = DEFAULT_EDGE_LENGTH, min_fillet_segments: int = 2
):
    """Closed surface of a box of side lengths ``size`` with all edges rounded by ``radius`` (>= 0).

    Each face of the box is a grid; a grid point ``s`` on the sharp box maps to
    ``q = clip(s, -c, c) + r * (s - clip(s)) / |s - clip(s)|`` with ``c = size/2 - r`` (identity on the
    flat part). Grid lines in the fillet strip are placed at ``c + r tan(phi)``, phi uniform in
    [0, pi/4], so the fillet arcs are sampled uniformly in angle. Faces are flat where ``|s| <= c``.
    """
    h = np.asarray(size, dtype=np.float64) / 2
    r = float(radius)
    if np.any(h <= 0) or r < 0 or np.any(r > h + 1e-15):
        raise ObjectMeshError(f"rounded box: need 0 <= radius <= half size, got size {size}, radius {radius}")
    c = h - r

    def axis_coords(k):
        n_flat = max(1, math.ceil(2 * c[k] / edge_length)) if c[k] > 1e-12 else 0
        m = (
            _arc_segments(r, math.pi / 4, edge_length, DEFAULT_CHORD_ERROR, min_fillet_segments)
            if r > 0
            else 0
        )
        flat = np.linspace(-c[k], c[k], n_flat + 1) if n_flat else np.array([0.0])
        strip = c[k] + r * np.tan(np.linspace(0, math.pi / 4, m + 1)[1:]) if m else np.array([])
        return np.concatenate([-strip[::-1], flat, strip])

    coords = [axis_coords(k) for k in range(3)]
    verts, faces, offset = [], [], 0
    for normal_axis in range(3):
        u_axis, v_axis = (normal_axis + 1) % 3, (normal_axis + 2) % 3
        U, V = np.meshgrid(coords[u_axis], coords[v_axis], indexing="ij")
        nu, nv = U.shape
        for sign in (1.0, -1.0):
            s = np.zeros((nu, nv, 3))
            s[..., normal_axis] = sign * h[normal_axis]
            s[..., u_axis], s[..., v_axis] = U, V
            verts.append(s.reshape(-1, 3))
            i, j = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
            a = offset + i * nv + j
            b, cc, d = a + nv, a + nv + 1, a + 1
            # (u, v, n) is right-handed, so (a, b, c) winds counter-clockwise seen from +n
            quads = [np.stack([a, b, cc], -1), np.stack([a, cc, d], -1)]
            if sign < 0:
                quads = [q[..., ::-1] for q in quads]
            faces += [q.reshape(-1, 3) for q in quads]
            offset += nu * nv
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    mesh.merge_vertices()
    s = np.asarray(mesh.vertices)
    core = np.clip(s, -c, c)
    d = s - core
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    q = core + np.divide(r * d, norm, out=np.zeros_like(d), where=norm > 0)
    return trimesh.Trimesh(q, mesh.faces, process=False)


def cuboid(size, edge_radius: float = 0.0, edge_length: float = DEFAULT_EDGE_LENGTH):
    """Box of side lengths ``size`` [m] with rounded edges; returns (mesh, exact volume)."""
    return _finish(rounded_box_mesh(size, edge_radius, edge_length), "cuboid"), rounded_box_volume(
        size, edge_radius
    )


def _positive(**values):
    for key, val in values.items():
        if not (np.isfinite(val) and val > 0):
            raise ObjectMeshError(
                f"primitive dimension {key} must be a positive finite length [m], got {val}"
            )


# ----------------------------------------------------------------------------------------- catalogue
_BUILDERS = {
    "cuboid": cuboid,
    "cylinder": cylinder,
    "ellipsoid": ellipsoid,
    "annulus": annulus,
    "capsule": capsule,
    "cone": cone,
    "torus": torus,
}


@dataclass(frozen=True)
class PrimitiveSpec:
    """A named primitive: its category and the keyword arguments of the category's builder [m]."""

    name: str
    category: str
    params: dict = field(hash=False)

    def build(self, edge_length: float = DEFAULT_EDGE_LENGTH) -> tuple[trimesh.Trimesh, float]:
        """(surface mesh centred at its centroid, exact volume of the smooth shape [m^3])."""
        return build_primitive(self.category, edge_length=edge_length, **self.params)


def build_primitive(category: str, edge_length: float = DEFAULT_EDGE_LENGTH, **params):
    """Build a primitive of ``category`` (one of :data:`CATEGORIES`); returns (mesh, exact volume)."""
    if category not in _BUILDERS:
        raise KeyError(f"unknown primitive category {category!r}; choose from {', '.join(CATEGORIES)}")
    return _BUILDERS[category](edge_length=edge_length, **params)


def _mm(x: float) -> str:
    return f"{x * 1000:g}".replace(".", "p")


def _catalogue() -> dict[str, PrimitiveSpec]:
    specs: list[PrimitiveSpec] = []

    def add(name, category, **params):
        specs.append(PrimitiveSpec(name, category, params))

    # cuboids: side lengths (x, y, z), edge radius ~ 10-15 % of the smallest side
    for size in [
        (0.03, 0.03, 0.03),
        (0.05, 0.05, 0.05),
        (0.06, 0.04, 0.02),
        (0.10, 0.03, 0.03),
        (0.08, 0.06, 0.015),
        (0.12, 0.02, 0.02),
        (0.07, 0.035, 0.02),
        (0.04, 0.04, 0.09),
        (0.10, 0.10, 0.02),
    ]:
        r = round(0.15 * min(size), 4)
        add(f"cuboid_{'x'.join(_mm(s) for s in size)}", "cuboid", size=size, edge_radius=r)
    # cylinders: (radius, height)
    for radius, height in [
        (0.015, 0.06),
        (0.02, 0.04),
        (0.025, 0.10),
        (0.03, 0.03),
        (0.035, 0.02),
        (0.01, 0.10),
        (0.02, 0.08),
        (0.03, 0.06),
        (0.045, 0.05),
    ]:
        add(
            f"cylinder_r{_mm(radius)}_h{_mm(height)}",
            "cylinder",
            radius=radius,
            height=height,
            edge_radius=round(0.2 * min(radius, height / 2), 4),
        )
    # ellipsoids: semi-axes (a, b, c)
    for axes in [
        (0.02, 0.02, 0.02),
        (0.03, 0.03, 0.03),
        (0.035, 0.035, 0.035),
        (0.04, 0.02, 0.02),
        (0.035, 0.035, 0.015),
        (0.04, 0.025, 0.015),
        (0.03, 0.02, 0.02),
        (0.05, 0.025, 0.025),
        (0.025, 0.025, 0.045),
    ]:
        add(f"ellipsoid_{'x'.join(_mm(s) for s in axes)}", "ellipsoid", semi_axes=axes)
    # annuli: (outer radius, inner radius, height)
    for ro, ri, height in [
        (0.025, 0.015, 0.02),
        (0.03, 0.02, 0.01),
        (0.035, 0.025, 0.03),
        (0.02, 0.01, 0.04),
        (0.04, 0.03, 0.015),
        (0.03, 0.025, 0.05),
        (0.025, 0.02, 0.08),
        (0.035, 0.015, 0.025),
        (0.045, 0.035, 0.02),
    ]:
        add(
            f"annulus_ro{_mm(ro)}_ri{_mm(ri)}_h{_mm(height)}",
            "annulus",
            outer_radius=ro,
            inner_radius=ri,
            height=height,
            edge_radius=round(0.2 * min(ro - ri, height), 4),
        )
    # capsules: (radius, cylinder length)
    for radius, length in [
        (0.01, 0.04),
        (0.015, 0.03),
        (0.02, 0.04),
        (0.025, 0.02),
        (0.015, 0.08),
        (0.03, 0.03),
        (0.012, 0.06),
        (0.02, 0.08),
        (0.035, 0.01),
    ]:
        add(f"capsule_r{_mm(radius)}_l{_mm(length)}", "capsule", radius=radius, length=length)
    # cones and frustums: (bottom radius, top radius, height); top radius 0 = cone with rounded tip
    for rb, rt, height in [
        (0.03, 0.015, 0.05),
        (0.025, 0.01, 0.06),
        (0.035, 0.025, 0.04),
        (0.02, 0.005, 0.08),
        (0.03, 0.0, 0.06),
        (0.025, 0.0, 0.04),
        (0.035, 0.02, 0.025),
        (0.015, 0.005, 0.07),
        (0.03, 0.01, 0.03),
    ]:
        params = dict(
            bottom_radius=rb, top_radius=rt, height=height, edge_radius=round(0.15 * min(rb, height), 4)
        )
        if rt == 0:
            params["tip_radius"] = round(0.2 * rb, 4)
        else:
            params["edge_radius"] = round(min(params["edge_radius"], 0.5 * rt), 4)
        add(f"cone_rb{_mm(rb)}_rt{_mm(rt)}_h{_mm(height)}", "cone", **params)
    # tori: (major radius, minor radius)
    for major, minor in [
        (0.025, 0.008),
        (0.03, 0.01),
        (0.035, 0.012),
        (0.02, 0.01),
        (0.03, 0.005),
        (0.04, 0.008),
        (0.025, 0.012),
        (0.035, 0.006),
        (0.028, 0.014),
    ]:
        add(f"torus_R{_mm(major)}_r{_mm(minor)}", "torus", major_radius=major, minor_radius=minor)
    return {s.name: s for s in specs}


PRIMITIVES: dict[str, PrimitiveSpec] = _catalogue()
"""All named primitive instances, by name (at least 60, in :data:`CATEGORIES`)."""
