"""The thesis's indentation experiments (§2.3-2.4) run on the simulated membrane sensor.

Each study drives a :class:`~defgraspnets.tactile.sensor.MembraneSimulator` along pole indentations,
reads its interior depth camera, and applies the library algorithms to the frames:

- **contact regions** (Fig. 2.5): Algorithm 1 (:func:`~defgraspnets.tactile.contact_regions.classify_surface`)
  on the organized cloud of a sphere, rectangular prism and ring pressed 10 mm into the pole, scored
  against the simulator's *true* contact region (below) by IoU and boundary error;
- **contact and deformed areas vs depth** (Figs 2.7, 2.8): Type C and Type B+C areas
  (:func:`~defgraspnets.tactile.contact_regions.region_area`) for the 10/20/30 mm spheres over a depth
  sweep at several gas states;
- **force-indentation characteristics** (Figs 2.9, 2.10): axial FEM force vs camera-measured indentation
  (:func:`~defgraspnets.tactile.force_models.indentation_depth`) per sphere and gas state, Hertz fits
  (eq. 2.2), linear fits, and the 4th-order polynomial of the slope in PV;
- **force matching** (Fig. 2.11, Table 2.1): the
  :class:`~defgraspnets.tactile.force_models.ForceMatchingController`
  closes the loop on the camera-measured indentation against the FEM sensor; the error is the true FEM
  force minus the desired one.

True contact region. The FEM contact is a penalty on the signed distance g of each *outer* surface
vertex to the indenter, so a vertex carries contact force iff g < 0 (:mod:`defgraspnets.fem.contact`).
The camera sees the *inner* surface. Every pixel hits one inner triangle (``DepthFrame.face``); its
three inner vertices sit on the same through-thickness fibres as three outer vertices (the shell is a
sweep of the inner surface, :func:`~defgraspnets.tactile.membrane.build_membrane`). The pixel's outer
point is the barycentric combination, with the hit point's barycentric coordinates in the deformed
inner triangle, of the deformed outer vertices, and the pixel is in the true contact region iff that
point's signed distance to the indenter (at its reading pose) is at most ``contact_tolerance``. On
contacting vertices g is the (tiny) penalty penetration; between two of them on a flat face the
interpolated g is the same, on a convex indenter the chord lies inside it (g < 0), and toward a free
vertex g grows linearly, so the region is the FEM contact vertices' patch, bounded at the mesh's
resolution (~9 mm vertex spacing at ``cap_divisions = 8``, ~4.6 mm at 16).

Gas states (:class:`GasState`): the thesis labels states by the absolute P V [N m] of a *first*
sensor version (2 mm shell, smaller capsule; 32.5-103.4 N m). The simulated sensor is the second
version (47 mm membrane on a 10 cm housing, about 1.1 L of gas: PV ~ 113 N m already at atmospheric
pressure), so the thesis's numbers cannot be matched; a state here is the gauge pressure the sensor is
inflated to, then sealed (``closed``: Boyle's law, the thesis's coloured curves) or held open (the
thesis's black "free air exchange" curves: ``closed = False`` at 0 Pa). Each state's PV is reported as
``(P_atm + p) V`` of its inflated reference.

Flat obstacles: the simulator itself maps the prism
(:class:`~defgraspnets.tactile.indenters.BoxIndenter` -> FEM ``RoundedBox`` with sharp edges) and the ring
(:class:`~defgraspnets.tactile.indenters.RingIndenter` -> FEM ``TriangleMesh``) to FEM bodies
(:func:`~defgraspnets.tactile.sensor.fem_shape`); pole indentations press them with their flat face
(local -z) first.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields
from functools import partial

import numpy as np

from defgraspnets import fem
from defgraspnets.tactile.contact_regions import (
    RegionComparison,
    SurfaceType,
    classify_surface,
    compare_regions,
    region_area,
)
from defgraspnets.tactile.force_models import (
    ForceMatchingController,
    PVForceModel,
    fit_hertz,
    fit_linear,
    force_error_table,
    indentation_depth,
)
from defgraspnets.tactile.indenters import (
    SphereIndenter,
)
from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, MembraneSensor
from defgraspnets.tactile.sensor import MembraneSimulator, TactileReading

__all__ = [
    "AreaSweep",
    "ClassificationConfig",
    "ContactRegionResult",
    "ForceMatchingResult",
    "ForceSweep",
    "GasState",
    "area_sweep",
    "axial_force",
    "contact_point_count",
    "contact_region_experiment",
    "fit_force_models",
    "force_matching",
    "force_sweep",
    "make_study_simulator",
    "mesh_spacing",
    "run_contact_region_study",
    "run_force_model_study",
    "state_pv",
    "to_jsonable",
    "true_contact_mask",
]


# ----------------------------------------------------------------------------- gas states and simulators


@dataclass(frozen=True)
class GasState:
    """A pre-contact gas state: inflated to ``gauge_pressure`` [Pa], then sealed (``closed``) or held open."""

    gauge_pressure: float
    closed: bool = True

    def __post_init__(self):
        if not (np.isfinite(self.gauge_pressure) and self.gauge_pressure >= 0):
            raise ValueError(f"gauge_pressure must be finite and >= 0 Pa, got {self.gauge_pressure!r}")

    @property
    def label(self) -> str:
        kind = "closed" if self.closed else "open"
        return f"{kind} {self.gauge_pressure:g} Pa"


def make_study_simulator(
    sensor: MembraneSensor,
    indenter,
    state: GasState,
    friction: float = 0.5,
    intrinsics=None,
    options: fem.SolverOptions | None = None,
    device: str | None = "cpu",
    contact_subdivisions: int | None = None,
) -> MembraneSimulator:
    """The sensor at ``state`` by :func:`defgraspnets.tactile.datasets.make_simulator` (inflate open to the
    gauge pressure; if closed, seal there so that P V of the inflated state stays constant), for any
    indenter :class:`~defgraspnets.tactile.sensor.MembraneSimulator` accepts, solved on the Warp ``device``
    ("cpu", "cuda", ...; None = Warp's default), with sub-vertex contact ``contact_subdivisions`` (None:
    the options' value, vertex contact by default)."""
    from defgraspnets.tactile.datasets import make_simulator

    if not isinstance(state, GasState):
        raise TypeError(f"state must be a GasState, got {type(state).__name__}")
    return make_simulator(
        sensor,
        indenter,
        state.gauge_pressure,
        state.closed,
        friction=friction,
        intrinsics=intrinsics,
        options=options,
        device=device,
        contact_subdivisions=contact_subdivisions,
    )


def state_pv(sim: MembraneSimulator) -> float:
    """P V [N m] of the simulator's inflated pre-contact state: absolute pressure times gas volume."""
    ref = sim.reference
    return float((ATMOSPHERIC_PRESSURE + ref.gauge_pressure) * ref.gas_volume)


def axial_force(reading: TactileReading, direction=(0.0, 0.0, -1.0)) -> float:
    """Axial load [N] the membrane puts on an indenter travelling along ``direction`` (> 0 pressing)."""
    return float(-np.dot(reading.contact_force, np.asarray(direction, dtype=np.float64)))


# ----------------------------------------------------------------------------- true contact region


def _outer_of_inner(sensor: MembraneSensor) -> np.ndarray:
    """Map inner-surface vertex id -> outer vertex on the same through-thickness fibre (layer-major sweep)."""
    inner = sensor.inner_vertices
    num_surface = len(inner)
    if not np.array_equal(inner, np.arange(num_surface)):
        raise ValueError("the membrane mesh is not a layer-major sweep (inner vertices are not 0..S-1)")
    outer = inner + sensor.layers * num_surface
    p = sensor.mesh.points
    normal = p[inner] - sensor.dimensions.center
    normal[:, 2] = np.where(p[inner, 2] < sensor.dimensions.z_equator, 0.0, normal[:, 2])  # skirt: radial
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    if not np.allclose(p[outer] - p[inner], sensor.dimensions.thickness * normal, atol=1e-9):
        raise ValueError("outer vertices are not the inner ones swept through the thickness")
    return outer


def contact_point_count(sim: MembraneSimulator, reading: TactileReading) -> int:
    """Number of the outer surface's FEM contact points inside the indenter (g < 0): those carrying contact
    force. With vertex contact they are outer vertices; with sub-vertex contact
    (``contact_subdivisions`` > 1) the points on the outer triangles too
    (:meth:`~defgraspnets.tactile.sensor.MembraneSimulator.outer_contact_points`)."""
    body = sim.indenter.with_pose(reading.indenter_pose)
    return int((body.signed_distance(sim.outer_contact_points(reading.positions)) < 0).sum())


def true_contact_mask(
    sim: MembraneSimulator, reading: TactileReading, contact_tolerance: float = 1.0e-4
) -> np.ndarray:
    """(H, W) pixels of ``reading.depth`` whose membrane point is in contact with the indenter (module doc).

    Args:
        sim: the simulator that produced the reading (its sensor and indenter geometry).
        reading: a converged reading with a rendered depth frame.
        contact_tolerance: largest signed distance [m] of the pixel's outer-surface point to the indenter
            counted as contact; must exceed the penalty penetration (~1e-6 m here) and stay well below
            the mesh spacing.
    """
    if reading.depth is None or not reading.converged:
        raise ValueError("the reading must be converged and carry a depth frame")
    if not (np.isfinite(contact_tolerance) and contact_tolerance >= 0):
        raise ValueError(f"contact_tolerance must be finite and >= 0 m, got {contact_tolerance!r}")
    frame = reading.depth
    sensor = sim.sensor
    hit = frame.face >= 0
    tri = sensor.inner_faces[frame.face[hit]]  # (n, 3) inner vertex ids
    x = reading.positions
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    p = frame.points[hit].astype(np.float64)
    # barycentric coordinates of the hit point in the deformed inner triangle (least squares in its plane)
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    w = np.clip(np.stack([1.0 - wb - wc, wb, wc], axis=1), 0.0, 1.0)
    w /= w.sum(axis=1, keepdims=True)
    outer = _outer_of_inner(sensor)[tri]
    q = np.einsum("ni,nij->nj", w, x[outer])
    gap = sim.indenter.with_pose(reading.indenter_pose).signed_distance(q)
    mask = np.zeros(frame.face.shape, dtype=bool)
    mask[hit] = gap <= contact_tolerance
    return mask


# ----------------------------------------------------------------------------- classification settings


@dataclass(frozen=True)
class ClassificationConfig:
    """Parameters of Algorithm 1 (:func:`classify_surface`) for the full 224 x 171 frame.

    ``offset`` scales with the image: the thesis's p = 10 on the pico flexx (same focal length here).
    """

    offset: int = 10
    deformation_threshold: float = 1.0e-3
    curvature_threshold: float = 0.0
    window_radius: int = 3

    def classify(self, cloud: np.ndarray, reference_cloud: np.ndarray):
        return classify_surface(
            cloud,
            reference_cloud,
            offset=self.offset,
            deformation_threshold=self.deformation_threshold,
            curvature_threshold=self.curvature_threshold,
            window_radius=self.window_radius,
        )


# ----------------------------------------------------------------------------- Fig. 2.5


@dataclass
class ContactRegionResult:
    """One obstacle pressed into the pole, classified and scored (Fig. 2.5).

    Attributes:
        indenter: the obstacle's kind (``sphere``, ``box``, ``ring``) and ``dimensions`` [m].
        depth: commanded travel beyond first contact [m]; ``indentation``: camera-measured [m].
        pv: gas state P V [N m]; ``force``: axial FEM force [N].
        points: (H, W, 3) organized cloud [m]; ``labels``: (H, W) Algorithm 1 labels;
            ``true_mask``: (H, W) true contact pixels.
        comparison: estimated (Type C) vs true region: IoU, boundary errors [m], areas [m^2].
        deformed_area: Type B+C area [m^2]; ``contact_points``: FEM outer contact points with g < 0
            (:func:`contact_point_count`; JSON written before session 42 calls them ``contact_vertices``).
    """

    indenter: str
    dimensions: dict
    depth: float
    indentation: float
    pv: float
    force: float
    points: np.ndarray = field(repr=False)
    labels: np.ndarray = field(repr=False)
    true_mask: np.ndarray = field(repr=False)
    comparison: RegionComparison
    deformed_area: float
    contact_points: int

    def summary(self) -> dict:
        return {
            "indenter": self.indenter,
            "dimensions": self.dimensions,
            "depth": self.depth,
            "indentation": self.indentation,
            "pv": self.pv,
            "force": self.force,
            "iou": self.comparison.iou,
            "mean_boundary_error": self.comparison.mean_boundary_distance,
            "max_boundary_error": self.comparison.max_boundary_distance,
            "estimated_contact_area": self.comparison.estimated_area,
            "true_contact_area": self.comparison.true_area,
            "deformed_area": self.deformed_area,
            "contact_points": self.contact_points,
            "pixels": {t.name.lower(): int((self.labels == t).sum()) for t in SurfaceType},
        }


def _indenter_dimensions(indenter) -> dict:
    names = indenter._dimension_names()
    return {n: float(getattr(indenter, n)) for n in names}


def contact_region_experiment(
    sim: MembraneSimulator,
    depth: float = 0.01,
    classification: ClassificationConfig = ClassificationConfig(),
    contact_tolerance: float = 1.0e-4,
    max_step: float = 0.002,
) -> ContactRegionResult:
    """Press the simulator's indenter ``depth`` [m] into the pole, classify the frame, compare with the truth.

    Raises:
        RuntimeError: the indentation did not converge (e.g. the indenter slipped between vertices of a
            mesh too coarse for it), or the FEM reports no contact.
    """
    if not (np.isfinite(depth) and depth > 0):
        raise ValueError(f"depth must be > 0 m, got {depth!r}")
    reference = sim.reference_depth()
    reading = sim.indent([sim.pole_indentation(depth)], max_step=max_step)[0]
    if not reading.converged:
        raise RuntimeError(
            f"{type(sim.indenter).__name__} at {depth:g} m did not converge "
            "(mesh too coarse for the indenter?)"
        )
    truth = true_contact_mask(sim, reading, contact_tolerance)
    if not truth.any():
        raise RuntimeError("the FEM contact region is not visible to the camera (no true contact pixel)")
    cls = classification.classify(reading.depth.points, reference.points)
    cloud = reading.depth.points.astype(np.float64)
    cmp = compare_regions(cloud, cls.contact_mask, truth)
    return ContactRegionResult(
        indenter=sim.indenter.kind,
        dimensions=_indenter_dimensions(sim.indenter),
        depth=float(depth),
        indentation=indentation_depth(reading.depth.depth, reference.depth),
        pv=state_pv(sim),
        force=axial_force(reading),
        points=cloud,
        labels=cls.labels,
        true_mask=truth,
        comparison=cmp,
        deformed_area=region_area(cloud, cls.deformed_mask),
        contact_points=contact_point_count(sim, reading),
    )


# ----------------------------------------------------------------------------- Figs 2.7-2.9 sweeps


def _levels(depths) -> tuple[np.ndarray, float]:
    d = np.asarray(depths, dtype=np.float64).ravel()
    if d.size < 1 or not np.all(np.isfinite(d)) or d[0] <= 0 or np.any(np.diff(d) <= 0):
        raise ValueError(f"depths must be positive and increasing [m], got {d.tolist()}")
    return d / d[-1], float(d[-1])


@dataclass
class AreaSweep:
    """Contact and deformed areas vs depth for one sphere and gas state (Figs 2.7, 2.8).

    Arrays have one entry per depth; NaN where the reading did not converge.

    Attributes:
        sphere_diameter [m], state (label), closed, pv [N m].
        depth: commanded travel [m]; indentation: camera-measured [m]; force: axial FEM force [N].
        contact_area: Type C area [m^2]; deformed_area: Type B+C [m^2]; true_contact_area: the FEM
            contact region's area on the inner-surface cloud [m^2]; contact_points: FEM contact points
            (:func:`contact_point_count`; 1 at every depth where the sphere is below the mesh's resolution).
        converged: per depth.
    """

    sphere_diameter: float
    state: str
    closed: bool
    pv: float
    depth: np.ndarray
    indentation: np.ndarray
    force: np.ndarray
    contact_area: np.ndarray
    deformed_area: np.ndarray
    true_contact_area: np.ndarray
    contact_points: np.ndarray
    converged: np.ndarray
    seconds: float


def area_sweep(
    sim: MembraneSimulator,
    depths,
    classification: ClassificationConfig = ClassificationConfig(),
    contact_tolerance: float = 1.0e-4,
    max_step: float = 0.002,
    state: str = "",
    closed: bool = True,
) -> AreaSweep:
    """Indent the pole through ``depths`` [m] (one path, read at each depth) and measure the areas."""
    if not isinstance(sim.indenter, SphereIndenter):
        raise TypeError("the area sweeps of Figs 2.7-2.8 use sphere indenters")
    levels, final = _levels(depths)
    t0 = time.perf_counter()
    reference = sim.reference_depth()
    series = sim.indent_series([sim.pole_indentation(final)], levels, max_step=max_step)
    n = len(levels)
    out = {k: np.full(n, np.nan) for k in ("indentation", "force", "contact", "deformed", "true")}
    points = np.zeros(n, dtype=int)
    ok = np.zeros(n, dtype=bool)
    for i, (reading,) in enumerate(series):
        if not reading.converged:
            continue
        ok[i] = True
        cloud = reading.depth.points.astype(np.float64)
        cls = classification.classify(cloud, reference.points)
        out["indentation"][i] = indentation_depth(reading.depth.depth, reference.depth)
        out["force"][i] = axial_force(reading)
        out["contact"][i] = region_area(cloud, cls.contact_mask)
        out["deformed"][i] = region_area(cloud, cls.deformed_mask)
        out["true"][i] = region_area(cloud, true_contact_mask(sim, reading, contact_tolerance))
        points[i] = contact_point_count(sim, reading)
    return AreaSweep(
        sphere_diameter=2.0 * sim.indenter.radius,
        state=state,
        closed=closed,
        pv=state_pv(sim),
        depth=levels * final,
        indentation=out["indentation"],
        force=out["force"],
        contact_area=out["contact"],
        deformed_area=out["deformed"],
        true_contact_area=out["true"],
        contact_points=points,
        converged=ok,
        seconds=time.perf_counter() - t0,
    )


@dataclass
class ForceSweep:
    """Force-indentation curve of one sphere at one gas state (Fig. 2.9), with its fits.

    Attributes:
        sphere_diameter [m], state, closed, pv [N m].
        depth: commanded travel [m]; indentation: camera-measured delta [m]; force: axial FEM force [N].
        converged: per depth.
        linear: ``F = k delta + F_0`` fit on the camera-measured delta (slope [N/m], intercept [N],
            standard errors, r_squared); hertz: ``F = c delta^1.5`` with ``E*`` for
            ``R* = (1/R_sphere + 1/R_membrane)^-1`` (coefficient [N/m^1.5], effective_modulus [Pa]).
    """

    sphere_diameter: float
    state: str
    closed: bool
    pv: float
    depth: np.ndarray
    indentation: np.ndarray
    force: np.ndarray
    converged: np.ndarray
    contact_points: np.ndarray | None = None
    linear: dict | None = None
    hertz: dict | None = None
    seconds: float = 0.0


def force_sweep(
    sim: MembraneSimulator, depths, max_step: float = 0.002, state: str = "", closed: bool = True
) -> ForceSweep:
    """Axial force vs camera-measured indentation through ``depths`` [m] along one pole path, with fits.

    Fits use the converged samples with delta > 0; fewer than 3 leave ``linear``/``hertz`` None.
    """
    if not isinstance(sim.indenter, SphereIndenter):
        raise TypeError("the force characterization of Fig. 2.9 uses sphere indenters")
    levels, final = _levels(depths)
    t0 = time.perf_counter()
    reference = sim.reference_depth()
    series = sim.indent_series([sim.pole_indentation(final)], levels, max_step=max_step)
    n = len(levels)
    delta, force = np.full(n, np.nan), np.full(n, np.nan)
    points = np.zeros(n, dtype=int)
    ok = np.zeros(n, dtype=bool)
    for i, (reading,) in enumerate(series):
        if reading.converged:
            ok[i] = True
            delta[i] = indentation_depth(reading.depth.depth, reference.depth)
            force[i] = axial_force(reading)
            points[i] = contact_point_count(sim, reading)
    sweep = ForceSweep(
        sphere_diameter=2.0 * sim.indenter.radius,
        state=state,
        closed=closed,
        pv=state_pv(sim),
        depth=levels * final,
        indentation=delta,
        force=force,
        converged=ok,
        contact_points=points,
        seconds=time.perf_counter() - t0,
    )
    use = ok & (delta > 0)
    if use.sum() >= 3:
        lin = fit_linear(delta[use], force[use])
        r_star = 1.0 / (1.0 / sim.indenter.radius + 1.0 / sim.sensor.dimensions.outer_radius)
        hz = fit_hertz(delta[use], force[use], effective_radius=r_star)
        sweep.linear = asdict(lin)
        sweep.hertz = {
            "coefficient": hz.model.coefficient,
            "coefficient_std": hz.coefficient_std,
            "effective_radius": r_star,
            "effective_modulus": hz.effective_modulus,
            "effective_modulus_std": hz.effective_modulus_std,
            "residual_std": hz.residual_std,
        }
    return sweep


def fit_force_models(sweeps: list[ForceSweep], order: int = 4) -> dict[float, PVForceModel]:
    """Fig. 2.10: per sphere diameter, the polynomial of ``order`` through (PV, slope) of its closed states.

    Raises:
        ValueError: a diameter has fewer than ``order + 1`` fitted closed states.
    """
    out = {}
    for diameter in sorted({s.sphere_diameter for s in sweeps}):
        closed = [s for s in sweeps if s.sphere_diameter == diameter and s.closed and s.linear is not None]
        if len(closed) < order + 1:
            raise ValueError(
                f"the order-{order} slope polynomial of the {diameter * 1e3:g} mm sphere needs {order + 1} "
                f"closed gas states with a linear fit, got {len(closed)}"
            )
        pv = [s.pv for s in closed]
        out[diameter] = PVForceModel.fit(pv, [s.linear["slope"] for s in closed], order)
    return out


# ----------------------------------------------------------------------------- Fig. 2.11, Table 2.1


@dataclass
class ForceMatchingResult:
    """Force matching at one gas state (Fig. 2.11): one row per (desired force, trial).

    Attributes:
        pv [N m], state; desired_force, actual_force (true FEM axial force at the end) [N];
        target_indentation, measured_indentation (camera, at the end) [m]; travel: final actuator
        travel beyond contact [m]; steps: control steps used; converged: the indentation error fell
        within tolerance before ``max_steps``; trial: index of the trial (camera-noise realization).
        error_table: Table 2.1 row, ``{pv: (mean, standard error)}`` of ``F_actual - F_desired`` [N].
    """

    pv: float
    state: str
    desired_force: np.ndarray
    trial: np.ndarray
    actual_force: np.ndarray
    target_indentation: np.ndarray
    measured_indentation: np.ndarray
    travel: np.ndarray
    steps: np.ndarray
    converged: np.ndarray
    mean_error: float
    standard_error: float


def _measure(sim, reading, reference, camera, rng, percentile):
    """Camera-measured indentation of a reading: its noise-free frame, or re-rendered with ToF noise."""
    if camera is None:
        frame = reading.depth
    else:
        frame = camera.render(*sim.sensor.inner_surface(reading.positions), rng=rng, noisy=True)
    return indentation_depth(frame.depth, reference.depth, percentile=percentile)


def force_matching(
    sim: MembraneSimulator,
    controller: ForceMatchingController,
    desired_forces,
    trials: int = 1,
    indentation_tolerance: float = 5.0e-5,
    max_steps: int = 12,
    depth_noise: float = 0.0,
    indentation_percentile: float = 100.0,
    seed: int = 0,
    max_step: float = 0.002,
    state: str = "",
) -> ForceMatchingResult:
    """Drive the simulated sensor to each desired force by position control on the camera's indentation.

    For every desired force and trial the sensor starts at contact onset (delta = 0); each step reads
    delta from the depth image (:func:`indentation_depth` against the pre-contact reference, with
    zero-mean ToF range noise of relative std ``depth_noise`` if > 0, a new realization per trial), asks
    the controller for the actuator travel increment, and re-solves the FEM equilibrium at the new
    travel (quasi-static; each solve starts from the inflated membrane, so friction history along the
    actuator path is not modelled). It stops when ``|delta_des - delta| <= indentation_tolerance`` [m]
    or after ``max_steps``; the true FEM axial force of the last reading is ``F_actual``.
    """
    from defgraspnets.tactile.camera import DepthCamera, ToFNoise

    f_des = np.asarray(desired_forces, dtype=np.float64).ravel()
    if f_des.size < 1 or not np.all(np.isfinite(f_des)) or np.any(f_des <= 0):
        raise ValueError(f"desired_forces must be finite and > 0 N, got {f_des.tolist()}")
    if int(trials) != trials or trials < 1:
        raise ValueError(f"trials must be an integer >= 1, got {trials!r}")
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    if not indentation_tolerance > 0:
        raise ValueError(f"indentation_tolerance must be > 0 m, got {indentation_tolerance!r}")
    if not (np.isfinite(depth_noise) and depth_noise >= 0):
        raise ValueError(f"depth_noise must be finite and >= 0, got {depth_noise!r}")
    if sim.camera is None:
        raise ValueError("force matching needs the simulator's depth camera (intrinsics=None given)")
    reference = sim.reference_depth()
    camera = None
    if depth_noise > 0:
        camera = DepthCamera(sim.camera.intrinsics, noise=ToFNoise(relative_sigma=depth_noise))
    rows = []
    for force in f_des:
        for trial in range(int(trials)):
            rng = np.random.default_rng([seed, trial, int(round(force * 1e6))])
            travel, delta, reading, steps, done = 0.0, 0.0, None, 0, False
            target = controller.target_indentation(force)
            while steps < max_steps:
                cmd = controller.step(delta, force)
                if abs(cmd.indentation_error) <= indentation_tolerance and reading is not None:
                    done = True
                    break
                travel = max(travel + cmd.displacement, 1e-6)
                reading = sim.indent([sim.pole_indentation(travel)], max_step=max_step)[0]
                steps += 1
                if not reading.converged:
                    break
                delta = _measure(sim, reading, reference, camera, rng, indentation_percentile)
            if not done and reading is not None and reading.converged:
                done = abs(target - delta) <= indentation_tolerance
            actual = axial_force(reading) if reading is not None and reading.converged else np.nan
            rows.append((force, trial, actual, target, delta, travel, steps, done))
    a = np.array(rows, dtype=np.float64)
    ok = np.isfinite(a[:, 2])
    if not ok.any():
        raise RuntimeError("no force-matching trial reached a converged equilibrium")
    pv = state_pv(sim)
    table = force_error_table(np.full(ok.sum(), pv), a[ok, 2], a[ok, 0])
    mean, se = table[pv]
    return ForceMatchingResult(
        pv=pv,
        state=state,
        desired_force=a[:, 0],
        trial=a[:, 1].astype(int),
        actual_force=a[:, 2],
        target_indentation=a[:, 3],
        measured_indentation=a[:, 4],
        travel=a[:, 5],
        steps=a[:, 6].astype(int),
        converged=a[:, 7].astype(bool),
        mean_error=mean,
        standard_error=se,
    )


# ----------------------------------------------------------------------------- JSON


def to_jsonable(obj):
    """Dataclasses, arrays and numpy scalars -> JSON types (NaN/inf become None); large images are dropped
    by the callers (they go to the PNGs)."""
    if hasattr(obj, "__dataclass_fields__"):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    return obj


# ----------------------------------------------------------------------------- whole experiments


def mesh_spacing(sensor: MembraneSensor) -> float:
    """Median edge length of the outer (contact) surface [m]: the resolution of the vertex-based contact."""
    f = sensor.outer_faces
    p = sensor.mesh.points
    edges = np.concatenate([p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 1]], p[f[:, 0]] - p[f[:, 2]]])
    return float(np.median(np.linalg.norm(edges, axis=1)))


