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

The state is path independent (no friction history), so every pose is solved from scratch.

Force. The normal force is a linear model in the two quantities that carry the load of a
pressurized membrane: the displaced gas volume ``dV = V_ref - V`` (closed capsule: the gas pressure
rises with it; tension of the stretched membrane) and the contact area ``A_C`` (the gas pressure acts on
it),

    F_n = k_V dV + k_A A_C,

directed against the area-weighted object normal over the contact; ``k_V`` [N/m^3], ``k_A`` [Pa] and
``l`` [m] are fitted to the FEM sensor (:func:`calibrate`, ``scripts/calibrate_fast_membrane.py``).
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
    "run_fem_calibration",
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
        iterations: active-set iterations used.
        solve_time: wall time [s].
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
        max_iterations: active-set iterations.
    """

    def __init__(
        self,
        sensor: MembraneSensor,
        reference_positions,
        calibration: FastMembraneCalibration = DEFAULT_CALIBRATION,
        tolerance: float = 1.0e-5,
        max_iterations: int = 8,
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

    def with_calibration(self, calibration: FastMembraneCalibration) -> FastMembrane:
        """The same mesh and reference with other constants."""
        return FastMembrane(self.sensor, self.reference, calibration, self.tolerance, self.max_iterations)

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

        positions = self.reference + np.tile(u, (self.sensor.layers + 1, 1))
        volume = enclosed_volume(positions, self.sensor.inner_faces, self.sensor.rim_center)
        dv = max(0.0, self.reference_volume - volume)
        area = float(self.outer_area[contact].sum())
        cal = self.calibration
        fn = cal.volume_stiffness * dv + cal.area_pressure * area if contact.any() else 0.0
        force = np.zeros(3)
        if contact.any():
            n = (self.outer_area[contact, None] * grad[contact]).sum(axis=0)
            norm = np.linalg.norm(n)
            if norm > 0:
                force = -fn * n / norm  # the membrane pushes the object against its outward normal
        return FastMembraneState(
            positions=positions,
            column_displacement=u,
            contact_columns=contact,
            normal_force=float(fn),
            contact_force=force,
            displaced_volume=float(dv),
            contact_area=area,
            max_displacement=float(np.linalg.norm(u, axis=1).max()),
            residual_penetration=residual,
            clamped_contact=clamped_contact,
            iterations=iterations,
            solve_time=time.perf_counter() - t0,
        )

    def inner_surface(self, state: FastMembraneState) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the deformed inner surface for the depth camera (sensor frame)."""
        return self.sensor.inner_surface(state.positions)


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
) -> dict:
    """Calibrate the fast model against the sealed FEM sensor and report the errors (JSON-ready).

    FEM: :func:`defgraspnets.tactile.datasets.make_simulator` (membrane ``fem_cap_divisions``, two layers,
    ``gauge_pressure`` [Pa], sealed) indented by a sphere (at the pole and ``sphere_tilt_deg`` off axis) and
    a pipe (capsule, at the pole and turned ``pipe_turn_deg`` about z, ``pipe_offset`` [m] off axis), each at
    ``levels`` x ``max_depth`` [m]. Fast model: the ``fast_cap_divisions`` membrane FEM-inflated to the same
    gas state. The fit (:func:`calibrate`) uses all samples; a second fit on the spheres only is evaluated on
    the pipes (cross-shape generalization). The report's ``calibration`` goes into
    :data:`DEFAULT_CALIBRATION`.
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
    model = FastMembrane(fast_sensor, inflated.reference.positions)
    camera = DepthCamera(intrinsics)
    cal, rows = calibrate(model, spheres + pipes, camera)
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
        "fast_model": {"cap_divisions": fast_cap_divisions, "mean_solve_time_s": float(np.mean(timing))},
        "total_wall_time_s": time.perf_counter() - t0,
    }
