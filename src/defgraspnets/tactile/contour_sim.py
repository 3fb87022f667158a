"""Closed-loop contour following in simulation (thesis ch. 4, §4.3 experiments).

Loop, once per control step (1 Hz in the thesis):

    sensor pose T(t) --fast membrane model--> deformed inner surface, true force F(t)
                    --DepthCamera--> depth image --indented_points--> cloud (sensor frame)
                    --contact_depth_proxy (eq. 4.6 over the indented pixels)--> F~(t)
    ContourFollower(cloud, T(t), F~(t)) --eqs 4.1-4.5--> T(t+1)

The mechanics are the calibrated :class:`~defgraspnets.tactile.fast_membrane.FastMembrane`; the
observation pipeline is the real one (camera, Algorithm-1 deformation test, eq. 4.6).

The controller's "deformed point cloud" is the *contact core* of the indentation (:func:`indented_points`):
pixels pushed toward the camera by more than the deformation threshold *and* by more than ``core_fraction``
(0.5) of the reading's largest indentation — the black contact portion of Fig. 5.2. The plain 1 mm test is
not usable for edge mode: the membrane spreads an edge contact's indentation over its screening length
(~22 mm), so at a 2-3 N touch on the 0.5" pipe about 1 200 pixels covering a 66 x 59 mm patch of the
dome pass it, a nearly isotropic cloud (principal standard deviations 17 vs 15 mm). Its first principal
component then jumps between the pipe axis and its perpendicular from step to step; the sign rule
(agree with the previous tangent) is blind to a 90 deg swap (``v . v_prev ~ 0``), so after a swap back the
follower reverses with probability 1/2. Measured with the 1 mm test alone (K_v = 1 cm): the straight pipe
ended 0.006 m *behind* its start after 45 steps; the curved pipe's net progress changed sign with the
gains (0.09 m behind in one 60-step run). With the contact core (same gains): 0.41 m and 0.54 m forward.
The outward bulge of the sealed gas (FEM sensor) is excluded as in F~ (eq. 4.6).

The rigid housing (the camera cylinder below the clamped rim, ``0 <= z <= z_rim``, radius ``R_o``) is checked
against the scene every step: contact there is a failure (Fig. 4.3).

Scenes (:func:`standard_scenes`, world frame, metres):

- ``straight_pipe`` — a 0.5" (r = 6.35 mm) pipe along +y, edge mode;
- ``curved_pipe`` — the same pipe bent in 3-D (a lateral S-bend of 0.10 m and a 0.04 m dip), edge mode
  (the flexible gas connector of Fig. 5.3 / the curved pipe of Fig. 4.3);
- ``shelf_corner`` — a bookcase shelf board (18 mm, front edge along +x at y = z = 0) meeting a side
  panel (x = 0.25 m) whose front edge rises vertically; the sensor wipes the board's edge and meets the
  panel where the edge turns upward (Fig. 4.7), edge mode;
- ``limb`` — a forearm-like cylinder (r = 45 mm) along +x with a 20 mm Gaussian bump (a knee or elbow),
  surface mode in the vertical plane through the limb axis (Figs. 4.8-4.9).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.camera import DepthCamera
from defgraspnets.tactile.contour import (
    ContourFollower,
    ContourParameters,
    ContourRunMetrics,
    contour_run_metrics,
)
from defgraspnets.tactile.fast_membrane import FastMembrane, FastMembraneState, contact_depth_proxy
from defgraspnets.tactile.sdf import BoxSDF, BumpyCylinderSDF, SignedDistance, TubeSDF, UnionSDF

#: :class:`TactileSimulation` ``point_weighting`` choices.
POINT_WEIGHTINGS = ("count", "depth")

__all__ = [
    "ContourRun",
    "ContourScene",
    "ContourStudy",
    "Observation",
    "TactileSimulation",
    "build_fast_simulation",
    "contour_following_study",
    "force_proxy_correlation",
    "pearson_r",
    "pole_height",
    "pole_positions",
    "run_report",
    "curved_pipe_scene",
    "housing_points",
    "indented_points",
    "limb_scene",
    "path_progress",
    "pose_from",
    "run_contour_following",
    "shelf_corner_scene",
    "standard_scenes",
    "straight_pipe_scene",
]

PIPE_RADIUS = 0.00635  # m: the thesis's 0.5" pipe


def pose_from(position, approach) -> np.ndarray:
    """World <- sensor pose at ``position`` whose sensor +z (membrane pole) points along ``approach``.

    The sensor x axis is the world x (or y when approach is along x) made orthogonal to it.
    """
    a = np.asarray(approach, dtype=np.float64)
    a = a / np.linalg.norm(a)
    ref = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ a) * a
    x /= np.linalg.norm(x)
    t = np.eye(4)
    t[:3, :3] = np.stack([x, np.cross(a, x), a], axis=1)
    t[:3, 3] = position
    return t


def housing_points(dimensions, rings: int = 12, per_ring: int = 48) -> np.ndarray:
    """Sample points (sensor frame) of the rigid housing: cylinder ``r = R_o, 0 <= z <= z_rim``, base disk."""
    r = dimensions.outer_radius
    z = np.linspace(0.0, dimensions.z_rim, rings)
    phi = np.linspace(0.0, 2 * np.pi, per_ring, endpoint=False)
    side = np.stack(
        np.broadcast_arrays(r * np.cos(phi)[None], r * np.sin(phi)[None], z[:, None]), -1
    ).reshape(-1, 3)
    radii = np.linspace(0.0, r, 5)[:, None]
    disk = np.stack(np.broadcast_arrays(radii * np.cos(phi), radii * np.sin(phi), 0.0 * radii), -1).reshape(
        -1, 3
    )
    return np.concatenate([side, disk])


def indented_points(
    points,
    depth,
    reference_depth,
    threshold: float = 1.0e-3,
    core_fraction: float = 0.0,
    return_excess: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Points of an organized cloud pushed toward the camera by more than ``threshold`` [m] and by more than
    ``core_fraction`` times the largest indentation of the reading (the contact core).

    Args:
        points: (H, W, 3) organized cloud [m] of the current reading.
        depth: (H, W) its depth image [m] (NaN where no return).
        reference_depth: (H, W) depth image of the undeformed (inflated, contact-free) membrane [m].
        threshold: indentation depth above which a pixel belongs to the contact region [m].
        core_fraction: in [0, 1); keep only pixels indented by more than this fraction of the maximum
            indentation (0: the plain threshold).
        return_excess: also return each point's indentation beyond the cut (``max(threshold, core_fraction
            x max indentation)``), (N,) [m], > 0: a weight that falls continuously to 0 at the outline.

    Returns:
        (N, 3) points [m], N may be 0; with ``return_excess`` the pair (points, excess).
    """
    p = np.asarray(points, dtype=np.float64)
    d = np.asarray(depth, dtype=np.float64)
    d0 = np.asarray(reference_depth, dtype=np.float64)
    if d.ndim != 2 or d.shape != d0.shape or p.shape != (*d.shape, 3):
        raise ValueError(
            "need points (H, W, 3) with depth and reference_depth (H, W), "
            f"got {p.shape}, {d.shape}, {d0.shape}"
        )
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0 m, got {threshold}")
    if not 0.0 <= core_fraction < 1.0:
        raise ValueError(f"core_fraction must lie in [0, 1), got {core_fraction}")
    ind = d0 - d
    ok = np.isfinite(ind) & np.isfinite(p).all(axis=2)
    if not ok.any():
        return (np.empty((0, 3)), np.empty(0)) if return_excess else np.empty((0, 3))
    cut = max(threshold, core_fraction * float(ind[ok].max()))
    keep = ok & (ind > cut)
    return (p[keep], ind[keep] - cut) if return_excess else p[keep]