def _membranes(layers):
    from defgraspnets.tactile.membrane import build_membrane

    cache = {}

    def get(n):
        if n not in cache:
            cache[n] = build_membrane(cap_divisions=int(n), layers=int(layers))
        return cache[n]

    return get


def _states(states) -> list[GasState]:
    out = [
        s if isinstance(s, GasState) else GasState(float(s["gauge_pressure"]), bool(s["closed"]))
        for s in states
    ]
    if not out:
        raise ValueError("give at least one gas state")
    return out


def _per_diameter(diameters, cap_divisions, name) -> list[tuple[float, int]]:
    d = [float(x) for x in diameters]
    c = [int(x) for x in cap_divisions]
    if len(d) != len(c):
        raise ValueError(f"{name}: sphere_diameters {d} and cap_divisions {c} must have equal lengths")
    if any(not (np.isfinite(x) and x > 0) for x in d):
        raise ValueError(f"{name}: sphere diameters must be > 0 m, got {d}")
    return list(zip(d, c))


def run_contact_region_study(
    out_dir,
    obstacles: dict,
    obstacle_depth: float = 0.01,
    obstacle_state: dict | GasState = GasState(1500.0, True),
    obstacle_cap_divisions: int = 8,
    sphere_diameters=(0.01, 0.02, 0.03),
    sweep_cap_divisions=(8, 8, 8),
    sweep_states=({"gauge_pressure": 1500.0, "closed": True},),
    sweep_depths=(0.002, 0.004, 0.006, 0.008, 0.01),
    layers: int = 2,
    classification: ClassificationConfig = ClassificationConfig(),
    contact_tolerance: float = 1.0e-4,
    friction: float = 0.5,
    max_step: float = 0.002,
    device: str | None = "cpu",
    contact_subdivisions: int = 1,
    log=print,
) -> dict:
    """Figs 2.5, 2.7, 2.8 on the simulated sensor; writes PNGs and ``contact_regions.json`` to ``out_dir``.

    Args:
        obstacles: ``{name: {"kind": "sphere" | "box" | "ring", **dimensions}}`` pressed into the pole.
        obstacle_depth, obstacle_state, obstacle_cap_divisions: their travel [m], gas state, mesh.
        sphere_diameters, sweep_cap_divisions: the area sweeps' spheres [m] and the mesh for each.
        sweep_states: gas states (``{"gauge_pressure": Pa, "closed": bool}``) of the sweeps.
        sweep_depths: increasing travels beyond contact [m].
        device: Warp device of the FEM solves and the camera ("cpu", "cuda", ...).
        contact_subdivisions: FEM contact points on the n-subdivision of every surface triangle (1: the
            vertices; ``SolverOptions.contact_subdivisions``): indenters narrower than the mesh spacing
            then touch the triangles between the vertices.
    """
    from pathlib import Path

    from defgraspnets.tactile import study_plots
    from defgraspnets.tactile.indenters import make_indenter

    fem.SolverOptions(contact_subdivisions=contact_subdivisions)  # a bad value is named before any solve
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    membrane = _membranes(layers)
    t0 = time.perf_counter()
    report = {"obstacles": [], "area_sweeps": [], "mesh_spacing": {}}
    report["contact_subdivisions"] = contact_subdivisions
    study_sim = partial(
        make_study_simulator, friction=friction, device=device, contact_subdivisions=contact_subdivisions
    )

    o_state = _states([obstacle_state])[0]
    sensor = membrane(obstacle_cap_divisions)
    report["mesh_spacing"][str(obstacle_cap_divisions)] = mesh_spacing(sensor)
    results = []
    for name, spec in obstacles.items():
        spec = dict(spec)
        indenter = make_indenter(spec.pop("kind"), **spec)
        sim = study_sim(sensor, indenter, o_state)
        t = time.perf_counter()
        r = contact_region_experiment(sim, obstacle_depth, classification, contact_tolerance, max_step)
        results.append(r)
        report["obstacles"].append({"name": name, **r.summary(), "seconds": time.perf_counter() - t})
        log(
            f"{name}: IoU {r.comparison.iou:.3f}, boundary error mean "
            f"{1e3 * r.comparison.mean_boundary_distance:.2f} "
            f"max {1e3 * r.comparison.max_boundary_distance:.2f} mm, "
            f"area est {1e4 * r.comparison.estimated_area:.3f} "
            f"true {1e4 * r.comparison.true_area:.3f} cm^2"
        )
    if results:
        study_plots.plot_contact_regions(results, out / "contact_regions.png")

    sweeps = []
    for diameter, cap in _per_diameter(sphere_diameters, sweep_cap_divisions, "area sweep"):
        sensor = membrane(cap)
        spacing = mesh_spacing(sensor)
        report["mesh_spacing"][str(cap)] = spacing
        for state in _states(sweep_states):
            sim = study_sim(sensor, SphereIndenter(radius=0.5 * diameter), state)
            s = area_sweep(
                sim, sweep_depths, classification, contact_tolerance, max_step, state.label, state.closed
            )
            sweeps.append(s)
            entry = to_jsonable(s)
            entry.update(
                cap_divisions=cap, mesh_spacing=spacing, under_resolved=bool(s.contact_points.max() <= 1)
            )
            report["area_sweeps"].append(entry)
            log(
                f"{1e3 * diameter:g} mm sphere, {state.label} (PV {s.pv:.2f} N m): contact area "
                f"{np.round(1e4 * s.contact_area, 3).tolist()} cm^2, deformed "
                f"{np.round(1e4 * s.deformed_area, 2).tolist()}"
                f" cm^2 ({s.seconds:.1f} s)"
            )
    if sweeps:
        study_plots.plot_area_sweeps(sweeps, out / "contact_area.png", "contact_area")
        study_plots.plot_area_sweeps(sweeps, out / "deformed_area.png", "deformed_area")
    report["seconds"] = time.perf_counter() - t0
    report = to_jsonable(report)
    (out / "contact_regions.json").write_text(json.dumps(report, indent=1))
    return report


