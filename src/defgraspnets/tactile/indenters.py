"""Rigid indenters of the thesis's tactile experiments, their poses, and the indentation workspace.

Indenters (geometry in their local frame, placed by a :class:`Pose` in the sensor frame of
:mod:`defgraspnets.tactile.membrane`; metres):

- :class:`SphereIndenter`: the 10, 20 and 30 mm diameter contact spheres of §2.3-2.4
  (:data:`CONTACT_SPHERES`) and the 1 cm PLA fingertip of the finger-poking dataset, §3.3
  (:data:`FINGERTIP`). Signed distance ``phi(p) = |p| - r``.
- :class:`BoxIndenter`: the rectangular prism of §2.3 (flat face down, local -z).
  ``phi = |max(q, 0)| + min(max_i q_i, 0)`` with ``q = |p| - h`` (h: half extents).
- :class:`RingIndenter`: the ring of §2.3, a hollow cylinder about local z (flat annular face
  down). Axisymmetric, so ``phi`` is the 2-D box distance in the meridian plane ``(rho, z)``.
- :class:`CapsuleIndenter`: a forearm-like body, axis along local x (§3.3 collected the forearm
  data on a human forearm; the 3-D-printed ellipsoid replica failed for friction, not geometry).
  ``phi = dist(p, segment) - r``.

The thesis gives no dimensions for the prism, the ring or the forearm: the defaults here
(:data:`RECTANGULAR_PRISM`, :data:`RING`, :data:`FOREARM`) are assumptions sized so that their
contact regions fit in the 3 cm radius plotted in Fig. 2.5, and an adult forearm's ~8 cm width.

Poses: position [m] and unit quaternion ``(x, y, z, w)`` (scalar last, as Warp and SciPy), i.e. the
7-vector stored in the tactile datasets. Experiment commands (:class:`PokeCommand`,
:class:`ForearmCommand`) follow the parameterisation of §3.3 and turn into indenter poses; every
pose can be checked against the sensor's workspace (:func:`check_workspace`): no indenter point may
reach below the clamped rim plane, where the rigid housing is (an indentation "beyond the rim").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.membrane import MembraneDimensions

__all__ = [
    "CONTACT_SPHERES",
    "FINGERTIP",
    "FOREARM",
    "INDENTER_KINDS",
    "RECTANGULAR_PRISM",
    "RING",
    "BoxIndenter",
    "CapsuleIndenter",
    "ForearmCommand",
    "Indenter",
    "IndenterError",
    "PokeCommand",
    "Pose",
    "RingIndenter",
    "SphereIndenter",
    "WorkspaceError",
    "check_workspace",
    "forearm_grid",
    "make_indenter",
    "poke_grid",
]


class IndenterError(ValueError):
    """Invalid indenter geometry, pose or command (NaN, out of range)."""


class WorkspaceError(IndenterError):
    """An indenter pose or command leaves the sensor's allowed workspace (e.g. beyond the rim)."""


def _finite_vector(value, shape, name) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != shape:
        raise IndenterError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise IndenterError(f"{name} contains NaN or inf: {a.tolist()}")
    return a


@dataclass(frozen=True, eq=False)
class Pose:
    """Rigid pose: ``x_sensor = R(q) x_local + position``.

    Args:
        position: (3,) [m].
        quaternion: (4,) ``(x, y, z, w)``; normalized here, must have norm in [0.5, 2] (a clear
            error instead of silently normalizing garbage).
    """

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    quaternion: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))

    def __post_init__(self):
        p = _finite_vector(self.position, (3,), "pose position")
        q = _finite_vector(self.quaternion, (4,), "pose quaternion")
        norm = np.linalg.norm(q)
        if not 0.5 <= norm <= 2.0:
            raise IndenterError(f"pose quaternion must be (near) unit, got norm {norm:g}")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quaternion", q / norm)

    @classmethod
    def from_array(cls, a) -> Pose:
        """From the stored 7-vector ``(x, y, z, qx, qy, qz, qw)``."""
        a = _finite_vector(a, (7,), "pose 7-vector")
        return cls(a[:3], a[3:])

    @classmethod
    def from_rotation(cls, position, rotation: Rotation) -> Pose:
        return cls(position, rotation.as_quat())

    def to_array(self) -> np.ndarray:
        """(7,) ``(x, y, z, qx, qy, qz, qw)``."""
        return np.concatenate([self.position, self.quaternion])

    @property
    def rotation(self) -> Rotation:
        return Rotation.from_quat(self.quaternion)

    def apply(self, local_points) -> np.ndarray:
        """Local -> sensor frame for (..., 3) points."""
        return (
            self.rotation.apply(np.asarray(local_points, dtype=np.float64).reshape(-1, 3)).reshape(
                np.shape(local_points)
            )
            + self.position
        )

    def inverse_apply(self, points) -> np.ndarray:
        """Sensor -> local frame for (..., 3) points."""
        p = np.asarray(points, dtype=np.float64)
        return self.rotation.inv().apply((p - self.position).reshape(-1, 3)).reshape(p.shape)

    def __repr__(self) -> str:
        return f"Pose(position={self.position.tolist()}, quaternion={self.quaternion.tolist()})"