@dataclass(frozen=True)
class Observation:
    """One simulated reading.

    Attributes:
        points: (N, 3) indented membrane points (:func:`indented_points`), sensor frame [m] (the
            controller's and the LfD features' input).
        depth_proxy: ``F~`` of eq. (4.6) [m] over the indented pixels
            (:func:`~defgraspnets.tactile.fast_membrane.contact_depth_proxy`).
        normal_force: the fast model's contact force magnitude [N] (the "external F/T sensor").
        in_contact: the membrane touches the scene (model state, not the camera's view).
        housing_contact: the rigid housing (or clamped rim) touches the scene.
        state: the fast model's state.
        depth: (H, W) depth image [m].
        weights: (N,) weight of each point for the features (``TactileSimulation.point_weighting``), None:
            every point counts once.
    """

    points: np.ndarray
    depth_proxy: float
    normal_force: float
    in_contact: bool
    housing_contact: bool
    state: FastMembraneState
    depth: np.ndarray = field(repr=False)
    weights: np.ndarray | None = field(default=None, repr=False)


class TactileSimulation:
    """Fast membrane mechanics + the real observation pipeline.

    Args:
        model: the calibrated fast membrane.
        camera: the interior depth camera.
        deformation_threshold: indentation above which a pixel is deformed [m] (Algorithm 1).
        core_fraction: the observed cloud keeps the pixels indented by more than this fraction of the
            reading's largest indentation (:func:`indented_points`; 0 keeps every indented pixel).
        point_weighting: ``"count"``: every observed point counts once in the features
            (``Observation.weights`` None); ``"depth"``: each point is weighted by its indentation beyond the
            core cut (:func:`indented_points` ``return_excess``), a ramp that is 0 at the core's outline, so
            pixels entering or leaving the core do not move the features in steps.
    """

    def __init__(
        self,
        model: FastMembrane,
        camera: DepthCamera,
        deformation_threshold: float = 1.0e-3,
        core_fraction: float = 0.5,
        point_weighting: str = "count",
    ):
        if not deformation_threshold > 0:
            raise ValueError(f"deformation_threshold must be > 0 m, got {deformation_threshold}")
        if not 0.0 <= core_fraction < 1.0:
            raise ValueError(f"core_fraction must lie in [0, 1), got {core_fraction}")
        if point_weighting not in POINT_WEIGHTINGS:
            raise ValueError(f"point_weighting must be one of {POINT_WEIGHTINGS}, got {point_weighting!r}")
        self.core_fraction = float(core_fraction)
        self.point_weighting = point_weighting
        self.model = model
        self.camera = camera
        self.deformation_threshold = float(deformation_threshold)
        frame = camera.render(*model.sensor.inner_surface(model.reference), noisy=False)
        self.reference_depth = frame.depth
        self.reference_points = frame.points
        self.housing = housing_points(model.sensor.dimensions)

    def housing_contact(self, scene: SignedDistance, sensor_pose) -> bool:
        t = np.asarray(sensor_pose, dtype=np.float64)
        return bool((scene.distance(self.housing @ t[:3, :3].T + t[:3, 3]) < 0).any())

    def observe(
        self, scene: SignedDistance, sensor_pose, rng: np.random.Generator | None = None
    ) -> Observation:
        state = self.model.solve(scene, sensor_pose)
        frame = self.camera.render(*self.model.inner_surface(state), rng=rng)
        pts, excess = indented_points(
            frame.points,
            frame.depth,
            self.reference_depth,
            self.deformation_threshold,
            self.core_fraction,
            return_excess=True,
        )
        weights = excess if self.point_weighting == "depth" else None
        proxy = contact_depth_proxy(frame.depth, self.reference_depth, self.deformation_threshold)
        housing = state.clamped_contact or self.housing_contact(scene, sensor_pose)
        return Observation(
            pts, proxy, state.normal_force, state.in_contact, housing, state, frame.depth, weights
        )


