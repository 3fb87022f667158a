"""Fast membrane model for closed-loop tactile simulation, calibrated against the FEM sensor.

The FEM sensor (:class:`defgraspnets.tactile.sensor.MembraneSimulator`) needs seconds per state, too
slow inside a contour-following loop of hundreds of steps. This model replaces only the *mechanics*:
given the sensor pose and a rigid scene (a :class:`~defgraspnets.tactile.sdf.SignedDistance`), it
returns the deformed membrane vertices and the contact force; the observation pipeline stays the real
one (the interior :class:`~defgraspnets.tactile.camera.DepthCamera` renders the deformed inner surface,
:func:`~defgraspnets.tactile.contact_regions.deformed_points` and
:func:`~defgraspnets.tactile.force_models.depth_force_proxy` read it).

Kinematics. The shell mesh is a sweep of its inner surface through the thickness
(:func:`~defgraspnets.tactile.membrane.build_membrane`), so vertex ``k S + s`` (layer k) lies above
inner vertex s. Each *column* s moves rigidly by one displacement ``u_s`` (the thickness is preserved).
Starting from the FEM-inflated reference ``X`` (sensor frame), with the outer vertex ``y_s = X_s^o + u_s``
mapped to the world by the sensor pose ``x_s = R y_s + p``:

1. contact (active set C): a column whose outer vertex penetrates the scene, ``phi(x_s) < 0``, joins C
   and is pushed inward along its reference membrane normal ``-n_s`` until it leaves the object,
   ``u_s <- u_s - t_s n_s`` with ``phi(R (y_s - t_s n_s) + p) = 0`` (sphere tracing from inside);
2. the free columns follow the linearized, pre-tensioned membrane: a *screened* membrane equation
   on the reference inner surface, discretized with the cotangent Laplacian K and lumped areas M,

       (K + M / l^2) u_F = -(K + M / l^2)_FC u_C,       u = 0 on the clamped rim,

   whose solution decays away from the contact over the screening length ``l`` (membrane tension
   against the stiffness of the curved, pressurized shell and of bending; l is calibrated);
3. repeat 1-2 until no outer vertex penetrates (a few iterations).

Sub-vertex contact (``contact_samples_per_face = m > 0``, ``m = (n + 1)(n + 2) / 2``). The vertex-wise
contact above sees an object only where a *vertex* penetrates it: a feature narrower than the mesh spacing
h (3.9 mm at the pole of the 20-division membrane) is missed or read in steps of h. Instead, contact is
tested at m sample points on each outer triangle f = (a, b, c), the grid points of its uniform
n-subdivision (corners included, :func:`subdivision_points`), with barycentric weights ``beta_qa`` and
lumped shares of the triangle's area (summing to ``A_f``); a sample moves with its triangle's columns,
``y_q = sum_a beta_qa (X_a^o + u_a)``. The membrane carries frictionless contact loads along the columns'
inward directions ``d_a = -n_a``: a load ``mu_a`` at column a (normalized by the membrane tension, [m])
displaces every column through the screened-membrane Green's function ``G = A^-1`` (A the operator above
on the unclamped columns, applied to each Cartesian component),

    u = G D mu,      w_K = C_KK mu_K,      C_ab = G_ab (d_a . d_b),

where ``w_a = d_a . u_a`` is the normal displacement of column a and K the loaded columns (of the
triangles with a constrained sample). A loaded column moves freely in the tangent directions
(frictionless), so no column jumps when a sample enters or leaves the contact. The loads minimize the
membrane energy ``1/2 u^T A u = 1/2 w_K^T C_KK^-1 w_K`` subject to an obstacle condition at the samples
that penetrate the scene in the reference state,

    w_q = sum_a beta_qa (d_q . d_a) w_a >= psi_q,

``d_q`` the normalized interpolation of the columns' ``d_a`` and ``psi_q`` the sample's exit depth along
``d_q`` (sphere tracing, with bisection where the ray runs along a face; as step 1 for a vertex). With an
edge radius r > 0 the obstacle ramps to zero within r of an edge,
``psi_q = t_q min(1, e_q / min(r, t_q / 2))`` with ``e_q = -phi(y_q)`` the distance to the nearest face
(``t_q cos(theta)`` away from edges, theta the exit face's angle to ``d_q``, so faces inclined by less than
60 deg and smooth objects keep ``psi_q = t_q``), a rounding of the object's edges at the scale of the
membrane's thickness that the coarse piecewise-linear surface can follow. This is a least-distance program in
``z = L^-1 w_K`` (``C_KK = L L^T``), solved exactly by non-negative least squares (Lawson and Hanson, ch.
23). Samples that the deformed membrane pushes into the scene (e.g. a flank moved into a side face) are
added with ``psi_q = w_q + t_q`` and the program is solved again (at most ``max_iterations`` passes). The
samples with an obstacle condition are *in contact* (as the columns that penetrated in the vertex-wise
model; n = 1 gives the same set) and a column is in contact when it carries load. The contact area ``A_C``
is the area of the reference surface inside the scene, ``phi`` interpolated linearly on the n^2
sub-triangles of each triangle (:func:`negative_area_fraction`; continuous in the object's pose), plus the
area shares of the samples added by later passes. ``m = 0`` keeps the vertex-wise model above, the
default (measured in ``benchmarks/fast_membrane_subvertex_cpu.md``: the sub-vertex contact does not improve
the closed loops).

The state is path independent (no friction history), so every pose is solved from scratch.

Force. The normal force is a linear model in the two quantities that carry the load of a
pressurized membrane: the displaced gas volume ``dV = V_ref - V`` (closed capsule: the gas pressure
rises with it; tension of the stretched membrane) and the contact area ``A_C`` (the gas pressure acts on
it),

    F_n = k_V dV + k_A A_C,

directed against the area-weighted object normal over the contact (``A_C``: the lumped outer areas of
the contact columns; with sub-vertex contact see above, and the normals weighted by area share times
obstacle depth ``psi_q``, so that the rim of the contact enters continuously); ``k_V``
[N/m^3], ``k_A`` [Pa] and ``l`` [m] are fitted to the FEM sensor (:func:`calibrate`,
``scripts/calibrate_fast_membrane.py``).
:data:`DEFAULT_CALIBRATION` holds the constants with their provenance and measured error.

Limits: no friction (tangential load, shear of the membrane), no dynamics, no self-contact; the
projection assumes a penetration much smaller than the object's curvature radius from the far side
(:attr:`FastMembraneState.max_displacement` is reported; the closed loop rejects deep states).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from defgraspnets.fem.bodies import check_rigid_transform
from defgraspnets.tactile.force_models import depth_force_proxy
from defgraspnets.tactile.membrane import MembraneSensor, enclosed_volume
from defgraspnets.tactile.sdf import SignedDistance

__all__ = [
    "DEFAULT_CALIBRATION",
    "FastMembrane",
    "FastMembraneCalibration",
    "FastMembraneState",
    "calibrate",
    "calibration_summary",
    "contact_depth_proxy",
    "cotangent_laplacian",
    "depth_change_error",
    "fem_samples",
    "indenter_scene",
    "least_distance_multipliers",
    "negative_area_fraction",
    "run_fem_calibration",
    "subdivision_points",
]


@dataclass(frozen=True)
class FastMembraneCalibration:
    """Constants of the fast model and where they came from.

    Attributes:
        screening_length: ``l`` [m], decay length of the free membrane's deflection.
        volume_stiffness: ``k_V`` [N/m^3].
        area_pressure: ``k_A`` [Pa].
        provenance: how the constants were obtained (FEM configuration, samples, errors).
    """

    screening_length: float
    volume_stiffness: float
    area_pressure: float
    provenance: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if not (np.isfinite(self.screening_length) and self.screening_length > 0):
            raise ValueError(f"screening_length must be > 0 m, got {self.screening_length!r}")
        for name in ("volume_stiffness", "area_pressure"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")

    def to_dict(self) -> dict:
        return asdict(self)


#: Output of ``python scripts/calibrate_fast_membrane.py`` (defaults; 154 s on a shared 2-core AMD EPYC),
#: copied verbatim. FEM: ``make_simulator`` on ``build_membrane(cap_divisions=8, layers=2)``, 1500 Pa, sealed,
#: friction 0.5, pico flexx at half resolution; 16 readings: sphere r = 10 mm (pole, 25 deg off axis) and a
#: 0.5" pipe (capsule r = 6.35 mm, L = 120 mm; pole, turned 30 deg 10 mm off axis) at 2.5/5/7.5/10 mm.
#: Fast model on ``cap_divisions=12`` (FEM-inflated, 1500 Pa). Errors of this fit (all 16 samples):
#: force RMS 0.115 N (mean 10 %, max 33 % relative, the max at the 2.5 mm sphere); depth-change RMS
#: 1.06 mm (max 1.78 mm at 10 mm of pipe); indented-pixel F~ (:func:`contact_depth_proxy`) mean 34 %
#: low (max 67 %, at 2.5-5 mm). Fit on the spheres only, tested on the pipes: force RMS 0.26 N (max 50 %).
#: Pearson r of the FEM force against the FEM's indented-pixel F~: 0.996; against the plain F~ of
#: eq. (4.6): -0.99 (the sealed gas bulges the free membrane, see :func:`contact_depth_proxy`).
#: Re-run in session 16 with the FEM's smoothed contact onset (1e-2 h, the default since session 15; 34 s
#: on the 2-core CPU): the same screening length, volume stiffness and area pressure within 0.05 % and
#: 0.4 %, force RMS 0.114 N, depth-change RMS 1.05 mm (benchmarks/fast_membrane_calibration_smoothed_onset
#: .json), so these constants stand.
DEFAULT_CALIBRATION = FastMembraneCalibration(
    screening_length=0.02215673192244301,
    volume_stiffness=133781.31439741084,
    area_pressure=822.7557552862826,
    provenance={
        "source": "scripts/calibrate_fast_membrane.py (defaults)",
        "fem": "cap_divisions=8, layers=2, 1500 Pa sealed, friction 0.5, camera pico flexx x0.5",
        "fast_model_cap_divisions": 12,
        "samples": "sphere r=10 mm x2 poses, capsule r=6.35 mm x2 poses; depths 2.5, 5, 7.5, 10 mm",
        "force_rms_error_N": 0.11469617519477766,
        "force_max_relative_error": 0.33126397452882245,
        "depth_change_rms_error_m": 0.0010560677640808426,
        "depth_change_max_rms_error_m": 0.0017752295088655939,
        "contact_depth_proxy_mean_relative_error": 0.33687817318808505,
        "cross_shape_force_rms_error_N": 0.26448132627379034,
        "fem_pearson_r_force_vs_contact_depth_proxy": 0.9955528621420957,
        "fem_pearson_r_force_vs_plain_depth_proxy": -0.9915659426477239,
    },
)


def cotangent_laplacian(points: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Cotangent stiffness matrix K (V, V) (positive semi-definite) and lumped vertex areas (V,) [m^2].

    ``K_ij = -(cot a_ij + cot b_ij) / 2`` for the edge ij opposite the angles a, b; ``K_ii = -sum_j K_ij``;
    lumped area = one third of the adjacent triangles' areas. Only vertices used by ``faces`` get
    non-zero rows.
    """
    x = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if x.ndim != 2 or x.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"need points (V, 3) and faces (F, 3), got {x.shape}, {f.shape}")
    n = x.shape[0]
    rows, cols, vals = [], [], []
    area = 0.5 * np.linalg.norm(np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]), axis=1)
    if (area <= 0).any():
        raise ValueError("degenerate (zero-area) triangle in the surface")
    for k in range(3):
        i, j, o = f[:, (k + 1) % 3], f[:, (k + 2) % 3], f[:, k]  # edge ij opposite vertex o
        a, b = x[i] - x[o], x[j] - x[o]
        cot = (a * b).sum(axis=1) / np.linalg.norm(np.cross(a, b), axis=1)
        w = 0.5 * cot
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-w, -w, w, w]
    k_mat = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    mass = np.zeros(n)
    np.add.at(mass, f.ravel(), np.repeat(area / 3.0, 3))
    return k_mat.tocsr(), mass