# --------------------------------------------------------------------------- indenters
@dataclass(frozen=True, eq=False, kw_only=True)
class Indenter:
    """A rigid body with a local shape and a pose. Subclasses define the shape."""

    kind: ClassVar[str] = ""
    pose: Pose = field(default_factory=Pose)

    def __post_init__(self):
        if not isinstance(self.pose, Pose):
            raise IndenterError(f"pose must be a Pose, got {type(self.pose).__name__}")
        for name in self._dimension_names():
            value = getattr(self, name)
            if not np.isscalar(value) or not np.isfinite(value) or value <= 0:
                raise IndenterError(
                    f"{type(self).__name__}.{name} must be a finite length > 0 m, got {value!r}"
                )

    def _dimension_names(self) -> tuple[str, ...]:
        return ()

    def with_pose(self, pose: Pose) -> Indenter:
        return replace(self, pose=pose)

    def local_signed_distance(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def local_trimesh(self):
        raise NotImplementedError

    def signed_distance(self, points) -> np.ndarray:
        """Signed distance [m] of sensor-frame points (..., 3) to the surface, negative inside."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise IndenterError(f"points must have shape (..., 3), got {p.shape}")
        return self.local_signed_distance(self.pose.inverse_apply(p).reshape(-1, 3)).reshape(p.shape[:-1])

    def trimesh(self):
        """The surface as a :class:`trimesh.Trimesh` in the sensor frame (for contact and rendering)."""
        mesh = self.local_trimesh()
        mesh.vertices = self.pose.apply(mesh.vertices)
        return mesh

    def lowest_z(self) -> float:
        """Lowest sensor-frame z of the body [m] (exact for the analytic shapes)."""
        return float(self.trimesh().vertices[:, 2].min())


@dataclass(frozen=True, eq=False, kw_only=True)
class SphereIndenter(Indenter):
    """Rigid sphere of radius ``radius`` [m] centred at the pose origin."""

    kind: ClassVar[str] = "sphere"
    radius: float = 0.005

    def _dimension_names(self):
        return ("radius",)

    def local_signed_distance(self, p):
        return np.linalg.norm(p, axis=-1) - self.radius

    def local_trimesh(self):
        import trimesh

        return trimesh.creation.icosphere(subdivisions=3, radius=self.radius)

    def lowest_z(self) -> float:
        return float(self.pose.position[2] - self.radius)


@dataclass(frozen=True, eq=False, kw_only=True)
class CapsuleIndenter(Indenter):
    """Capsule: the segment ``x in [-length/2, length/2]`` (local x axis) swept by a sphere of ``radius``."""

    kind: ClassVar[str] = "capsule"
    radius: float = 0.04
    length: float = 0.20

    def _dimension_names(self):
        return ("radius", "length")

    def local_signed_distance(self, p):
        h = 0.5 * self.length
        nearest = np.stack(
            [np.clip(p[..., 0], -h, h), np.zeros(p.shape[:-1]), np.zeros(p.shape[:-1])], axis=-1
        )
        return np.linalg.norm(p - nearest, axis=-1) - self.radius

    def local_trimesh(self):
        import trimesh

        mesh = trimesh.creation.capsule(height=self.length, radius=self.radius, count=[32, 32])
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # z -> x axis
        return mesh

    def lowest_z(self) -> float:
        h = 0.5 * self.length
        ends = self.pose.apply(np.array([[-h, 0, 0], [h, 0, 0]]))
        return float(ends[:, 2].min() - self.radius)


@dataclass(frozen=True, eq=False, kw_only=True)
class BoxIndenter(Indenter):
    """Rectangular prism with edge lengths ``size_x, size_y, size_z`` [m], centred at the pose origin."""

    kind: ClassVar[str] = "box"
    size_x: float = 0.03
    size_y: float = 0.015
    size_z: float = 0.02

    def _dimension_names(self):
        return ("size_x", "size_y", "size_z")

    @property
    def half_extents(self) -> np.ndarray:
        return 0.5 * np.array([self.size_x, self.size_y, self.size_z])

    def local_signed_distance(self, p):
        q = np.abs(p) - self.half_extents
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)

    def local_trimesh(self):
        import trimesh

        return trimesh.creation.box(extents=2 * self.half_extents)

    def lowest_z(self) -> float:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        return float(self.pose.apply(corners * self.half_extents)[:, 2].min())


@dataclass(frozen=True, eq=False, kw_only=True)
class RingIndenter(Indenter):
    """Hollow cylinder about local z, radii ``inner_radius < outer_radius``, centred at the origin."""

    kind: ClassVar[str] = "ring"
    outer_radius: float = 0.015
    inner_radius: float = 0.010
    height: float = 0.02

    def _dimension_names(self):
        return ("outer_radius", "inner_radius", "height")

    def __post_init__(self):
        super().__post_init__()
        if self.inner_radius >= self.outer_radius:
            raise IndenterError(
                f"ring needs inner_radius < outer_radius, got {self.inner_radius} >= {self.outer_radius}"
            )

    def local_signed_distance(self, p):
        rho = np.linalg.norm(p[..., :2], axis=-1)
        mid, half_w = (
            0.5 * (self.outer_radius + self.inner_radius),
            0.5 * (self.outer_radius - self.inner_radius),
        )
        q = np.stack([np.abs(rho - mid) - half_w, np.abs(p[..., 2]) - 0.5 * self.height], axis=-1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)

    def local_trimesh(self):
        import trimesh

        return trimesh.creation.annulus(
            r_min=self.inner_radius, r_max=self.outer_radius, height=self.height, sections=64
        )

    def lowest_z(self) -> float:
        # the lowest point of a rim circle of radius R_o at local z = +-h/2: c_z - R_o |sin(tilt)| - h/2 |cos|
        axis = self.pose.rotation.apply([0.0, 0.0, 1.0])
        radial = np.sqrt(max(0.0, 1.0 - axis[2] ** 2))
        return float(self.pose.position[2] - self.outer_radius * radial - 0.5 * self.height * abs(axis[2]))


#: The kinds stored in the tactile datasets, mapped to their classes.
INDENTER_KINDS: dict[str, type[Indenter]] = {
    cls.kind: cls for cls in (SphereIndenter, CapsuleIndenter, BoxIndenter, RingIndenter)
}


def make_indenter(kind: str, **dimensions) -> Indenter:
    """Build an indenter by its dataset kind (``"sphere"``, ``"capsule"``, ``"box"``, ``"ring"``)."""
    if kind not in INDENTER_KINDS:
        raise IndenterError(f"unknown indenter kind {kind!r}; known: {sorted(INDENTER_KINDS)}")
    return INDENTER_KINDS[kind](**dimensions)


#: §3.3: "A rigid sphere 1 cm in diameter printed from PLA ... an approximate duplicate of an average
#: human fingertip".
FINGERTIP = SphereIndenter(radius=0.005)
#: §2.3-2.4: contact spheres of diameters 10, 20 and 30 mm.
CONTACT_SPHERES = {d: SphereIndenter(radius=d / 2000.0) for d in (10, 20, 30)}
#: §2.3 rectangular prism (dimensions assumed, see the module docstring).
RECTANGULAR_PRISM = BoxIndenter()
#: §2.3 ring (dimensions assumed).
RING = RingIndenter()
#: Forearm-like capsule, 8 cm wide and 28 cm long overall (assumed).
FOREARM = CapsuleIndenter(radius=0.04, length=0.20)


# --------------------------------------------------------------------------- workspace
def check_workspace(indenter: Indenter, dimensions: MembraneDimensions, clearance: float = 0.0) -> None:
    """Raise :class:`WorkspaceError` if the indenter reaches below the clamped rim plane.

    Below ``z_rim`` lies the rigid housing (and the membrane's clamped rim): an indenter there would
    push beyond the sensor's rim, a pose the experiments never visit and the FEM model does not cover.
    """
    lowest = indenter.lowest_z()
    limit = dimensions.z_rim + clearance
    if lowest < limit:
        raise WorkspaceError(
            f"{indenter.kind} indenter reaches z = {lowest:.4f} m, below the clamped rim plane "
            f"z_rim + clearance = {limit:.4f} m: the pose lies beyond the sensor rim"
        )


def _finite_fields(obj, names) -> None:
    for name in names:
        value = getattr(obj, name)
        if not np.isscalar(value) or not np.isfinite(value):
            raise IndenterError(f"{type(obj).__name__}.{name} must be a finite number, got {value!r}")


@dataclass(frozen=True)
class PokeCommand:
    """One state of the finger-poking experiment (§3.3, Figs. 3.2-3.3).

    The indenter first touches the outer hemisphere at the contact point above radius
    ``contact_radius`` from the axis on the meridian at azimuth ``phi``, then moves a distance
    ``depth`` (delta) along the direction tilted by ``theta`` from -z within that meridian plane,
    towards the axis: ``d = -(sin theta e_rho(phi) + cos theta e_z)`` (the text does not give the
    tilt sense; towards the axis covers the inward surface normal at theta = asin(rho / R_o)).

    Args:
        phi: meridian azimuth [rad] (thesis: pi j / 20, j = 0..39).
        contact_radius: rho [m] (thesis: 0..4 cm in 1 cm steps, "leaving enough of a distance from the
            base of the hemisphere so that boundary contact conditions can be avoided").
        theta: tilt from the sensor axis [rad], 0..pi/2 (thesis: pi k / 18, k = 0..9).
        depth: delta [m] >= 0 (thesis: 0.5..2.5 cm).
    """

    phi: float
    contact_radius: float
    theta: float
    depth: float

    #: The thesis's largest contact radius [m]; commands beyond it are rejected by default.
    max_contact_radius: ClassVar[float] = 0.04

    def __post_init__(self):
        _finite_fields(self, ("phi", "contact_radius", "theta", "depth"))
        if not 0.0 <= self.theta <= np.pi / 2 + 1e-12:
            raise IndenterError(f"theta must be in [0, pi/2] rad, got {self.theta!r}")
        if self.depth < 0:
            raise IndenterError(f"indentation depth must be >= 0 m, got {self.depth!r}")
        if self.contact_radius < 0:
            raise IndenterError(f"contact radius must be >= 0 m, got {self.contact_radius!r}")

    def direction(self) -> np.ndarray:
        """(3,) unit indentation direction in the sensor frame."""
        e_rho = np.array([np.cos(self.phi), np.sin(self.phi), 0.0])
        return -(np.sin(self.theta) * e_rho + np.cos(self.theta) * np.array([0.0, 0.0, 1.0]))

    def indenter_pose(
        self,
        dimensions: MembraneDimensions,
        indenter: SphereIndenter,
        max_contact_radius: float | None = None,
    ) -> Pose:
        """Pose of a spherical indenter for this command; checks the workspace.

        The sphere touches the undeformed outer surface at the contact point ``p`` (centre
        ``p + r n``) and moves by ``depth * d``.

        Raises:
            WorkspaceError: contact point beyond ``max_contact_radius`` (default: the thesis's 4 cm),
                a direction pointing out of the membrane, or a final pose below the rim plane.
        """
        if not isinstance(indenter, SphereIndenter):
            raise IndenterError(f"poking uses a sphere indenter, got {type(indenter).__name__}")
        limit = self.max_contact_radius if max_contact_radius is None else max_contact_radius
        if self.contact_radius > limit:
            raise WorkspaceError(
                f"contact radius {self.contact_radius:g} m exceeds the allowed {limit:g} m "
                f"(outer radius {dimensions.outer_radius:g} m): too close to the sensor rim"
            )
        p, n = dimensions.outer_surface_point(self.phi, self.contact_radius)
        d = self.direction()
        if self.depth > 0 and np.dot(d, n) >= 0:
            raise WorkspaceError(f"direction theta={self.theta:g} rad does not point into the membrane here")
        pose = Pose(p + indenter.radius * n + self.depth * d)
        check_workspace(indenter.with_pose(pose), dimensions)
        return pose


@dataclass(frozen=True)
class ForearmCommand:
    """One state of the forearm shearing / torquing experiment (§3.3, Fig. 3.5).

    The device indents the forearm by ``depth`` (measured at the pole), then either shears by
    ``shear_distance`` along the in-plane direction ``shear_direction`` or twists by ``twist`` about
    its axis. The parameters are the device's motion, as in the thesis; the forearm's pose in the
    sensor frame is the inverse relative motion: ``c = R_z(-psi) (c0 - s e(phi_s))``, orientation
    ``R_z(-psi)``, with ``c0 = (0, 0, z_pole + r - delta)`` and the forearm axis along sensor x.

    Args:
        depth: delta [m] >= 0 (thesis: m / 4 cm, m = 0..8).
        shear_direction: phi_s [rad] (thesis: 2 pi l / 40).
        shear_distance: s [m] >= 0 (thesis: 0.3..1.5 cm).
        twist: psi [rad], |psi| <= pi/3 (thesis: pi n / 24, n = 0..8, both senses).
    """

    depth: float
    shear_direction: float = 0.0
    shear_distance: float = 0.0
    twist: float = 0.0

    def __post_init__(self):
        _finite_fields(self, ("depth", "shear_direction", "shear_distance", "twist"))
        if self.depth < 0 or self.shear_distance < 0:
            raise IndenterError(
                f"depth and shear distance must be >= 0 m, got {self.depth!r}, {self.shear_distance!r}"
            )
        if abs(self.twist) > np.pi / 3 + 1e-12:
            raise IndenterError(
                f"twist must be within +-pi/3 rad (slip limit of the thesis), got {self.twist!r}"
            )

    def indenter_pose(self, dimensions: MembraneDimensions, forearm: CapsuleIndenter) -> Pose:
        """Pose of the forearm capsule for this command; checks the workspace."""
        if not isinstance(forearm, CapsuleIndenter):
            raise IndenterError(f"the forearm is a capsule indenter, got {type(forearm).__name__}")
        if self.depth > dimensions.outer_radius:
            raise WorkspaceError(
                f"forearm depth {self.depth:g} m exceeds the membrane's outer radius "
                f"{dimensions.outer_radius:g} m"
            )
        c0 = dimensions.outer_pole + np.array([0.0, 0.0, forearm.radius - self.depth])
        shear = self.shear_distance * np.array(
            [np.cos(self.shear_direction), np.sin(self.shear_direction), 0.0]
        )
        rot = Rotation.from_rotvec([0.0, 0.0, -self.twist])
        pose = Pose.from_rotation(rot.apply(c0 - shear), rot)
        check_workspace(forearm.with_pose(pose), dimensions)
        return pose


def poke_grid() -> list[PokeCommand]:
    """The 10,000 finger-poking states of §3.3: 40 phi x 5 rho x 10 theta x 5 delta."""
    return [
        PokeCommand(np.pi * j / 20, rho, np.pi * k / 18, delta)
        for j in range(40)
        for rho in np.linspace(0.0, 0.04, 5)
        for k in range(10)
        for delta in np.linspace(0.005, 0.025, 5)
    ]


def forearm_grid() -> list[ForearmCommand]:
    """Forearm states of §3.3: shears (40 phi x 5 s x 9 delta) then twists (2 senses x 9 psi x 9 delta).

    The thesis reports 1726 states per repetition; its text does not say which of these 1962
    combinations were skipped.
    """
    depths = [m / 400.0 for m in range(9)]
    shears = [
        ForearmCommand(delta, 2 * np.pi * l / 40, s)
        for delta in depths
        for l in range(40)
        for s in np.linspace(0.003, 0.015, 5)
    ]
    twists = [
        ForearmCommand(delta, twist=sign * np.pi * n / 24)
        for delta in depths
        for sign in (1, -1)
        for n in range(9)
    ]
    return shears + twists