@dataclass(frozen=True)
class ContourScene:
    """A contour-following task: the rigid scene, the start pose and the controller settings.

    Attributes:
        name: scene label.
        sdf: the rigid scene (world frame).
        start_pose: (4, 4) world <- sensor pose before the approach.
        mode, plane_normal, search_direction, travel_direction: controller settings (see
            :class:`~defgraspnets.tactile.contour.ContourParameters`).
        progress_direction: world direction for the distance covered.
        steps: control steps to run.
        path: (K, 3) the edge or surface line to follow (for plots and path-error metrics).
    """

    name: str
    sdf: SignedDistance
    start_pose: np.ndarray
    mode: str
    search_direction: tuple
    travel_direction: tuple
    progress_direction: tuple
    steps: int
    path: np.ndarray
    plane_normal: tuple | None = None

    def parameters(self, base: ContourParameters) -> ContourParameters:
        """``base`` gains with this scene's mode and directions."""
        return replace(
            base,
            mode=self.mode,
            plane_normal=self.plane_normal,
            search_direction=self.search_direction,
            travel_direction=self.travel_direction,
        )


def _start_above(point, approach, clearance: float, model_pole_height: float) -> np.ndarray:
    a = np.asarray(approach, dtype=np.float64)
    a /= np.linalg.norm(a)
    return pose_from(np.asarray(point) - a * (model_pole_height + clearance), a)