def run_force_model_study(
    out_dir,
    sphere_diameters=(0.01, 0.02, 0.03),
    cap_divisions=(8, 8, 8),
    states=(
        {"gauge_pressure": 500.0, "closed": True},
        {"gauge_pressure": 1000.0, "closed": True},
        {"gauge_pressure": 1500.0, "closed": True},
        {"gauge_pressure": 2000.0, "closed": True},
        {"gauge_pressure": 2500.0, "closed": True},
        {"gauge_pressure": 0.0, "closed": False},
    ),
    depths=(0.002, 0.004, 0.006, 0.008, 0.01),
    polynomial_order: int = 4,
    matching_diameter: float = 0.01,
    matching_states=(0, 2, 4),
    desired_force_fractions=(0.25, 0.5, 0.75),
    trials: int = 1,
    gain: float = 0.8,
    controller_max_step: float = 0.002,
    indentation_tolerance: float = 5.0e-5,
    max_steps: int = 12,
    depth_noise: float = 0.0,
    indentation_percentile: float = 100.0,
    seed: int = 0,
    layers: int = 2,
    friction: float = 0.5,
    max_step: float = 0.002,
    device: str | None = "cpu",
    contact_subdivisions: int = 1,
    log=print,
) -> dict:
    """Figs 2.9-2.11 and Table 2.1 on the simulated sensor; writes PNGs and ``force_models.json``
    (FEM solves and camera on the Warp ``device``; ``contact_subdivisions`` as in
    :func:`run_contact_region_study`).

    ``matching_states`` index ``states`` (closed ones, inside the PV range of the polynomial); the desired
    forces at a state are ``desired_force_fractions`` of the largest force its characterization reached.
    """
    from pathlib import Path

    from defgraspnets.tactile import study_plots

    fem.SolverOptions(contact_subdivisions=contact_subdivisions)  # a bad value is named before any solve
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    membrane = _membranes(layers)
    gas = _states(states)
    pairs = _per_diameter(sphere_diameters, cap_divisions, "force sweep")
    if not pairs:
        raise ValueError("the force study needs at least one sphere diameter")
    if float(matching_diameter) not in [d for d, _ in pairs]:
        raise ValueError(
            f"matching_diameter {matching_diameter} must be one of sphere_diameters {sphere_diameters}"
        )
    for i in matching_states:
        if not (0 <= int(i) < len(gas)) or not gas[int(i)].closed:
            raise ValueError(f"matching_states must index closed states of `states`, got {i}")
    fractions = np.asarray(desired_force_fractions, dtype=np.float64)
    if fractions.size < 1 or np.any(fractions <= 0) or np.any(fractions >= 1):
        raise ValueError(f"desired_force_fractions must lie in (0, 1), got {fractions.tolist()}")
    t0 = time.perf_counter()
    report = {
        "sweeps": [],
        "polynomials": {},
        "force_matching": [],
        "table_2_1": {},
        "mesh_spacing": {},
        "contact_subdivisions": contact_subdivisions,
    }
    sweeps, sims = [], {}
    for diameter, cap in pairs:
        sensor = membrane(cap)
        report["mesh_spacing"][str(cap)] = mesh_spacing(sensor)
        for k, state in enumerate(gas):
            sim = make_study_simulator(
                sensor,
                SphereIndenter(radius=0.5 * diameter),
                state,
                friction=friction,
                device=device,
                contact_subdivisions=contact_subdivisions,
            )
            s = force_sweep(sim, depths, max_step, state.label, state.closed)
            sweeps.append(s)
            if diameter == float(matching_diameter) and k in [int(i) for i in matching_states]:
                sims[k] = (sim, s)
            entry = to_jsonable(s)
            entry.update(cap_divisions=cap, under_resolved=bool(s.contact_points.max() <= 1))
            report["sweeps"].append(entry)
            slope = s.linear["slope"] if s.linear else float("nan")
            log(
                f"{1e3 * diameter:g} mm sphere, {state.label} (PV {s.pv:.2f} N m): F = "
                f"{np.round(s.force, 3).tolist()} N at delta {np.round(1e3 * s.indentation, 2).tolist()} mm; "
                f"slope {slope:.1f} N/m ({s.seconds:.1f} s)"
            )
    models = fit_force_models(sweeps, polynomial_order)
    for diameter, model in models.items():
        report["polynomials"][f"{diameter:g}"] = {
            "order": model.slope_fit.order,
            "coefficients": model.slope_fit.coefficients,
            "x_center": model.slope_fit.x_center,
            "x_scale": model.slope_fit.x_scale,
            "residual_std": model.slope_fit.residual_std,
            "pv_range": model.pv_range,
        }
    matching = []
    for k in [int(i) for i in matching_states]:
        sim, s = sims[k]
        controller = ForceMatchingController(
            models[float(matching_diameter)].at(s.pv), gain, controller_max_step
        )
        f_max = float(np.nanmax(s.force))
        t = time.perf_counter()
        r = force_matching(
            sim, controller, fractions * f_max, trials, indentation_tolerance, max_steps, depth_noise,
            indentation_percentile, seed, max_step, s.state,
        )  # fmt: skip
        matching.append(r)
        report["force_matching"].append({**to_jsonable(r), "seconds": time.perf_counter() - t})
        report["table_2_1"][f"{r.pv:.2f}"] = {"mean_error": r.mean_error, "standard_error": r.standard_error}
        log(
            f"force matching at PV {r.pv:.2f} N m: F_des {np.round(r.desired_force, 3).tolist()} -> F_actual "
            f"{np.round(r.actual_force, 3).tolist()} N, error {r.mean_error:+.4f} +- {r.standard_error:.4f} N"
        )
    study_plots.plot_force_curves(sweeps, out / "force_indentation.png")
    study_plots.plot_slope_vs_pv(sweeps, models, out / "slope_vs_pv.png")
    study_plots.plot_force_matching(matching, out / "force_matching.png")
    report["seconds"] = time.perf_counter() - t0
    report = to_jsonable(report)
    (out / "force_models.json").write_text(json.dumps(report, indent=1))
    return report