@dataclass(frozen=True)
class FastMembraneState:
    """One solved state of the fast model.

    Attributes:
        positions: (N, 3) deformed membrane vertices, sensor frame [m].
        column_displacement: (S, 3) displacement of each column, sensor frame [m].
        contact_columns: (S,) bool, columns in contact with the scene.
        normal_force: ``F_n`` [N] (0 without contact).
        contact_force: (3,) force the membrane exerts on the scene, world [N].
        displaced_volume: ``dV`` [m^3].
        contact_area: ``A_C`` [m^2].
        max_displacement: largest column displacement [m].
        residual_penetration: deepest remaining penetration of an outer vertex [m] (>= 0).
        clamped_contact: whether a clamped (rigid) rim column penetrates the scene.
        iterations: active-set (vertex-wise) or sequential-QP (sub-vertex) iterations used.
        solve_time: wall time [s].
        contact_points: (P, 3) the contact samples, sensor frame [m] (sub-vertex contact; the outer
            vertices of the contact columns for the vertex-wise model).
        column_load: (S,) contact load of each column along its inward direction, normalized by the
            membrane tension [m] (sub-vertex contact; None for the vertex-wise model).
    """

    positions: np.ndarray
    column_displacement: np.ndarray
    contact_columns: np.ndarray
    normal_force: float
    contact_force: np.ndarray
    displaced_volume: float
    contact_area: float
    max_displacement: float
    residual_penetration: float
    clamped_contact: bool
    iterations: int
    solve_time: float
    contact_points: np.ndarray | None = None
    column_load: np.ndarray | None = None

    @property
    def in_contact(self) -> bool:
        return bool(self.contact_columns.any())