def straight_pipe_scene(
    pole_height: float,
    origin=(0.0, 0.0, 0.0),
    yaw: float = 0.0,
    pitch: float = 0.0,
    length: float = 0.6,
    steps: int = 45,
    clearance: float = 0.02,
) -> ContourScene:
    """A straight 0.5" pipe starting at ``origin``, heading +y turned by ``yaw`` (about z) and ``pitch``."""
    rot = Rotation.from_euler("zx", [yaw, pitch]).as_matrix()
    axis = rot @ np.array([0.0, 1.0, 0.0])
    o = np.asarray(origin, dtype=np.float64)
    line = o + np.linspace(-0.1, length, 2)[:, None] * axis
    start = o + 0.05 * axis + np.array([0.0, 0.0, PIPE_RADIUS])
    return ContourScene(
        "straight_pipe", TubeSDF(line, PIPE_RADIUS), _start_above(start, (0, 0, -1), clearance, pole_height),
        "edge", (0.0, 0.0, -1.0), tuple(axis), tuple(axis), steps, line,
    )  # fmt: skip


def curved_pipe_scene(pole_height: float, steps: int = 60, clearance: float = 0.02) -> ContourScene:
    """A 0.5" pipe bent in 3-D: a lateral S-bend (0.10 m) and a dip (0.04 m) while heading +y."""
    s = np.linspace(-0.1, 0.7, 400)
    u = np.clip(s / 0.6, 0.0, 1.0)
    x = 0.10 * (3 * u**2 - 2 * u**3)  # smoothstep S-bend
    z = -0.04 * np.sin(np.pi * u) ** 2  # a dip
    line = np.stack([x, s, z], axis=1)
    start = np.array([0.0, 0.05, PIPE_RADIUS])
    return ContourScene(
        "curved_pipe", TubeSDF(line, PIPE_RADIUS), _start_above(start, (0, 0, -1), clearance, pole_height),
        "edge", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (0.0, 1.0, 0.0), steps, line,
    )  # fmt: skip


def shelf_corner_scene(
    pole_height: float, steps: int = 50, clearance: float = 0.02, side: float = 0.25, board: float = 0.018
) -> ContourScene:
    """A bookcase shelf: an 18 mm board (top at z = 0, front face at y = 0, extending to +y) meeting a side
    panel at x = ``side`` that rises to z = 0.4 m. The sensor lowers at 45 deg onto the board's front edge,
    wipes it along +x and meets the panel, whose front edge turns upward (Fig. 4.7)."""
    depth = 0.3
    shelf = BoxSDF((side / 2 - 0.25, depth / 2, -board / 2), (side / 2 + 0.25, depth / 2, board / 2))
    panel = BoxSDF((side + board / 2, depth / 2, 0.2 - board / 2), (board / 2, depth / 2, 0.2))
    a = np.array([0.0, 1.0, -1.0]) / np.sqrt(2.0)
    path = np.array([[0.0, 0.0, 0.0], [side, 0.0, 0.0], [side, 0.0, 0.4]])
    return ContourScene(
        "shelf_corner", UnionSDF((shelf, panel)), _start_above((0.05, 0.0, 0.0), a, clearance, pole_height),
        "edge", tuple(a), (1.0, 0.0, 0.0), (1.0, 0.0, 0.0), steps, path,
    )  # fmt: skip


