"""The soft tactile sensor's silicone membrane as a tetrahedral mesh, and its enclosed gas.

Geometry (thesis §2.2, second sensor version, the one of chapters 3-5): a hemispherical Ecoflex 00-50
shell of inner radius ``R_i = 47 mm`` (the *neutral* radius, i.e. with free air exchange, so at
atmospheric pressure) and outer radius ``R_o = 50 mm`` (uniform thickness ``t = 3 mm``; outer/inner
diameters 100/94 mm), continued below its equator by a ``h_s = 30 mm`` cylindrical skirt whose lower
rim is clamped (cable ties) onto a rigid cylinder that houses the depth camera.

Sensor frame (used by every tactile module): origin at the camera's optical centre, which sits on
the axis on the rigid base plane at the bottom of the housing; ``+z`` along the sensor axis towards
the pole of the membrane; x, y as the camera's image axes (the thesis, §3.3: "the principal camera
axes also share the same orientation as the force-torque coordinate frame"). Heights along z:

    z_rim  = rim_height                  clamped lower rim of the skirt (top of the rigid cylinder)
    z_eq   = z_rim + h_s                 equator of the hemisphere, centre of the spheres
    z_pole = z_eq + R_i  (inner),  z_eq + R_o  (outer)

Mesh: a structured shell sweep, deterministic and fast. The inner surface is an *equiangular
cubed-sphere* hemisphere (top face plus the upper halves of the four side faces of a cube projected
onto the sphere; no pole singularity, all quads near-square) joined conformingly at the equator to a
quad grid on the cylindrical skirt. Every surface vertex ``X_s`` with outward radial unit vector
``n_s`` is swept through the thickness, ``X = X_s + (k t / L) n_s`` for ``k = 0..L``, and every
surface triangle times a layer is a prism split into three tets with the vertex-index rule of
Dompierre et al. (1999, "How to subdivide pyramids, prisms and hexahedra into tetrahedra"), which is
conforming across neighbouring prisms for any triangle surface.

Enclosed gas (for the closed capsule's isothermal law ``P V = const``, the thesis's PV states): the
gas is bounded by the inner membrane surface and the rim disk ``z = z_rim``; by the divergence
theorem, for a closed triangulated surface,

    V = (1/6) sum_faces (a - c) . ((b - c) x (d - c)),

with outward (gas-side) oriented faces and any point c. Choosing c on the rim disk makes the disk's
own (coplanar) contribution vanish, so the inner faces alone give the exact polyhedral volume for
any deformed configuration whose clamped rim stays planar. The rigid housing below the rim adds a
constant gas volume (a cylinder from the base plane to the rim, camera volume neglected).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from defgraspnets.fem.material import Material
from defgraspnets.fem.mesh import TetMesh

__all__ = [
    "ATMOSPHERIC_PRESSURE",
    "ECOFLEX_00_50",
    "INFLATED_INNER_RADIUS",
    "THESIS_PV_STATES",
    "MembraneDimensions",
    "MembraneError",
    "MembraneSensor",
    "PVState",
    "build_membrane",
    "enclosed_volume",
]


class MembraneError(ValueError):
    """Invalid membrane dimensions, resolution, or deformed configuration."""


# --------------------------------------------------------------------------- material
#: Smooth-On Ecoflex 00-50 (the thesis's membrane silicone, §2.2). Sources and derivation:
#:
#: - density: specific gravity 1.07 (Smooth-On Ecoflex Series technical bulletin) -> 1070 kg/m^3;
#: - stiffness: the bulletin's 100 % modulus (engineering stress at stretch 2) is 12 psi = 82.7 kPa.
#:   Fitting an incompressible neo-Hookean solid to it, whose uniaxial nominal stress is
#:   ``P = mu (lam - lam^-2)``, gives ``mu = 82.7 kPa / 1.75 = 47.3 kPa`` and the small-strain
#:   Young's modulus ``E = 3 mu = 142 kPa`` (the secant value ``sigma_100 / 1 = 83 kPa`` is a lower
#:   bound; published small-strain moduli of Ecoflex grades scatter by about a factor 2 with test
#:   method and cure, so treat E as a calibration parameter);
#: - Poisson ratio: silicone rubber is nearly incompressible (bulk/shear modulus ratio ~1e4,
#:   nu ~ 0.4999). The FEM engine needs nu < 0.5 and its linear tets lock volumetrically as
#:   nu -> 0.5. nu = 0.48 (lambda/mu = 24) keeps volume changes below ~4 % of the deviatoric
#:   strain while the sheet's membrane stiffness E/(1 - nu^2) is within 3 % of the incompressible
#:   limit; use 0.45 for coarse meshes (less locking), 0.49 for fine ones.
#:
#: The co-rotated model of :mod:`defgraspnets.fem.material` uses E at small strain; large membrane
#: stretches (inflation 47 -> 50 mm is 6 %) stay in its accurate range.
ECOFLEX_00_50 = Material(youngs_modulus=1.42e5, poisson_ratio=0.48, density=1070.0)

#: Standard sea-level atmospheric pressure [Pa] (ISO 2533): the gas state with free air exchange.
ATMOSPHERIC_PRESSURE = 101_325.0

#: Inner radius [m] of the membrane at the fixed pressure state used in chapters 3-5 of the thesis
#: ("inflated to 50 mm, compared to its neutral 47 mm radius").
INFLATED_INNER_RADIUS = 0.050

#: Pre-contact gas states of the thesis as products P V [N m = J] (absolute pressure times gas
#: volume; a gauge pressure of a few kPa would imply tens of litres of gas, so P is absolute).
#: Measured on the *first* sensor version (2 mm shell, §2.2-2.4): force matching at 32.5, 61.2 and
#: 103.4 N m (Table 2.1), contact-region estimation at 70 N m (§2.3).
THESIS_PV_STATES = {"force_matching": (32.5, 61.2, 103.4), "contact_region": (70.0,)}


@dataclass(frozen=True)
class PVState:
    """Thermodynamic state of the sensor's enclosed gas: absolute pressure and volume.

    The thesis labels every pre-contact gas state by the product ``P V`` [N m]; for the closed
    capsule at constant temperature (Boyle), ``P V`` stays constant while the membrane deforms:
    ``P' = P V / V'`` (:meth:`isothermal`).

    Args:
        pressure: absolute gas pressure P [Pa] > 0.
        volume: gas volume V [m^3] > 0 (membrane cavity plus the housing, see
            :meth:`MembraneSensor.gas_volume`).
        label: optional name (e.g. ``"free_air"``, ``"pv70"``).
    """

    pressure: float
    volume: float
    label: str = ""

    def __post_init__(self):
        for name in ("pressure", "volume"):
            value = getattr(self, name)
            if not np.isscalar(value) or not np.isfinite(value) or value <= 0:
                raise MembraneError(f"PVState.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))

    @property
    def pv(self) -> float:
        """The state label of the thesis, P V [N m = J]."""
        return self.pressure * self.volume

    @property
    def gauge_pressure(self) -> float:
        """P - P_atm [Pa]: the pressure load on the membrane (outside is atmospheric)."""
        return self.pressure - ATMOSPHERIC_PRESSURE

    def isothermal(self, volume: float) -> PVState:
        """The state after an isothermal volume change of the closed capsule: P' = P V / V'."""
        if not np.isfinite(volume) or volume <= 0:
            raise MembraneError(f"gas volume must be finite and > 0 m^3, got {volume!r}")
        return PVState(self.pv / volume, volume, self.label)

    @classmethod
    def from_pv(cls, pv: float, volume: float, label: str = "") -> PVState:
        """The state with product ``pv`` [N m] at gas volume ``volume`` [m^3]."""
        if not np.isfinite(pv) or pv <= 0:
            raise MembraneError(f"PV must be finite and > 0 N m, got {pv!r}")
        return cls(pv / volume, volume, label or f"pv{pv:g}")

    @classmethod
    def free_air(cls, volume: float) -> PVState:
        """Free air exchange with the atmosphere (the thesis's neutral state)."""
        return cls(ATMOSPHERIC_PRESSURE, volume, "free_air")


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class MembraneDimensions:
    """Analytic geometry of the undeformed membrane in the sensor frame [m].

    Args:
        inner_radius: R_i, hemisphere inner radius (thesis: 47 mm neutral).
        thickness: t = R_o - R_i (thesis: 3 mm).
        skirt_height: h_s, cylindrical skirt length below the equator (thesis: 30 mm).
        rim_height: z of the clamped rim above the camera / base plane. The thesis gives no number
            (the distance "was experimentally selected to optimize for visibility and field of
            view"); 0.10 m is the pico flexx's quoted minimum range (10 cm), so every membrane point
            the camera sees lies in its working range.
        housing_radius: inner radius of the rigid cylinder below the rim, for the housing gas volume
            (default: the membrane inner radius; its wall thickness is not given in the thesis).
    """

    inner_radius: float = 0.047
    thickness: float = 0.003
    skirt_height: float = 0.030
    rim_height: float = 0.10
    housing_radius: float | None = None

    def __post_init__(self):
        for name in ("inner_radius", "thickness", "skirt_height", "rim_height"):
            value = getattr(self, name)
            if not np.isscalar(value) or not np.isfinite(value) or value <= 0:
                raise MembraneError(f"MembraneDimensions.{name} must be a finite length > 0 m, got {value!r}")
        if self.thickness >= 0.5 * self.inner_radius:
            raise MembraneError(
                f"thickness {self.thickness:g} m is not thin against the radius {self.inner_radius:g} m"
            )
        if self.housing_radius is not None and not (0 < self.housing_radius <= self.inner_radius):
            raise MembraneError(f"housing_radius must be in (0, inner_radius], got {self.housing_radius!r}")

    @property
    def outer_radius(self) -> float:
        return self.inner_radius + self.thickness

    @property
    def z_rim(self) -> float:
        return self.rim_height

    @property
    def z_equator(self) -> float:
        """Height of the hemisphere's equator and centre [m]."""
        return self.rim_height + self.skirt_height

    @property
    def center(self) -> np.ndarray:
        """Centre of the hemisphere (0, 0, z_eq) [m]."""
        return np.array([0.0, 0.0, self.z_equator])

    @property
    def inner_pole(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.z_equator + self.inner_radius])

    @property
    def outer_pole(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.z_equator + self.outer_radius])

    @property
    def cavity_volume(self) -> float:
        """Analytic gas volume above the rim disk: hemisphere + cylinder, (2/3) pi R^3 + pi R^2 h_s."""
        r = self.inner_radius
        return 2.0 / 3.0 * np.pi * r**3 + np.pi * r**2 * self.skirt_height

    @property
    def housing_volume(self) -> float:
        """Gas volume of the rigid housing between base plane and rim, pi R_h^2 z_rim [m^3]."""
        r = self.inner_radius if self.housing_radius is None else self.housing_radius
        return np.pi * r**2 * self.rim_height

    def outer_surface_point(self, phi: float, contact_radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Point on the outer hemisphere above radius ``rho`` from the axis, and its outward normal.

        ``p = (rho cos phi, rho sin phi, z_eq + sqrt(R_o^2 - rho^2))``, ``n = (p - centre) / R_o``
        (the thesis's pre-indentation contact points, §3.3, Fig. 3.2).
        """
        r_o = self.outer_radius
        if not (np.isfinite(phi) and np.isfinite(contact_radius)):
            raise MembraneError(f"contact point must be finite, got phi={phi!r}, radius={contact_radius!r}")
        if not 0.0 <= contact_radius <= r_o:
            raise MembraneError(
                f"contact radius {contact_radius:g} m lies outside the hemisphere (0 <= rho <= {r_o:g} m)"
            )
        z = self.z_equator + np.sqrt(r_o**2 - contact_radius**2)
        p = np.array([contact_radius * np.cos(phi), contact_radius * np.sin(phi), z])
        return p, (p - self.center) / r_o


def enclosed_volume(points: np.ndarray, inner_faces: np.ndarray, rim_center: np.ndarray) -> float:
    """Gas volume [m^3] enclosed by the inner membrane surface and its planar rim disk.

    ``V = -(1/6) sum_f (a - c) . ((b - c) x (d - c))`` over the inner faces ``(a, b, d)``, oriented
    with the *solid's* outward normal (pointing into the gas, hence the minus sign), with ``c`` the
    centre of the rim disk. Exact for the triangulated surface as long as the rim loop stays in the
    plane through ``c`` (the clamped rim).

    Args:
        points: (N, 3) vertex positions [m] (rest or deformed).
        inner_faces: (F, 3) vertex indices of the inner surface triangles.
        rim_center: (3,) a point on the rim disk [m].
    """
    p = np.asarray(points, dtype=np.float64)
    c = np.asarray(rim_center, dtype=np.float64)
    a, b, d = (p[inner_faces[:, k]] - c for k in range(3))
    return float(-np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0)


# --------------------------------------------------------------------------- surface sweep
def _cubed_sphere_hemisphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (P, 3) and quads (Q, 4) of an equiangular cubed-sphere upper hemisphere.

    Top cube face: ``(tan a, tan b, 1)``; side faces: ``e + tan(a) t + tan(b) z`` with
    ``a in [-pi/4, pi/4]`` (n cells) and ``b in [0, pi/4]`` (n/2 cells), normalized. The equator
    (b = 0) gets 4n vertices equally spaced in azimuth. Shared patch edges are merged.
    """
    ta = np.tan(np.linspace(-np.pi / 4, np.pi / 4, n + 1))
    tb = np.tan(np.linspace(0.0, np.pi / 4, n // 2 + 1))
    ez = np.array([0.0, 0.0, 1.0])
    grids = [np.stack(np.meshgrid(ta, ta, indexing="ij"), axis=-1) @ np.eye(3)[:2] + ez]
    sides = [
        ((1, 0, 0), (0, 1, 0)),
        ((0, 1, 0), (-1, 0, 0)),
        ((-1, 0, 0), (0, -1, 0)),
        ((0, -1, 0), (1, 0, 0)),
    ]
    for e, t in sides:
        a, b = np.meshgrid(ta, tb, indexing="ij")
        grids.append(np.asarray(e) + a[..., None] * np.asarray(t) + b[..., None] * ez)
    points, quads, offset = [], [], 0
    for g in grids:
        ni, nj = g.shape[0] - 1, g.shape[1] - 1
        idx = offset + np.arange((ni + 1) * (nj + 1)).reshape(ni + 1, nj + 1)
        quads.append(
            np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
        )
        points.append(g.reshape(-1, 3))
        offset += idx.size
    dirs = np.concatenate(points)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[np.abs(dirs[:, 2]) < 1e-12, 2] = 0.0  # the equator exactly in the plane
    return _merge(dirs, np.concatenate(quads), tol=1e-9)


def _merge(points: np.ndarray, cells: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident points (closer than ``tol``), keeping the first; remap ``cells``."""
    tree = cKDTree(points)
    rep = np.arange(len(points))
    for i, j in sorted(tree.query_pairs(tol)):
        rep[j] = min(rep[j], rep[i])
    keep, inverse = np.unique(rep, return_inverse=True)
    return points[keep], inverse[cells]


def _split_quads(quads: np.ndarray, positions: np.ndarray, mirror_symmetric: bool = False) -> np.ndarray:
    """Two triangles per quad, cut along the shorter diagonal (deterministic, better shaped). Quads whose
    diagonals are equally long (the skirt's rectangles) are all cut along 0-2; with ``mirror_symmetric``
    (ties to 1e-9) along 0-2 where the quad's centre has x y >= 0 and along 1-3 elsewhere, so that the cut
    is mirror-symmetric about the planes x = 0 and y = 0 (no quad straddles them)."""
    q = quads
    d02 = np.linalg.norm(positions[q[:, 0]] - positions[q[:, 2]], axis=1)
    d13 = np.linalg.norm(positions[q[:, 1]] - positions[q[:, 3]], axis=1)
    use02 = d02 <= d13 + 1e-12 * d02
    if mirror_symmetric:
        centre = positions[q].mean(axis=1)
        tie = np.abs(d02 - d13) <= 1e-9 * d02
        use02 = np.where(tie, centre[:, 0] * centre[:, 1] >= 0.0, use02)
    t02 = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    t13 = np.concatenate([q[:, [0, 1, 3]], q[:, [1, 2, 3]]])
    mask = np.concatenate([use02, use02])
    return np.where(mask[:, None], t02, t13)


def _prisms_to_tets(triangles: np.ndarray, num_surface: int, layers: int) -> np.ndarray:
    """Split the prisms (triangle x layer) into 3 tets each, conformingly.

    With the triangle's surface ids sorted ``a < b < c`` and primes for the next layer, the
    lateral quad diagonals run from the lower layer of the smaller id to the upper layer of the
    larger one; the tets are ``(a,b,c,c')``, ``(a,b,b',c')``, ``(a,a',b',c')``. Neighbouring prisms
    share the two ids of a lateral face and hence choose the same diagonal.
    """
    t = np.sort(triangles, axis=1)
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    tets = []
    for k in range(layers):
        lo, hi = k * num_surface, (k + 1) * num_surface
        tets += [
            np.stack([a + lo, b + lo, c + lo, c + hi], axis=1),
            np.stack([a + lo, b + lo, b + hi, c + hi], axis=1),
            np.stack([a + lo, a + hi, b + hi, c + hi], axis=1),
        ]
    return np.concatenate(tets)


# --------------------------------------------------------------------------- the sensor
@dataclass(frozen=True, eq=False)
class MembraneSensor:
    """The membrane mesh with everything the FEM engine, the camera and the gas law need.

    Built by :func:`build_membrane`; do not construct directly.

    Attributes:
        mesh: the tetrahedral membrane (rest configuration, sensor frame) [m].
        dimensions: the analytic geometry it discretizes.
        material: Ecoflex 00-50 by default (:data:`ECOFLEX_00_50`).
        layers: number of element layers through the thickness.
        clamped_vertices: (C,) sorted indices of the vertices fixed to the rigid housing.
        inner_faces: (Fi, 3) inner-surface triangles, oriented with the solid's outward normal
            (pointing into the gas): the camera's target and the gas pressure's follower load
            ``f = (P - P_atm) * area * (-n)`` per face.
        outer_faces: (Fo, 3) outer-surface triangles (contact with indenters), outward normals.
        vertex_layer: (N,) through-thickness layer of each vertex, 0 = inner surface, L = outer.
    """

    mesh: TetMesh
    dimensions: MembraneDimensions
    material: Material
    layers: int
    clamped_vertices: np.ndarray
    inner_faces: np.ndarray
    outer_faces: np.ndarray
    vertex_layer: np.ndarray = field(repr=False)

    @property
    def rim_center(self) -> np.ndarray:
        """Centre of the clamped rim disk (0, 0, z_rim) [m]."""
        return np.array([0.0, 0.0, self.dimensions.z_rim])

    @cached_property
    def inner_vertices(self) -> np.ndarray:
        return np.nonzero(self.vertex_layer == 0)[0]

    @cached_property
    def outer_vertices(self) -> np.ndarray:
        return np.nonzero(self.vertex_layer == self.layers)[0]

    @cached_property
    def rim_loop(self) -> np.ndarray:
        """Indices of the inner-surface vertices on the rim plane (the boundary of the gas surface)."""
        z = self.mesh.points[self.inner_vertices, 2]
        return self.inner_vertices[np.abs(z - self.dimensions.z_rim) <= 1e-9]

    @cached_property
    def cavity_volume(self) -> float:
        """Undeformed gas volume above the rim disk [m^3], from the inner surface mesh."""
        return self.enclosed_volume()

    def enclosed_volume(self, points: np.ndarray | None = None) -> float:
        """Gas volume above the rim disk [m^3] for vertex positions ``points`` (default: rest).

        Raises:
            MembraneError: ``points`` has the wrong shape, is not finite, or the rim loop has left
                the rim plane (the closing disk would no longer be planar).
        """
        p = self._checked_points(points)
        z_rim = p[self.rim_loop, 2]
        offset = np.max(np.abs(z_rim - self.dimensions.z_rim))
        if offset > 1e-6 * self.dimensions.inner_radius:
            raise MembraneError(
                f"the rim vertices left the rim plane z = {self.dimensions.z_rim:g} m by up to "
                f"{offset:.3g} m; the enclosed volume assumes a clamped (planar) rim"
            )
        return enclosed_volume(p, self.inner_faces, self.rim_center)

    def gas_volume(self, points: np.ndarray | None = None) -> float:
        """Total gas volume: membrane cavity (at ``points``) plus the rigid housing [m^3]."""
        return self.enclosed_volume(points) + self.dimensions.housing_volume

    def inner_surface(self, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (N, 3), faces (Fi, 3)) of the inner surface, for the depth camera."""
        return self._checked_points(points), self.inner_faces

    def _checked_points(self, points) -> np.ndarray:
        if points is None:
            return self.mesh.points
        p = np.asarray(points, dtype=np.float64)
        if p.shape != self.mesh.points.shape:
            raise MembraneError(f"points must have shape {self.mesh.points.shape}, got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise MembraneError("points contain NaN or inf")
        return p

    def __repr__(self) -> str:
        d = self.dimensions
        return (
            f"MembraneSensor(R_i={d.inner_radius:g} m, t={d.thickness:g} m, skirt={d.skirt_height:g} m, "
            f"layers={self.layers}, vertices={self.mesh.num_vertices}, tets={self.mesh.num_tets})"
        )


def mirror_average(sensor: MembraneSensor, positions) -> np.ndarray:
    """The mean of vertex ``positions`` (N, 3), sensor frame [m], and their images under the mirrors about
    x = 0, y = 0 and both (each vertex takes its mirror vertex's position, mirrored): the mirror-symmetric
    part of a field on the membrane. The FEM inflation of even a mirror-symmetric surface mesh is not
    symmetric (the prisms' tet split follows vertex numbers; 0.12 mm at 1500 Pa, cap 12), which a fast model
    built on it would carry into every reading.

    Raises:
        MembraneError: when the rest mesh is not mirror-symmetric (a vertex without a mirror vertex) or the
            positions are not finite (N, 3).
    """
    rest = sensor.mesh.points
    x = np.asarray(positions, dtype=np.float64)
    if x.shape != rest.shape or not np.isfinite(x).all():
        raise MembraneError(f"positions must be finite with shape {rest.shape}, got {x.shape}")
    tree = cKDTree(rest)
    total = x.copy()
    for mirror in ((-1.0, 1.0, 1.0), (1.0, -1.0, 1.0), (-1.0, -1.0, 1.0)):
        m = np.asarray(mirror)
        dist, image = tree.query(rest * m)
        if dist.max() > 1e-9 * sensor.dimensions.outer_radius:
            raise MembraneError(f"the membrane mesh has no mirror vertex for vertex {int(np.argmax(dist))}")
        total += x[image] * m
    return total / 4.0


def build_membrane(
    dimensions: MembraneDimensions | None = None,
    cap_divisions: int = 16,
    skirt_divisions: int | None = None,
    layers: int = 2,
    clamp_band: float = 0.0,
    material: Material = ECOFLEX_00_50,
    mirror_symmetric: bool = False,
) -> MembraneSensor:
    """Build the membrane tet mesh (structured shell sweep, see the module docstring).

    Args:
        dimensions: geometry (default: the thesis sensor, :class:`MembraneDimensions`).
        cap_divisions: cells along a cube-face edge of the cubed-sphere cap (even, >= 4); the equator
            has ``4 * cap_divisions`` vertices (16 -> 64, element size ~4.6 mm at R_i = 47 mm).
        skirt_divisions: cells along the skirt height (default: about square cells).
        layers: element layers through the thickness, >= 2 so the shell can bend.
        clamp_band: height above the rim [m] within which vertices are clamped (0: the rim ring
            only; > 0 models the band of the skirt held by the cable ties).
        material: membrane material.
        mirror_symmetric: split the skirt's rectangles into triangles mirror-symmetrically about the
            planes x = 0 and y = 0 (the cap's split already is): then the whole inner surface maps onto
            itself under both mirrors (a fast model's response does too once its reference shape is
            symmetric as well: :func:`mirror_average` of the FEM inflation, as
            ``build_fast_simulation(mirror_symmetric=True)`` does). False (default) cuts every skirt
            rectangle along the same diagonal, as the meshes of the shipped tactile datasets and
            checkpoints; the skirt then maps onto itself under neither mirror.

    Raises:
        MembraneError: for invalid resolution or clamp band.
    """
    dims = MembraneDimensions() if dimensions is None else dimensions
    n = int(cap_divisions)
    if n != cap_divisions or n < 4 or n % 2:
        raise MembraneError(f"cap_divisions must be an even integer >= 4, got {cap_divisions!r}")
    if int(layers) != layers or layers < 2:
        raise MembraneError(
            f"layers must be an integer >= 2 (bending needs several elements), got {layers!r}"
        )
    layers = int(layers)
    r_i, h_s, z_eq = dims.inner_radius, dims.skirt_height, dims.z_equator
    if skirt_divisions is None:
        skirt_divisions = max(1, int(round(h_s / (2 * np.pi * r_i / (4 * n)))))
    if int(skirt_divisions) != skirt_divisions or skirt_divisions < 1:
        raise MembraneError(f"skirt_divisions must be an integer >= 1, got {skirt_divisions!r}")
    m = int(skirt_divisions)
    if not (np.isfinite(clamp_band) and 0.0 <= clamp_band < h_s):
        raise MembraneError(f"clamp_band must be in [0, skirt_height={h_s:g}) m, got {clamp_band!r}")

    # inner surface: cubed-sphere cap
    dirs, cap_quads = _cubed_sphere_hemisphere(n)
    cap_pos = dims.center + r_i * dirs
    # skirt: rings below the equator vertices, sorted by azimuth
    eq = np.nonzero(dirs[:, 2] == 0.0)[0]
    eq = eq[np.argsort(np.arctan2(dirs[eq, 1], dirs[eq, 0]))]
    if len(eq) != 4 * n:
        raise AssertionError(f"cubed-sphere equator has {len(eq)} vertices, expected {4 * n}")
    ring_dirs = dirs[eq]
    num_cap = len(dirs)
    ring_ids = [eq] + [num_cap + (k - 1) * 4 * n + np.arange(4 * n) for k in range(1, m + 1)]
    skirt_pos = [ring_dirs * r_i + np.array([0.0, 0.0, z_eq - k * h_s / m]) for k in range(1, m + 1)]
    skirt_quads = []
    for k in range(m):
        up, down = ring_ids[k], ring_ids[k + 1]
        skirt_quads.append(np.stack([up, np.roll(up, -1), np.roll(down, -1), down], axis=1))
    surface_pos = np.concatenate([cap_pos, *skirt_pos])
    surface_dir = np.concatenate([dirs, np.tile(ring_dirs, (m, 1))])
    surface_pos[ring_ids[-1], 2] = dims.z_rim  # exactly on the rim plane
    quads = np.concatenate([cap_quads, *skirt_quads])
    triangles = _split_quads(quads, surface_pos, mirror_symmetric=mirror_symmetric)

    # sweep through the thickness and split prisms
    num_surface = len(surface_pos)
    offsets = np.arange(layers + 1) * dims.thickness / layers
    points = (surface_pos[None] + offsets[:, None, None] * surface_dir[None]).reshape(-1, 3)
    tets = _prisms_to_tets(triangles, num_surface, layers)
    mesh = TetMesh.oriented(points, tets, name="membrane")

    vertex_layer = np.repeat(np.arange(layers + 1), num_surface)
    faces = mesh.surface_faces
    face_layer = vertex_layer[faces]
    inner = faces[np.all(face_layer == 0, axis=1)]
    outer = faces[np.all(face_layer == layers, axis=1)]
    rim = np.all(np.abs(points[faces, 2] - dims.z_rim) <= 1e-12, axis=1)
    if len(inner) + len(outer) + rim.sum() != len(faces) or len(inner) != len(triangles):
        raise AssertionError("membrane boundary is not inner + outer + rim surfaces")
    clamped = np.nonzero(points[:, 2] <= dims.z_rim + clamp_band + 1e-12)[0]
    return MembraneSensor(
        mesh=mesh,
        dimensions=dims,
        material=material,
        layers=layers,
        clamped_vertices=clamped,
        inner_faces=np.ascontiguousarray(inner),
        outer_faces=np.ascontiguousarray(outer),
        vertex_layer=vertex_layer,
    )