class FastMembrane:
    """The fast model on one membrane mesh (see the module docstring).

    Args:
        sensor: the membrane mesh (:func:`~defgraspnets.tactile.membrane.build_membrane`).
        reference_positions: (N, 3) inflated (pre-contact) vertex positions, sensor frame [m], e.g.
            ``MembraneSimulator(...).reference.positions`` (the FEM inflation of the same mesh).
        calibration: the model constants (default :data:`DEFAULT_CALIBRATION`).
        tolerance: penetration accepted as contact resolution [m].
        max_iterations: active-set (vertex-wise) or sequential-QP (sub-vertex) iterations.
        contact_samples_per_face: ``m``: 0 for the vertex-wise contact, else ``(n + 1)(n + 2) / 2`` (3, 6,
            10, 15, ...) contact samples on each outer triangle, the grid of its n-subdivision (sub-vertex
            contact, module docstring).
        contact_margin: sub-vertex contact: faces whose vertices are farther from the scene than this plus
            their longest edge [m] are not sampled.
        contact_edge_radius: sub-vertex contact: ``r`` [m], the obstacle ramps to zero over this distance
            from an object's edge (module docstring); 0 keeps the edges sharp.
    """

    def __init__(
        self,
        sensor: MembraneSensor,
        reference_positions,
        calibration: FastMembraneCalibration = DEFAULT_CALIBRATION,
        tolerance: float = 1.0e-5,
        max_iterations: int = 8,
        contact_samples_per_face: int = 0,
        contact_margin: float = 5.0e-4,
        contact_edge_radius: float = 0.0,
    ):
        if not isinstance(sensor, MembraneSensor):
            raise TypeError(f"sensor must be a MembraneSensor, got {type(sensor).__name__}")
        ref = np.asarray(reference_positions, dtype=np.float64)
        if ref.shape != sensor.mesh.points.shape or not np.isfinite(ref).all():
            raise ValueError(f"reference_positions must be finite with shape {sensor.mesh.points.shape}")
        if not isinstance(calibration, FastMembraneCalibration):
            raise TypeError("calibration must be a FastMembraneCalibration")
        if not tolerance > 0 or int(max_iterations) < 1:
            raise ValueError("tolerance must be > 0 m and max_iterations >= 1")
        self.sensor = sensor
        self.calibration = calibration
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        n = ref.shape[0]
        layers = sensor.layers
        if n % (layers + 1):
            raise ValueError(
                "the membrane mesh is not a swept shell (vertex count not a multiple of layers + 1)"
            )
        s = n // (layers + 1)
        if not np.array_equal(sensor.vertex_layer, np.repeat(np.arange(layers + 1), s)):
            raise ValueError("the membrane mesh is not a swept shell (vertex_layer is not layer-major)")
        if sensor.inner_faces.max() >= s:
            raise ValueError("inner faces must use layer-0 vertices only")
        self.num_columns = s
        self.reference = ref
        self.inner_reference = ref[:s]
        self.outer_reference = ref[layers * s : (layers + 1) * s]
        normal = self.outer_reference - self.inner_reference
        #: (S, 3) unit inward direction of each column (sensor frame): the membrane is pressed along it
        self.inward = -normal / np.linalg.norm(normal, axis=1, keepdims=True)
        self.clamped = np.zeros(s, dtype=bool)
        self.clamped[np.unique(sensor.clamped_vertices % s)] = True
        stiffness, inner_area = cotangent_laplacian(self.inner_reference, sensor.inner_faces)
        ratio = (sensor.dimensions.outer_radius / sensor.dimensions.inner_radius) ** 2
        self.outer_area = inner_area * ratio  # lumped outer-surface areas (thin shell) [m^2]
        self.operator = (stiffness + sp.diags(inner_area / calibration.screening_length**2)).tocsc()
        self.reference_volume = enclosed_volume(ref, sensor.inner_faces, sensor.rim_center)
        self.contact_samples_per_face = int(contact_samples_per_face)
        self.contact_margin = float(contact_margin)
        self.contact_edge_radius = float(contact_edge_radius)
        if not self.contact_margin >= 0:
            raise ValueError(f"contact_margin must be >= 0 m, got {contact_margin}")
        if self.contact_samples_per_face:
            self._setup_samples(self.contact_samples_per_face)

    def with_calibration(self, calibration: FastMembraneCalibration) -> FastMembrane:
        """The same mesh, reference and contact options with other constants."""
        return FastMembrane(
            self.sensor,
            self.reference,
            calibration,
            self.tolerance,
            self.max_iterations,
            self.contact_samples_per_face,
            self.contact_margin,
            self.contact_edge_radius,
        )

    # ------------------------------------------------------------------ sub-vertex contact set-up
    def _setup_samples(self, m: int) -> None:
        """Sample layout, areas and the (lazily filled) Green's function of the sub-vertex contact."""
        n = int(round((np.sqrt(8 * max(m, 0) + 1) - 3) / 2))
        if n < 1 or (n + 1) * (n + 2) // 2 != m:
            raise ValueError(
                f"contact_samples_per_face must be 0 or (n + 1)(n + 2) / 2 (3, 6, 10, 15, ...), got {m}"
            )
        self.contact_subdivisions = n
        self.sample_barycentric, share, self._sub_triangles = subdivision_points(n)  # (m, 3), (m,), (n^2, 3)
        faces = np.asarray(self.sensor.inner_faces, dtype=np.int64)  # column indices (layer 0)
        movable = ~self.clamped
        self.sample_faces = faces[movable[faces].any(axis=1)]  # faces with at least one movable column
        x = self.outer_reference[self.sample_faces]
        face_area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        self.sample_face_area = face_area  # (F,) outer reference triangle areas [m^2]
        #: (F, m) area each contact sample stands for, outer reference surface [m^2]
        self.sample_area = face_area[:, None] * share[None, :]
        self._movable_index = np.full(self.num_columns, -1)
        self._movable_index[movable] = np.arange(movable.sum())
        a = self.operator[movable][:, movable].tocsc()
        self._green_factor = splu(a)
        self._green = np.zeros((self.num_columns, self.num_columns))  # G[:, j], filled on demand
        self._green_done = np.zeros(self.num_columns, dtype=bool)

    def _green_columns(self, cols: np.ndarray) -> np.ndarray:
        """(S, k) columns ``G[:, cols]`` of the screened-membrane Green's function (0 on the clamped rim)."""
        missing = cols[~self._green_done[cols]]
        if missing.size:
            movable = ~self.clamped
            rhs = np.zeros((int(movable.sum()), missing.size))
            rhs[self._movable_index[missing], np.arange(missing.size)] = 1.0
            sol = self._green_factor.solve(rhs)
            block = np.zeros((self.num_columns, missing.size))
            block[movable] = sol
            self._green[:, missing] = block
            self._green_done[missing] = True
        return self._green[:, cols]

    # ------------------------------------------------------------------ mechanics
    def _extend(self, u: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """Screened-membrane extension of the displacements of the ``fixed`` columns to the free ones."""
        free = ~fixed
        if not free.any():
            return u
        a = self.operator
        a_ff = a[free][:, free]
        rhs = -(a[free][:, fixed] @ u[fixed])
        out = u.copy()
        out[free] = splu(a_ff.tocsc()).solve(rhs)
        return out

    def _exit_depth(self, scene: SignedDistance, points, directions, phi) -> np.ndarray:
        """Distance along each unit direction [m] from a point inside the scene to its first exit.

        Sphere tracing: inside the solid ``|phi|`` is the distance to the nearest surface, so a step of
        ``|phi|`` never overshoots the exit; it converges where the ray meets the surface transversally.
        """
        t = np.zeros(points.shape[0])
        d = -np.asarray(phi, dtype=np.float64)
        for _ in range(64):
            active = d > 0.1 * self.tolerance
            if not active.any():
                break
            t[active] += np.maximum(d[active], 0.1 * self.tolerance)
            d[active] = -scene.distance(points[active] + t[active, None] * directions[active])
        return t

    def solve(self, scene: SignedDistance, sensor_pose) -> FastMembraneState:
        """Deformed membrane and contact force for the sensor at ``sensor_pose`` (world <- sensor)."""
        if not isinstance(scene, SignedDistance):
            raise TypeError(f"scene must be a SignedDistance, got {type(scene).__name__}")
        pose = check_rigid_transform(sensor_pose, "sensor_pose", single=True)
        rot, pos = pose[:3, :3], pose[:3, 3]
        t0 = time.perf_counter()
        if self.contact_samples_per_face:
            return self._solve_subvertex(scene, rot, pos, t0)
        s = self.num_columns
        u = np.zeros((s, 3))
        contact = np.zeros(s, dtype=bool)
        iterations = 0
        for iterations in range(1, self.max_iterations + 1):  # noqa: B007 (the count is reported)
            world = (self.outer_reference + u) @ rot.T + pos
            phi, grad = scene.evaluate(world)
            pen = (phi < -self.tolerance) & ~self.clamped
            if not pen.any():
                break
            contact |= pen
            depth = self._exit_depth(scene, world[pen], self.inward[pen] @ rot.T, phi[pen])
            u[pen] += depth[:, None] * self.inward[pen]
            u = self._extend(u, contact | self.clamped)
        world = (self.outer_reference + u) @ rot.T + pos
        phi, grad = scene.evaluate(world)
        residual = float(max(0.0, -phi[~self.clamped].min())) if (~self.clamped).any() else 0.0
        clamped_contact = bool((phi[self.clamped] < 0).any())

        return self._state(
            u,
            contact_columns=contact,
            area=float(self.outer_area[contact].sum()),
            in_contact=bool(contact.any()),
            normal_weights=self.outer_area[contact],
            normals=grad[contact],
            residual=residual,
            clamped_contact=clamped_contact,
            iterations=iterations,
            t0=t0,
            contact_points=self.outer_reference[contact] + u[contact],
        )

    def _state(
        self, u, contact_columns, area, in_contact, normal_weights, normals, residual, clamped_contact,
        iterations, t0, contact_points, column_load=None,
    ) -> FastMembraneState:  # fmt: skip
        """The state of column displacements ``u``: the swept shell's positions, the displaced gas volume
        and the force model ``F_n = k_V dV + k_A A_C``, directed against the object normals (``normals``,
        world frame) averaged with ``normal_weights`` over the contact."""
        positions = self.reference + np.tile(u, (self.sensor.layers + 1, 1))
        volume = enclosed_volume(positions, self.sensor.inner_faces, self.sensor.rim_center)
        dv = max(0.0, self.reference_volume - volume)
        cal = self.calibration
        fn = cal.volume_stiffness * dv + cal.area_pressure * area if in_contact else 0.0
        force = np.zeros(3)
        if in_contact:
            n = (normal_weights[:, None] * normals).sum(axis=0)
            norm = np.linalg.norm(n)
            if norm > 0:
                force = -fn * n / norm  # the membrane pushes the object against its outward normal
        return FastMembraneState(
            positions=positions,
            column_displacement=u,
            contact_columns=contact_columns,
            normal_force=float(fn),
            contact_force=force,
            displaced_volume=float(dv),
            contact_area=area,
            max_displacement=float(np.linalg.norm(u, axis=1).max()),
            residual_penetration=residual,
            clamped_contact=clamped_contact,
            iterations=iterations,
            solve_time=time.perf_counter() - t0,
            contact_points=contact_points,
            column_load=column_load,
        )

    # ------------------------------------------------------------------ sub-vertex contact
    def _face_samples(self, scene: SignedDistance, rot, pos, u):
        """Faces that may touch the scene and their samples: (faces (Fc,), sensor-frame sample positions
        (Fc, m, 3) [m], signed distances (Fc, m) [m]).

        A face is skipped when ``min_a phi(y_a) - L_f >= contact_margin`` (L_f its longest deformed edge,
        which bounds the distance of any of its points to any of its vertices; phi is 1-Lipschitz)."""
        y = self.outer_reference + u
        yf = y[self.sample_faces]  # (F, 3, 3)
        phi_v = scene.distance(y @ rot.T + pos)[self.sample_faces].min(axis=1)
        edges = np.linalg.norm(yf - np.roll(yf, 1, axis=1), axis=2).max(axis=1)
        near = np.flatnonzero(phi_v - edges < self.contact_margin)
        yq = np.einsum("mk,fkd->fmd", self.sample_barycentric, yf[near])
        phi = scene.distance(yq.reshape(-1, 3) @ rot.T + pos).reshape(near.size, yq.shape[1])
        return near, yq, phi

    def _exit_along(self, scene: SignedDistance, points, directions, phi) -> np.ndarray:
        """Exit depth [m] along unit ``directions`` (world) from ``points`` inside the scene.

        Sphere tracing (:meth:`_exit_depth`), then, where it stalled (a point close to a surface that the
        ray runs along, e.g. just inside a box's side face while pushed toward its top) or did not start
        (a point on the surface), bisection between the last inside depth and a depth found outside by
        doubling a 1 mm step (0 when the ray leaves the solid at once)."""
        t = self._exit_depth(scene, points, directions, phi)
        # stalled: still inside, or never moved (a point on the surface, whose ray
        # may run along the face it lies on into the solid)
        stalled = (scene.distance(points + t[:, None] * directions) < -0.1 * self.tolerance) | (t == 0)
        if stalled.any():
            p, d = points[stalled], directions[stalled]
            lo, step = t[stalled], np.full(int(stalled.sum()), 1.0e-3)
            hi = lo + step
            for _ in range(8):
                inside = scene.distance(p + hi[:, None] * d) < 0
                if not inside.any():
                    break
                lo = np.where(inside, hi, lo)
                step = np.where(inside, 2 * step, step)
                hi = np.where(inside, hi + step, hi)
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                inside = scene.distance(p + mid[:, None] * d) < 0
                lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
            t[stalled] = hi
        return t

    def _rows(self, scene, rot, pos, faces, beta, y, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Non-penetration rows ``sum_a c_qa w_a >= psi_q`` of penetrating points (module docstring).

        ``faces`` (P,) index :attr:`sample_faces`, ``beta`` (P, 3) are the points' barycentric coordinates and
        ``y`` (P, 3) their sensor-frame positions at the displacement ``u``. Returns the columns (P, 3), the
        coefficients ``c_qa = beta_qa (d_q . d_a)`` (P, 3) (0 on the clamped rim) and ``psi_q = w_q + t_q``
        [m]: the sample's current normal displacement plus its exit depth along its inward direction."""
        cols = self.sample_faces[faces]
        d_cols = self.inward[cols]  # (P, 3, 3)
        d_q = np.einsum("pa,pad->pd", beta, d_cols)
        d_q /= np.linalg.norm(d_q, axis=1, keepdims=True)
        x = y @ rot.T + pos
        phi = scene.distance(x)
        t = self._exit_along(scene, x, d_q @ rot.T, phi)
        if self.contact_edge_radius > 0:
            # within r of another face than the exit face (an edge), the obstacle ramps to 0 at the edge:
            # psi = t min(1, e / min(r, t / 2)), e = -phi the distance to the nearest face (t cos(theta)
            # on the exit face, theta its angle to d_q: a face inclined by less than 60 deg keeps psi = t)
            e = np.maximum(-phi, 0.0)
            t = t * np.minimum(1.0, e / np.maximum(np.minimum(self.contact_edge_radius, 0.5 * t), 1e-12))
        coeff = beta * np.maximum(np.einsum("pd,pad->pa", d_q, d_cols), 0.0)
        coeff[self.clamped[cols]] = 0.0
        w = (u[cols] * d_cols).sum(axis=2)  # (P, 3) normal displacements of the columns
        return cols, coeff, (coeff * w).sum(axis=1) + t

    def _solve_subvertex(self, scene: SignedDistance, rot, pos, t0: float) -> FastMembraneState:
        """Sub-vertex contact: the membrane's normal loads by least-distance programs (module docstring)."""
        s = self.num_columns
        m = self.sample_barycentric.shape[0]
        u = np.zeros((s, 3))
        load = np.zeros(s)
        cols, coeff, psi = np.empty((0, 3), dtype=np.int64), np.empty((0, 3)), np.empty(0)
        sid = np.empty(0, dtype=np.int64)  # sample id (face * m + k) of each row
        iterations = 0
        solved = False
        area = 0.0
        for iterations in range(1, self.max_iterations + 1):  # noqa: B007 (the count is reported)
            faces, yq, phi = self._face_samples(scene, rot, pos, u)
            solved = False
            # the reference state: every point inside the scene; later passes: points without a row yet
            # that the deformed membrane pushes into the scene (e.g. a flank moved into a side face)
            pen = phi < (0.0 if iterations == 1 else -self.tolerance)
            if iterations > 1:
                pen &= ~np.isin(faces[:, None] * m + np.arange(m)[None, :], sid)
            if iterations == 1:  # the obstacle region's area, continuous in the object's pose
                frac = negative_area_fraction(phi[:, self._sub_triangles]).mean(axis=1)
                area = float((self.sample_face_area[faces] * frac).sum())
            if not pen.any():
                break
            f, k = np.nonzero(pen)
            if iterations > 1:  # points added by a later pass count with their area shares
                area += float(self.sample_area[faces[f], k].sum())
            c, cc, ps = self._rows(scene, rot, pos, faces[f], self.sample_barycentric[k], yq[f, k], u)
            keep = cc.sum(axis=1) > 0
            cols, coeff = np.concatenate([cols, c[keep]]), np.concatenate([coeff, cc[keep]])
            psi, sid = np.concatenate([psi, ps[keep]]), np.concatenate([sid, (faces[f] * m + k)[keep]])
            if psi.size == 0:
                break
            columns = np.unique(cols[coeff > 0])
            local = np.searchsorted(columns, cols).clip(max=columns.size - 1)
            jac = np.zeros((psi.size, columns.size))
            np.add.at(jac, (np.repeat(np.arange(psi.size), 3), local.ravel()), coeff.ravel())
            d = self.inward[columns]
            green = self._green_columns(columns)  # (S, k)
            chol = np.linalg.cholesky(green[columns] * (d @ d.T))  # C_KK = L L^T
            lam = least_distance_multipliers(jac @ chol, psi)
            load = np.zeros(s)
            load[columns] = jac.T @ lam  # mu_K = J^T lambda >= 0
            u = green @ (load[columns, None] * d)
            solved = True
        if solved:
            faces, yq, phi = self._face_samples(scene, rot, pos, u)
        # contact samples: those that penetrated the scene (the obstacle region; at n = 1 the vertex-wise
        # model's contact set)
        ids = (faces[:, None] * m + np.arange(m)[None, :]).ravel()
        touching = np.isin(ids, sid)
        points = yq.reshape(-1, 3)[touching]
        phi_v = scene.distance((self.outer_reference + u) @ rot.T + pos)
        movable = ~self.clamped
        residual = max(0.0, -float(phi.min()) if phi.size else 0.0)
        if movable.any():
            residual = max(residual, -float(phi_v[movable].min()))
        clamped_contact = bool((phi_v[self.clamped] < 0).any())

        in_contact = bool(touching.any()) and area > 0
        weight, grad = np.zeros(0), np.zeros((0, 3))
        if in_contact:
            # object normals weighted by area share x obstacle depth (the rim of the contact, psi -> 0,
            # enters continuously)
            grad = scene.evaluate(points @ rot.T + pos)[1]
            order = np.argsort(sid)
            unique, start = np.unique(sid[order], return_index=True)
            deepest = np.maximum.reduceat(psi[order], start)
            where = np.searchsorted(unique, ids[touching])
            weight = self.sample_area.ravel()[ids[touching]] * np.maximum(deepest[where], 0.0)
            if not weight.any():
                weight = self.sample_area.ravel()[ids[touching]]
        return self._state(
            u,
            contact_columns=load > 0,
            area=area,
            in_contact=in_contact,
            normal_weights=weight,
            normals=grad,
            residual=residual,
            clamped_contact=clamped_contact,
            iterations=iterations,
            t0=t0,
            contact_points=points,
            column_load=load,
        )

    def inner_surface(self, state: FastMembraneState) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the deformed inner surface for the depth camera (sensor frame)."""
        return self.sensor.inner_surface(state.positions)


def subdivision_points(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid points of a uniform n-subdivision of a triangle, their area shares and the sub-triangles.

    Returns the barycentric coordinates ``(i, j, n - i - j) / n`` ((n + 1)(n + 2) / 2, 3), corners first,
    each point's share of the triangle's area (lumped: one third of each of the n^2 sub-triangles it
    belongs to; corners 1 / (3 n^2), edge points 1 / n^2, interior points 2 / n^2; they sum to 1; n = 1
    gives the corners alone, with the lumped vertex areas of the vertex-wise contact) and the n^2
    sub-triangles as (n^2, 3) indices into the points."""
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    n = int(n)
    ij = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    bary = np.array([(i, j, n - i - j) for i, j in ij], dtype=np.float64) / n
    corners = (bary == 1.0).any(axis=1)
    edge = (bary == 0.0).any(axis=1) & ~corners
    share = np.where(corners, 1.0 / 3.0, np.where(edge, 1.0, 2.0)) / n**2
    order = np.argsort(~corners, kind="stable")
    where = {ij[k]: r for r, k in enumerate(order)}
    sub = [(where[i, j], where[i + 1, j], where[i, j + 1]) for i in range(n) for j in range(n - i)]
    sub += [
        (where[i + 1, j], where[i + 1, j + 1], where[i, j + 1])
        for i in range(n - 1)
        for j in range(n - 1 - i)
    ]
    return bary[order], share[order], np.array(sub, dtype=np.int64)


def negative_area_fraction(values) -> np.ndarray:
    """Fraction of a triangle where the linear interpolation of its corner ``values`` (..., 3) is < 0.

    With the sorted values ``v0 <= v1 <= v2``: 0 if ``v0 >= 0``; ``v0^2 / ((v0 - v1)(v0 - v2))`` if only
    ``v0 < 0``; ``1 - v2^2 / ((v2 - v0)(v2 - v1))`` if only ``v2 >= 0``; 1 if all are negative. It is
    continuous in the values, so an area measured with it moves continuously with the object."""
    v = np.sort(np.asarray(values, dtype=np.float64), axis=-1)
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    out = np.where(v2 < 0, 1.0, 0.0)
    one = (v0 < 0) & (v1 >= 0)
    two = (v1 < 0) & (v2 >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(one, v0**2 / ((v0 - v1) * (v0 - v2)), out)
        out = np.where(two, 1.0 - v2**2 / ((v2 - v0) * (v2 - v1)), out)
    return out


def least_distance_multipliers(matrix, bound) -> np.ndarray:
    """Multipliers ``lambda >= 0`` of the least-distance program ``min |z|^2 / 2`` s.t. ``E z >= f``.

    ``E`` is ``matrix`` (P, k), ``f`` is ``bound`` (P,); the solution is ``z = E^T lambda``. Lawson and
    Hanson's reduction to non-negative least squares (Solving Least Squares Problems, ch. 23):
    ``y = argmin_{y >= 0} |[E^T; f^T] y - e_{k+1}|`` with residual r, then ``z = -r_{1:k} / r_{k+1}`` and
    ``lambda = y / (-r_{k+1})``. ``f`` is scaled to unit maximum first (the program is homogeneous in
    ``f``). Raises ``ValueError`` when the constraints are inconsistent (``r = 0``).
    """
    from scipy.optimize import nnls

    e = np.asarray(matrix, dtype=np.float64)
    f = np.asarray(bound, dtype=np.float64)
    if e.ndim != 2 or f.shape != (e.shape[0],):
        raise ValueError(f"need matrix (P, k) and bound (P,), got {e.shape} and {f.shape}")
    scale = float(np.abs(f).max()) if f.size else 0.0
    if scale == 0.0 or not (f > 0).any():
        return np.zeros(f.size)  # z = 0 is feasible
    k = e.shape[1]
    system = np.vstack([e.T, f[None, :] / scale])
    target = np.zeros(k + 1)
    target[-1] = 1.0
    y, _ = nnls(system, target, maxiter=50 * max(f.size, 1))
    r = system @ y - target
    if not -r[-1] > 1e-12:
        raise ValueError("inconsistent contact constraints (least-distance program infeasible)")
    return y * (scale / -r[-1])


# ----------------------------------------------------------------------------- calibration


def depth_change_error(depth, reference, fem_depth, fem_reference, threshold: float = 5.0e-4) -> float:
    """RMS difference [m] of the depth *changes* ``p(0) - p`` of the model and the FEM images.

    Taken over the pixels valid in all four images whose change exceeds ``threshold`` [m] in either
    (comparing changes removes the meshes' different faceting of the undeformed membrane)."""
    images = [np.asarray(a, dtype=np.float64) for a in (depth, reference, fem_depth, fem_reference)]
    if len({a.shape for a in images}) != 1 or images[0].ndim != 2:
        raise ValueError("the four depth images must be 2D with equal shapes")
    d, d0, f, f0 = images
    valid = np.isfinite(d) & np.isfinite(d0) & np.isfinite(f) & np.isfinite(f0)
    change_model, change_fem = d0 - d, f0 - f
    deformed = valid & ((np.abs(change_model) > threshold) | (np.abs(change_fem) > threshold))
    if not deformed.any():
        return 0.0
    return float(np.sqrt(np.mean((change_model[deformed] - change_fem[deformed]) ** 2)))


def contact_depth_proxy(depth, reference_depth, threshold: float = 1.0e-3) -> float:
    """``F~`` of eq. (4.6) summed over the pixels pressed toward the camera by more than ``threshold`` [m].

    The sealed sensor's gas pressure rises when the membrane is indented and bulges the rest of the
    membrane outward (depth *increases* over most of the image); the plain sum of eq. (4.6) then
    falls as the force grows (measured on the FEM sensor, ``scripts/calibrate_fast_membrane.py``).
    Restricting the sum to the indented pixels keeps the depth-force correlation of Fig. 4.4. Returns
    0 when no pixel is indented.
    """
    d = np.asarray(depth, dtype=np.float64)
    d0 = np.asarray(reference_depth, dtype=np.float64)
    if d.shape != d0.shape or d.ndim != 2:
        raise ValueError(f"depth images must be 2D with equal shapes, got {d.shape} and {d0.shape}")
    if not threshold >= 0:
        raise ValueError(f"threshold must be >= 0 m, got {threshold}")
    with np.errstate(invalid="ignore"):
        mask = (d0 - d) > threshold
    if not mask.any():
        return 0.0
    return depth_force_proxy(d, d0, mask)


#: default grid of screening lengths ``l`` [m] searched by :func:`calibrate`
_SCREENING_LENGTHS = tuple(float(v) for v in np.geomspace(0.004, 0.08, 15))


def calibrate(
    model: FastMembrane,
    samples: list[dict],
    camera,
    screening_lengths=_SCREENING_LENGTHS,
    deformation_threshold: float = 5.0e-4,
) -> tuple[FastMembraneCalibration, list[dict]]:
    """Fit ``l`` (grid search on the depth-image error) and ``k_V, k_A`` (non-negative least squares).

    Args:
        model: a :class:`FastMembrane` on the mesh to calibrate (its constants are ignored).
        samples: FEM readings, each ``{"scene": SignedDistance (sensor frame), "force": F_n [N],
            "depth": (H, W) FEM depth image, "reference_depth": (H, W) the FEM's pre-contact image,
            "name": str}`` (sensor pose = identity).
        camera: the :class:`~defgraspnets.tactile.camera.DepthCamera` that rendered the FEM images.
        screening_lengths: candidate ``l`` [m].
        deformation_threshold: pixels displaced more than this [m] enter the depth error.

    Returns:
        The calibration and one row per sample: FEM and model force, depth RMS error [m], F~ of both.
    """
    from scipy.optimize import nnls

    if len(samples) < 2:
        raise ValueError("calibration needs at least 2 FEM samples")
    eye = np.eye(4)
    reference = camera.render(*model.sensor.inner_surface(model.reference), noisy=False).depth
    best = None
    for ell in np.asarray(screening_lengths, dtype=np.float64):
        m = model.with_calibration(FastMembraneCalibration(float(ell), 0.0, 0.0))
        states = [m.solve(smp["scene"], eye) for smp in samples]
        depths = [camera.render(*m.inner_surface(st), noisy=False).depth for st in states]
        err = np.sqrt(
            np.mean(
                [
                    depth_change_error(
                        d, reference, smp["depth"], smp["reference_depth"], deformation_threshold
                    )
                    ** 2
                    for d, smp in zip(depths, samples)
                ]
            )
        )
        if best is None or err < best[0]:
            best = (err, float(ell), states, depths)
    _, ell, states, depths = best
    design = np.array([[st.displaced_volume, st.contact_area] for st in states])
    target = np.array([smp["force"] for smp in samples], dtype=np.float64)
    coef, _ = nnls(design, target)
    rows = []
    for smp, st, d in zip(samples, states, depths):
        f_model = float(design[len(rows)] @ coef)
        rows.append(
            {
                "name": smp["name"],
                "fem_force": float(smp["force"]),
                "model_force": f_model,
                "depth_rms_error": depth_change_error(
                    d, reference, smp["depth"], smp["reference_depth"], deformation_threshold
                ),
                "fem_depth_proxy": depth_force_proxy(smp["depth"], smp["reference_depth"]),
                "model_depth_proxy": depth_force_proxy(d, reference),
                "fem_contact_depth_proxy": contact_depth_proxy(smp["depth"], smp["reference_depth"]),
                "model_contact_depth_proxy": contact_depth_proxy(d, reference),
                "displaced_volume": st.displaced_volume,
                "contact_area": st.contact_area,
            }
        )
    cal = FastMembraneCalibration(ell, float(coef[0]), float(coef[1]))
    return cal, rows


def indenter_scene(indenter, pose) -> SignedDistance:
    """The FEM indenter (sphere or capsule, local x axis) at ``pose`` as a scene SDF (sensor frame)."""
    from defgraspnets.tactile.indenters import CapsuleIndenter, SphereIndenter
    from defgraspnets.tactile.sdf import SphereSDF, TubeSDF

    if isinstance(indenter, SphereIndenter):
        return SphereSDF(tuple(pose.position), indenter.radius)
    if isinstance(indenter, CapsuleIndenter):
        axis = pose.rotation.apply([1.0, 0.0, 0.0])
        half = 0.5 * indenter.length * axis
        return TubeSDF(np.stack([pose.position - half, pose.position + half]), indenter.radius)
    raise TypeError(f"no scene for indenter {type(indenter).__name__}")


def fem_samples(simulator, indentations, levels, name: str) -> list[dict]:
    """Run the FEM sensor (:meth:`MembraneSimulator.indent_series`) and return calibration samples.

    Each sample holds the indenter as a scene, the FEM normal force magnitude ``|F_c|`` [N], the FEM
    depth image and its pre-contact reference; non-converged readings are dropped (reported by name).
    """
    reference = simulator.reference_depth().depth
    readings = simulator.indent_series(list(indentations), levels)
    out = []
    for row in readings:
        for k, r in enumerate(row):
            if not r.converged or r.depth is None:
                continue
            out.append(
                {
                    "name": f"{name}[{k}]@{r.depth_travel * 1e3:.1f}mm",
                    "scene": indenter_scene(simulator.indenter, r.indenter_pose),
                    "force": float(np.linalg.norm(r.contact_force)),
                    "depth": r.depth.depth,
                    "reference_depth": reference,
                    "indentation_depth": r.depth_travel,
                }
            )
    return out


def calibration_summary(rows: list[dict]) -> dict:
    """Errors of a fit (rows of :func:`calibrate`): force [N], depth change [m], ``F~``, correlations."""
    if len(rows) < 2:
        raise ValueError(f"need at least 2 calibration rows for a summary, got {len(rows)}")
    f = np.array([[r["fem_force"], r["model_force"]] for r in rows])
    p = np.array([[r["fem_contact_depth_proxy"], r["model_contact_depth_proxy"]] for r in rows])
    plain = np.array([r["fem_depth_proxy"] for r in rows])
    rel = np.abs(f[:, 1] - f[:, 0]) / f[:, 0]
    prel = np.abs(p[:, 1] - p[:, 0]) / p[:, 0]
    return {
        "force_rms_error_N": float(np.sqrt(np.mean((f[:, 1] - f[:, 0]) ** 2))),
        "force_max_relative_error": float(rel.max()),
        "force_mean_relative_error": float(rel.mean()),
        "depth_change_rms_error_m": float(np.sqrt(np.mean([r["depth_rms_error"] ** 2 for r in rows]))),
        "depth_change_max_rms_error_m": float(max(r["depth_rms_error"] for r in rows)),
        "contact_depth_proxy_max_relative_error": float(prel.max()),
        "contact_depth_proxy_mean_relative_error": float(prel.mean()),
        "fem_pearson_r_force_vs_contact_depth_proxy": float(np.corrcoef(f[:, 0], p[:, 0])[0, 1]),
        "fem_pearson_r_force_vs_plain_depth_proxy": float(np.corrcoef(f[:, 0], plain)[0, 1]),
        "model_pearson_r_force_vs_contact_depth_proxy": float(np.corrcoef(f[:, 1], p[:, 1])[0, 1]),
    }


def run_fem_calibration(
    fem_cap_divisions: int = 8,
    fast_cap_divisions: int = 12,
    camera_scale: float = 0.5,
    gauge_pressure: float = 1500.0,
    max_depth: float = 0.010,
    levels=(0.25, 0.5, 0.75, 1.0),
    sphere_radius: float = 0.01,
    pipe_radius: float = 0.00635,
    pipe_length: float = 0.12,
    sphere_tilt_deg: float = 25.0,
    pipe_turn_deg: float = 30.0,
    pipe_offset: float = 0.01,
    contact_samples_per_face: int = 0,
    contact_edge_radius: float = 0.0,
) -> dict:
    """Calibrate the fast model against the sealed FEM sensor and report the errors (JSON-ready).

    FEM: :func:`defgraspnets.tactile.datasets.make_simulator` (membrane ``fem_cap_divisions``, two layers,
    ``gauge_pressure`` [Pa], sealed) indented by a sphere (at the pole and ``sphere_tilt_deg`` off axis) and
    a pipe (capsule, at the pole and turned ``pipe_turn_deg`` about z, ``pipe_offset`` [m] off axis), each at
    ``levels`` x ``max_depth`` [m]. Fast model: the ``fast_cap_divisions`` membrane FEM-inflated to the same
    gas state. The fit (:func:`calibrate`) uses all samples; a second fit on the spheres only is evaluated on
    the pipes (cross-shape generalization). The report's ``calibration`` goes into
    :data:`DEFAULT_CALIBRATION`. ``contact_samples_per_face``, ``contact_edge_radius``: the fast model's
    contact (:class:`FastMembrane`); ``fit_default_constants`` reports the errors of
    :data:`DEFAULT_CALIBRATION` unchanged on that model.
    """
    from scipy.spatial.transform import Rotation

    from defgraspnets.tactile.camera import PICO_FLEXX, DepthCamera
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import CapsuleIndenter, Pose, SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane
    from defgraspnets.tactile.sensor import Indentation

    levels = tuple(float(v) for v in levels)
    if len(levels) < 1 or not all(0 < v <= 1 for v in levels):
        raise ValueError(f"levels must be fractions in (0, 1], got {levels}")
    for name, v in (
        ("max_depth", max_depth),
        ("gauge_pressure", gauge_pressure),
        ("camera_scale", camera_scale),
        ("sphere_radius", sphere_radius),
        ("pipe_radius", pipe_radius),
        ("pipe_length", pipe_length),
    ):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v}")
    t0 = time.perf_counter()
    intrinsics = PICO_FLEXX.scaled(camera_scale)
    fem_sensor = build_membrane(cap_divisions=fem_cap_divisions, layers=2)
    d = fem_sensor.dimensions
    top = d.outer_pole[2] + 0.05
    tilt = np.deg2rad(sphere_tilt_deg)
    direction = -np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    start = d.center - direction * (d.outer_radius + 0.06)

    sphere = SphereIndenter(radius=sphere_radius)
    sim = make_simulator(fem_sensor, sphere, gauge_pressure, True, batch_size=2, intrinsics=intrinsics)
    spheres = fem_samples(
        sim,
        [
            Indentation(Pose((0, 0, top)), max_depth, (0, 0, -1)),
            Indentation(Pose(start), max_depth, tuple(direction)),
        ],
        levels,
        f"sphere_r{sphere_radius * 1e3:g}mm",
    )
    pipe = CapsuleIndenter(radius=pipe_radius, length=pipe_length)
    sim = make_simulator(fem_sensor, pipe, gauge_pressure, True, batch_size=2, intrinsics=intrinsics)
    turned = Rotation.from_euler("z", pipe_turn_deg, degrees=True).as_quat()
    pipes = fem_samples(
        sim,
        [
            Indentation(Pose((0, 0, top)), max_depth, (0, 0, -1)),
            Indentation(Pose((0, pipe_offset, top), turned), max_depth, (0, 0, -1)),
        ],
        levels,
        f"pipe_r{pipe_radius * 1e3:g}mm",
    )
    if len(spheres) < 2 or len(pipes) < 2:
        raise RuntimeError(f"too few converged FEM samples: {len(spheres)} sphere, {len(pipes)} pipe")
    t_fem = time.perf_counter() - t0

    fast_sensor = build_membrane(cap_divisions=fast_cap_divisions, layers=2)
    inflated = make_simulator(fast_sensor, sphere, gauge_pressure, False, batch_size=1, intrinsics=None)
    model = FastMembrane(
        fast_sensor,
        inflated.reference.positions,
        contact_samples_per_face=contact_samples_per_face,
        contact_edge_radius=contact_edge_radius,
    )
    camera = DepthCamera(intrinsics)
    cal, rows = calibrate(model, spheres + pipes, camera)
    default = model.with_calibration(DEFAULT_CALIBRATION)
    _, rows_default = calibrate(
        default, spheres + pipes, camera, screening_lengths=[DEFAULT_CALIBRATION.screening_length]
    )
    rows_default = [
        {**row, "model_force": default.solve(smp["scene"], np.eye(4)).normal_force}
        for smp, row in zip(spheres + pipes, rows_default)
    ]
    cal_sph, _ = calibrate(model, spheres, camera)
    # the sphere-only constants on the pipes: depth errors from calibrate() at the fixed screening length,
    # forces from the fixed model (calibrate() refits the stiffnesses)
    fixed = model.with_calibration(cal_sph)
    _, rows_cross = calibrate(fixed, pipes, camera, screening_lengths=[cal_sph.screening_length])
    cross = [
        {**row, "model_force": fixed.solve(smp["scene"], np.eye(4)).normal_force}
        for smp, row in zip(pipes, rows_cross)
    ]
    fitted = model.with_calibration(cal)
    timing = [fitted.solve(smp["scene"], np.eye(4)).solve_time for smp in spheres + pipes]
    return {
        "calibration": {
            "screening_length": cal.screening_length,
            "volume_stiffness": cal.volume_stiffness,
            "area_pressure": cal.area_pressure,
        },
        "fit_all": calibration_summary(rows),
        "fit_default_constants": calibration_summary(rows_default),
        "cross_shape_fit_spheres_test_pipes": calibration_summary(cross),
        "samples": rows,
        "fem": {
            "cap_divisions": fem_cap_divisions,
            "layers": 2,
            "gauge_pressure_Pa": gauge_pressure,
            "closed": True,
            "friction": 0.5,
            "camera": f"pico flexx x{camera_scale} ({intrinsics.width}x{intrinsics.height})",
            "indenters": (
                f"sphere r={sphere_radius * 1e3:g} mm (pole, {sphere_tilt_deg:g} deg off axis); capsule "
                f"r={pipe_radius * 1e3:g} mm L={pipe_length * 1e3:g} mm (pole, {pipe_turn_deg:g} deg, "
                f"{pipe_offset * 1e3:g} mm off)"
            ),
            "depths_mm": [max_depth * 1e3 * lv for lv in levels],
            "wall_time_s": t_fem,
        },
        "fast_model": {
            "cap_divisions": fast_cap_divisions,
            "contact_samples_per_face": contact_samples_per_face,
            "contact_edge_radius_m": contact_edge_radius,
            "mean_solve_time_s": float(np.mean(timing)),
        },
        "total_wall_time_s": time.perf_counter() - t0,
    }