def limb_scene(pole_height: float, steps: int = 45, clearance: float = 0.02) -> ContourScene:
    """Forearm-like cylinder (r = 45 mm) along +x with a 20 mm bump at x = 0.25 m; surface mode, n_p = y."""
    limb = BumpyCylinderSDF((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.045, 0.02, 0.25, 0.04)
    xs = np.linspace(-0.05, 0.55, 200)
    path = np.stack([xs, 0 * xs, limb.profile(xs)[0]], axis=1)
    return ContourScene(
        "limb", limb, _start_above((0.03, 0.0, 0.045), (0, 0, -1), clearance, pole_height),
        "surface", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (1.0, 0.0, 0.0), steps, path,
        plane_normal=(0.0, 1.0, 0.0),
    )  # fmt: skip


def standard_scenes(pole_height: float) -> dict[str, ContourScene]:
    """The four scenes of the module docstring, keyed by name."""
    return {
        s.name: s
        for s in (
            straight_pipe_scene(pole_height),
            curved_pipe_scene(pole_height),
            shelf_corner_scene(pole_height),
            limb_scene(pole_height),
        )
    }


@dataclass(frozen=True)
class ContourRun:
    """Log of one closed-loop run (T steps) and its metrics.

    Attributes:
        poses: (T, 4, 4) sensor poses at which each reading was taken.
        in_contact, housing_contact: (T,) bool.
        depth_proxy: (T,) ``F~`` [m]; normal_force: (T,) true force [N].
        n_points: (T,) deformed points seen.
        metrics: :class:`~defgraspnets.tactile.contour.ContourRunMetrics` (force in ``F~`` units; the
            force tracking in newtons and the distance along the scene's path are in :func:`run_report`).
        stopped_early: why the run stopped before its last step (None: it did not).
    """

    poses: np.ndarray
    in_contact: np.ndarray
    housing_contact: np.ndarray
    depth_proxy: np.ndarray
    normal_force: np.ndarray
    n_points: np.ndarray
    metrics: ContourRunMetrics
    stopped_early: str | None = None

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


def run_contour_following(
    sim: TactileSimulation,
    scene: ContourScene,
    params: ContourParameters,
    steps: int | None = None,
    max_displacement: float = 0.03,
    rng: np.random.Generator | None = None,
) -> ContourRun:
    """Close the loop of the module docstring on ``scene`` with the gains of ``params``.

    The run stops early (``stopped_early`` says why) if the membrane would be pushed further than
    ``max_displacement`` [m] (beyond the fast model's range: the sensor is crushing the object).
    """
    p = scene.parameters(params)
    follower = ContourFollower(p)
    pose = np.asarray(scene.start_pose, dtype=np.float64).copy()
    n = scene.steps if steps is None else int(steps)
    if n < 1:
        raise ValueError(f"steps must be >= 1, got {n}")
    log = {k: [] for k in ("pose", "contact", "housing", "proxy", "force", "npts")}
    stopped = None
    for _ in range(n):
        obs = sim.observe(scene.sdf, pose, rng)
        log["pose"].append(pose.copy())
        log["contact"].append(obs.in_contact)
        log["housing"].append(obs.housing_contact)
        log["proxy"].append(obs.depth_proxy)
        log["force"].append(obs.normal_force)
        log["npts"].append(obs.points.shape[0])
        if obs.state.max_displacement > max_displacement:
            stopped = f"membrane displacement {obs.state.max_displacement:.3f} m > {max_displacement} m"
            break
        pose = follower.step(obs.points, pose, obs.depth_proxy).pose
    poses = np.array(log["pose"])
    contact = np.array(log["contact"], dtype=bool)
    housing = np.array(log["housing"], dtype=bool)
    proxy = np.array(log["proxy"])
    metrics = contour_run_metrics(
        poses[:, :3, 3], contact, proxy, p.desired_force, housing, scene.progress_direction
    )
    return ContourRun(
        poses, contact, housing, proxy, np.array(log["force"]), np.array(log["npts"]), metrics, stopped
    )


def build_fast_simulation(
    cap_divisions: int = 12,
    gauge_pressure: float = 1500.0,
    camera_scale: float = 0.5,
    calibration=None,
    deformation_threshold: float = 1.0e-3,
    core_fraction: float = 0.5,
    contact_samples_per_face: int = 0,
    contact_edge_radius: float = 0.0,
    point_weighting: str = "count",
    mirror_symmetric: bool = False,
) -> TactileSimulation:
    """The membrane mesh FEM-inflated to ``gauge_pressure`` [Pa], the calibrated fast model on it and the
    interior camera (pico flexx at ``camera_scale`` of its resolution): the closed loop's sensor
    (``calibration``: a :class:`~defgraspnets.tactile.fast_membrane.FastMembraneCalibration` or a mapping of
    its three constants, None for the default; ``deformation_threshold``, ``core_fraction``: see
    :class:`TactileSimulation`;
    ``contact_samples_per_face`` (0: vertex-wise contact; (n + 1)(n + 2) / 2: sub-vertex contact) and
    ``contact_edge_radius`` [m]: see :class:`~defgraspnets.tactile.fast_membrane.FastMembrane`;
    ``point_weighting``: see :class:`TactileSimulation`; ``mirror_symmetric``: the membrane mesh's skirt
    split mirror-symmetrically (:func:`~defgraspnets.tactile.membrane.build_membrane`) and the inflated
    reference's asymmetric part averaged out (:func:`~defgraspnets.tactile.membrane.mirror_average`): the
    fast model then reads mirrored scenes exactly mirrored)."""
    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.fast_membrane import DEFAULT_CALIBRATION, FastMembraneCalibration
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane, mirror_average

    if calibration is not None and not isinstance(calibration, FastMembraneCalibration):
        calibration = FastMembraneCalibration(**{k: float(v) for k, v in dict(calibration).items()})
    sensor = build_membrane(cap_divisions=cap_divisions, layers=2, mirror_symmetric=mirror_symmetric)
    inflated = make_simulator(sensor, SphereIndenter(radius=0.01), gauge_pressure, False, intrinsics=None)
    reference = inflated.reference.positions
    if mirror_symmetric:
        reference = mirror_average(sensor, reference)
    model = FastMembrane(
        sensor,
        reference,
        calibration or DEFAULT_CALIBRATION,
        contact_samples_per_face=contact_samples_per_face,
        contact_edge_radius=contact_edge_radius,
    )
    camera = DepthCamera(PICO_FLEXX.scaled(camera_scale))
    return TactileSimulation(model, camera, deformation_threshold, core_fraction, point_weighting)


def pole_height(sim: TactileSimulation) -> float:
    """Height of the inflated outer pole above the sensor origin [m]."""
    return float(sim.model.outer_reference[:, 2].max())


def path_progress(path, points) -> np.ndarray:
    """Arc length [m] along the polyline ``path`` (K, 3) of the closest path point to each of ``points``.

    ``points`` is (T, 3). The distance a contour follower has covered *along the object* is
    ``s[-1] - s[0]`` of the membrane pole's positions; it is negative when the follower went backwards.
    """
    c = np.asarray(path, dtype=np.float64)
    q = np.asarray(points, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 2 or not np.isfinite(c).all():
        raise ValueError(f"path must be a finite (K, 3) polyline with K >= 2, got {c.shape}")
    if q.ndim != 2 or q.shape[1] != 3 or not np.isfinite(q).all():
        raise ValueError(f"points must be finite with shape (T, 3), got {q.shape}")
    a, seg = c[:-1], np.diff(c, axis=0)
    length = np.linalg.norm(seg, axis=1)
    if not (length > 0).all():
        raise ValueError("path has repeated consecutive vertices")
    s0 = np.concatenate([[0.0], np.cumsum(length)])[:-1]
    # (T, K-1) parameter of the projection of each point on each segment, clipped to the segment
    u = np.clip(np.einsum("tkd,kd->tk", q[:, None, :] - a[None], seg) / length**2, 0.0, 1.0)
    foot = a[None] + u[..., None] * seg[None]
    k = np.argmin(np.linalg.norm(q[:, None, :] - foot, axis=2), axis=1)
    rows = np.arange(q.shape[0])
    return s0[k] + u[rows, k] * length[k]


def pole_positions(run: ContourRun, height: float) -> np.ndarray:
    """(T, 3) world positions of the membrane pole (sensor-frame point ``(0, 0, height)``) over a run."""
    return run.poses[:, :3, :3] @ np.array([0.0, 0.0, float(height)]) + run.positions


def pearson_r(x, y) -> float:
    """Pearson correlation coefficient of two equal-length samples (NaN if either is constant)."""
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size < 2:
        raise ValueError(f"need two 1D samples of equal length >= 2, got {a.shape}, {b.shape}")
    if a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def run_report(run: ContourRun, desired_force: float, scene: ContourScene | None = None, height=None) -> dict:
    """JSON-ready summary of one run: the metrics of :func:`contour_run_metrics` plus the true force and,
    given the ``scene`` and the pole ``height`` [m], the distance covered along the scene's path.

    Force tracking in newtons: ``true_force_rms_error_N`` is the RMS of ``F - F_des,N`` over the contact
    steps, ``F_des,N`` [N] being the force that the run's own least-squares line ``F = a F~ + b`` (over
    its contact steps) assigns to ``F~_des`` = ``desired_force``; ``force_proxy_pearson_r`` is the
    correlation of ``F~`` and ``F`` over those steps (the Fig. 4.4 analogue within one scene). NaN with
    fewer than 3 contact steps."""
    m = run.metrics
    along_path = float("nan")
    if scene is not None and height is not None:
        s = path_progress(scene.path, pole_positions(run, height))
        along_path = float(s[-1] - s[0])
    c = run.in_contact
    first = int(np.argmax(c)) if c.any() else len(c)
    force = run.normal_force[c]
    desired_newton, rms_newton, proxy_r = float("nan"), float("nan"), float("nan")
    if force.size >= 3 and np.ptp(run.depth_proxy[c]) > 0:
        slope, intercept = np.polyfit(run.depth_proxy[c], force, 1)
        desired_newton = float(slope * desired_force + intercept)
        rms_newton = float(np.sqrt(np.mean((force - desired_newton) ** 2)))
        if np.ptp(force) > 0:
            proxy_r = pearson_r(run.depth_proxy[c], force)
    return {
        "steps": int(len(c)),
        "first_contact_step": first,
        "contact_fraction": m.contact_fraction,
        "depth_proxy_rms_error_m": m.force_rms_error,
        "desired_depth_proxy_m": desired_force,
        "true_force_mean_N": float(force.mean()) if force.size else float("nan"),
        "true_force_std_N": float(force.std()) if force.size else float("nan"),
        "true_force_max_N": float(force.max()) if force.size else float("nan"),
        "desired_force_N": desired_newton,
        "true_force_rms_error_N": rms_newton,
        "force_proxy_pearson_r": proxy_r,
        "path_length_m": m.path_length,
        "distance_along_m": m.distance_along,
        "distance_along_path_m": along_path,
        "housing_contact_steps": m.housing_contact_steps,
        "stopped_early": run.stopped_early,
    }


def force_proxy_correlation(runs: Iterable[ContourRun], calibration=None) -> dict:
    """``F~`` (eq. 4.6) [m] against the true contact force [N] over all in-contact steps of ``runs`` (the
    Fig. 4.4 analogue): Pearson r, the sample count, the least-squares line ``force = a F~ + b`` (``a`` in
    N/m, ``b`` in N) and the FEM correlation recorded in the fast model's ``calibration`` (None without one).
    """
    runs = list(runs)
    proxy = np.concatenate([r.depth_proxy[r.in_contact] for r in runs])
    force = np.concatenate([r.normal_force[r.in_contact] for r in runs])
    r = pearson_r(proxy, force)  # ValueError below two in-contact samples
    slope, intercept = np.polyfit(proxy, force, 1)
    return {
        "pearson_r": r,
        "samples": int(proxy.size),
        "fit_N_per_m": float(slope),
        "fit_intercept_N": float(intercept),
        "fem_pearson_r": None
        if calibration is None
        else calibration.provenance.get("fem_pearson_r_force_vs_contact_depth_proxy"),
    }


@dataclass(frozen=True)
class ContourStudy:
    """The runs of :func:`contour_following_study` and their JSON-ready report.

    Attributes:
        scenes: the scenes run, by name (:func:`standard_scenes`).
        runs: their :class:`ContourRun`, by name.
        height: the sensor's pole height [m] (:func:`pole_height`).
        report: ``scenes`` (per scene :func:`run_report` plus ``wall_time_s``), ``force_proxy_correlation``
            (:func:`force_proxy_correlation`) and ``fast_model_calibration`` (the model's calibration).
    """

    scenes: dict[str, ContourScene]
    runs: dict[str, ContourRun]
    height: float
    report: dict


def contour_following_study(
    sim: TactileSimulation,
    scene_names: Sequence[str],
    params: ContourParameters,
    max_displacement: float = 0.03,
    log: Callable[[str], None] | None = print,
) -> ContourStudy:
    """Contour following (:func:`run_contour_following`) on each named scene of :func:`standard_scenes`
    with the gains of ``params``; ``log`` gets one line per scene (None: quiet)."""
    height = pole_height(sim)
    scenes = standard_scenes(height)
    unknown = sorted(set(scene_names) - set(scenes))
    if unknown:
        raise ValueError(f"unknown scenes {unknown}; choose from {sorted(scenes)}")
    runs, entries = {}, {}
    for name in scene_names:
        t = time.perf_counter()
        runs[name] = run = run_contour_following(sim, scenes[name], params, max_displacement=max_displacement)
        entries[name] = {
            **run_report(run, params.desired_force, scenes[name], height),
            "wall_time_s": time.perf_counter() - t,
        }
        if log is not None:
            log(f"{name}: {entries[name]}")
    calibration = sim.model.calibration
    report = {
        "scenes": entries,
        "force_proxy_correlation": force_proxy_correlation(runs.values(), calibration),
        "fast_model_calibration": calibration.to_dict(),
    }
    return ContourStudy({name: scenes[name] for name in runs}, runs, height, report)
