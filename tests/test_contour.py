"""Contour following (thesis ch. 4) closed in a kinematic simulation with a geometric contact model.

The simulated sensor is an inflated hemispherical membrane imaged from inside by a pinhole
camera; a rigid object deforms it geometrically: along each camera ray the membrane point is
the nearer of the undeformed membrane and the object surface (the membrane wraps the object).
The force measure is the depth-only proxy F~ of eq. (4.6). The real closed loop runs later on
the FEM membrane sensor; this test checks the controller logic and geometry end to end.
"""

from dataclasses import replace

import numpy as np
import pytest

from defgraspnets.tactile.contour import (
    ContourFollower,
    ContourParameters,
    alignment_rotation,
    axis_angle_matrix,
    contour_following_step,
    contour_run_metrics,
    object_normal,
    object_tangent,
)

MEMBRANE_RADIUS = 0.05  # [m]
MEMBRANE_CENTER_Z = 0.02  # sphere centre on the optical axis, sensor frame [m]
HOUSING_LENGTH = 0.05  # rigid cylinder behind the hemisphere [m]


def camera_rays(size=48, focal=20.0):
    r, c = np.mgrid[0:size, 0:size].astype(float)
    d = np.stack([(c - (size - 1) / 2) / focal, (r - (size - 1) / 2) / focal, np.ones((size, size))], -1)
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)


RAYS = camera_rays()


def _membrane_range():
    centre = np.array([0.0, 0.0, MEMBRANE_CENTER_Z])
    b = RAYS @ centre
    return b + np.sqrt(b**2 - centre @ centre + MEMBRANE_RADIUS**2)


REFERENCE_RANGE = _membrane_range()


class Pipe:
    """Infinite rigid cylinder (world frame)."""

    def __init__(self, point, direction, radius):
        self.point = np.asarray(point, float)
        self.direction = np.asarray(direction, float) / np.linalg.norm(direction)
        self.radius = radius

    def ray_entry(self, origin, dirs):
        """Range of the first intersection of rays with the cylinder (inf if missed)."""
        a = self.direction
        w = origin - self.point
        d_perp = dirs - np.outer(dirs @ a, a)
        w_perp = w - (w @ a) * a
        qa = (d_perp**2).sum(1)
        qb = 2 * d_perp @ w_perp
        qc = w_perp @ w_perp - self.radius**2
        disc = qb**2 - 4 * qa * qc
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-qb - np.sqrt(disc)) / (2 * qa)
        return np.where((disc > 0) & (t > 0), t, np.inf)

    def distance(self, x):
        w = x - self.point
        return np.linalg.norm(w - np.outer(w @ self.direction, self.direction), axis=1)


class Plane:
    """Rigid half-space below the plane through ``point`` with upward ``normal`` (world frame)."""

    def __init__(self, point, normal):
        self.point = np.asarray(point, float)
        self.normal = np.asarray(normal, float) / np.linalg.norm(normal)

    def ray_entry(self, origin, dirs):
        denom = dirs @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.point - origin) @ self.normal / denom
        return np.where((denom < 0) & (t > 0), t, np.inf)

    def distance(self, x):
        return (x - self.point) @ self.normal  # signed height above the plane


def sense(pose, obstacle):
    """Deformed points (sensor frame), force proxy F~ (eq. 4.6) and housing contact for a pose."""
    rot, pos = pose[:3, :3], pose[:3, 3]
    t_obj = obstacle.ray_entry(pos, RAYS @ rot.T)
    rng = np.minimum(REFERENCE_RANGE, t_obj)
    deformed = rng < REFERENCE_RANGE - 1e-6
    points = RAYS[deformed] * rng[deformed, None]
    force = float(((REFERENCE_RANGE - rng) * RAYS[:, 2]).sum())  # sum of depth decreases
    # housing: sample the rigid cylinder behind the hemisphere and test for penetration
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    zs = np.linspace(MEMBRANE_CENTER_Z - HOUSING_LENGTH, MEMBRANE_CENTER_Z, 6)
    ring = np.stack(
        np.broadcast_arrays(
            MEMBRANE_RADIUS * np.cos(ang)[:, None], MEMBRANE_RADIUS * np.sin(ang)[:, None], zs[None]
        ),
        -1,
    ).reshape(-1, 3)
    world = ring @ rot.T + pos
    d = obstacle.distance(world)
    housing = bool((d < getattr(obstacle, "radius", 0.0)).any())
    return points, force, housing


def looking_down(position):
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical (approach) axis along -z world
    pose[:3, 3] = position
    return pose


def run(obstacle, params, start, steps):
    follower = ContourFollower(params)
    pose = looking_down(start)
    log = {"pos": [], "contact": [], "force": [], "housing": [], "nr_dot_vo": []}
    for _ in range(steps):
        points, force, housing = sense(pose, obstacle)
        cmd = follower.step(points, pose, force)
        log["pos"].append(pose[:3, 3].copy())
        log["contact"].append(cmd.in_contact)
        log["force"].append(force)
        log["housing"].append(housing)
        n_r = -pose[:3, :3] @ np.array(params.approach_axis)
        log["nr_dot_vo"].append(float(n_r @ cmd.tangent) if cmd.in_contact else np.nan)
        pose = cmd.pose
    return {k: np.array(v) for k, v in log.items()}, pose


def calibrate(obstacle, pose_at, depth=0.003, h=1e-4):
    """Desired F~ at ``depth`` of penetration and the local slope dF~/d(penetration)."""
    f0 = sense(pose_at(depth), obstacle)[1]
    f1 = sense(pose_at(depth + h), obstacle)[1]
    return f0, (f1 - f0) / h


POLE = MEMBRANE_CENTER_Z + MEMBRANE_RADIUS  # pole distance from the camera along the approach axis


@pytest.mark.parametrize("slope_deg", [0.0, 15.0])
def test_edge_mode_keeps_contact_and_travels_along_a_straight_pipe(slope_deg):
    s = np.radians(slope_deg)
    direction = np.array([np.cos(s), 0.0, np.sin(s)])
    pipe = Pipe([0.0, 0.0, 0.0], direction, 0.00635)  # 1/2" pipe as in §5.4
    f_des, dfd = calibrate(pipe, lambda d: looking_down([0.0, 0.0, pipe.radius + POLE - d]))
    params = ContourParameters(
        tracking_step=2e-3,
        force_gain=0.5 / dfd,
        alignment_gain=0.5,
        desired_force=f_des,
        mode="edge",
        travel_direction=(1.0, 0.0, 0.0),
    )
    start = np.array([0.0, 0.004, pipe.radius + POLE + 0.006])  # 6 mm above, 4 mm off the pipe axis
    steps = 80
    log, final = run(pipe, params, start, steps)
    m = contour_run_metrics(log["pos"], log["contact"], log["force"], f_des, log["housing"], direction)
    first = int(np.argmax(log["contact"]))
    assert 0 < first < 10  # approach phase, then contact
    assert m.contact_fraction == 1.0
    assert m.housing_contact_steps == 0
    in_c = log["contact"]
    assert m.force_rms_error < 0.25 * f_des
    assert abs(log["force"][-20:].mean() - f_des) < 0.05 * f_des
    # travels along the edge at ~K_v per step, without drifting off it
    assert m.distance_along > 0.85 * params.tracking_step * (steps - first)
    assert m.path_length < 1.3 * params.tracking_step * steps
    membrane_centre = log["pos"][in_c] + MEMBRANE_CENTER_Z * np.array([0, 0, -1.0])  # approx. (small tilt)
    assert np.abs(pipe.distance(membrane_centre)[first + 5 :] - (MEMBRANE_RADIUS + pipe.radius)).max() < 0.01
    # axis alignment: n_r becomes perpendicular to the tangent (eq. 4.2 drives theta -> 0)
    assert abs(log["nr_dot_vo"][-1]) < 0.02
    if slope_deg > 0:
        assert abs(log["nr_dot_vo"][first]) > 0.2  # it did have to rotate
    approach = final[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert abs(approach @ direction) < 0.02


def test_axis_alignment_term_keeps_the_rigid_housing_off_a_steep_pipe():
    """Fig. 4.3: without (here: with a negligible) axis-alignment term the housing hits the object."""
    s = np.radians(45.0)
    direction = np.array([np.cos(s), 0.0, np.sin(s)])
    pipe = Pipe([0.0, 0.0, 0.0], direction, 0.00635)
    f_des, dfd = calibrate(pipe, lambda d: looking_down([0.0, 0.0, pipe.radius + POLE - d]))
    housing_steps = {}
    for gain in (0.5, 1e-3):
        params = ContourParameters(
            tracking_step=2e-3, force_gain=0.5 / dfd, alignment_gain=gain, desired_force=f_des
        )
        log, _ = run(pipe, params, np.array([0.0, 0.0, pipe.radius + POLE + 0.006]), 60)
        m = contour_run_metrics(log["pos"], log["contact"], log["force"], f_des, log["housing"], direction)
        assert m.contact_fraction == 1.0
        housing_steps[gain] = m.housing_contact_steps
    assert housing_steps[0.5] == 0
    assert housing_steps[1e-3] > 30


def test_surface_mode_follows_a_tilted_plane_in_the_user_plane():
    normal = np.array([-np.sin(np.radians(10)), 0.0, np.cos(np.radians(10))])
    table = Plane([0.0, 0.0, 0.0], normal)
    f_des, dfd = calibrate(table, lambda d: looking_down([0.0, 0.0, POLE - d]), depth=0.002)
    params = ContourParameters(
        tracking_step=2e-3,
        force_gain=0.5 / dfd,
        alignment_gain=0.5,
        desired_force=f_des,
        mode="surface",
        plane_normal=(0.0, 1.0, 0.0),
        travel_direction=(1.0, 0.0, 0.0),
        plane_band=3e-3,
    )  # ~ the pixel spacing of this coarse 48 x 48 camera
    log, _ = run(table, params, np.array([0.0, 0.0, POLE + 0.004]), 60)
    m = contour_run_metrics(log["pos"], log["contact"], log["force"], f_des, log["housing"])
    assert m.contact_fraction == 1.0
    assert abs(log["force"][-10:].mean() - f_des) < 0.1 * f_des
    motion = log["pos"][-1] - log["pos"][20]
    assert abs(motion[1]) < 1e-6  # stays in the user plane (normal n_p = y)
    assert motion[0] > 0.8 * 2e-3 * 40
    assert abs(motion @ normal) / np.linalg.norm(motion) < 0.05  # climbs along the slope


def test_state_quantities_follow_eqs_4_3_to_4_5():
    # edge mode: the first principal component of an elongated cloud
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [0.02, 0.002, 0.001]
    v = object_tangent(pts, "edge", reference_direction=(-1.0, 0.0, 0.0))
    assert v[0] < -0.99
    # surface mode: a disc in z = 0; the slice normal to n_p = y gives the x axis
    xy = rng.uniform(-0.01, 0.01, size=(4000, 2))
    disc = np.column_stack([xy, np.zeros(len(xy))])[np.hypot(*xy.T) < 0.01]
    v = object_tangent(disc, "surface", plane_normal=(0.0, 1.0, 0.0), reference_direction=(1.0, 0.0, 0.0))
    assert v == pytest.approx([1.0, 0.0, 0.0], abs=1e-3)
    n_r = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)
    n_o = object_normal(n_r, [1.0, 0.0, 0.0])
    assert n_o == pytest.approx([0.0, 0.0, 1.0])
    omega, theta = alignment_rotation(n_r, n_o)
    assert theta == pytest.approx(np.arctan(0.3))
    assert axis_angle_matrix(omega, theta) @ n_r == pytest.approx(n_o)
    with pytest.raises(ValueError, match="parallel"):
        object_normal([1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="need at least 2"):
        object_tangent(np.zeros((1, 3)), "edge")


def test_controller_terms_and_no_contact_search():
    params = ContourParameters(tracking_step=0.01, force_gain=0.002, alignment_gain=1.0, desired_force=5.0)
    pose = looking_down([0.0, 0.0, 0.1])
    pts = np.column_stack([np.linspace(-0.02, 0.02, 50), np.zeros(50), np.full(50, 0.07)])
    cmd = contour_following_step(pts, pose, force=3.0, params=params)
    # tracking along +x, force term moves toward the object (-z world) when F < F_des (eq. 4.1)
    assert cmd.translation == pytest.approx([0.01, 0.0, -0.002 * 2.0])
    assert cmd.alignment_angle == pytest.approx(0.0)
    cmd = contour_following_step(pts, pose, force=7.0, params=params)
    assert cmd.translation[2] == pytest.approx(0.004)  # too much force: back off
    idle = contour_following_step(np.zeros((0, 3)), pose, force=0.0, params=params)
    assert not idle.in_contact and idle.translation == pytest.approx([0.0, 0.0, -0.01])
    with pytest.raises(ValueError, match="surface mode needs"):
        ContourParameters(0.01, 0.0, 1.0, 1.0, mode="surface")
    with pytest.raises(ValueError, match="K_theta"):
        ContourParameters(0.01, 0.0, 1.5, 1.0)
    with pytest.raises(ValueError, match="rotation"):
        contour_following_step(pts, np.diag([2.0, 1, 1, 1]), 0.0, params)


def test_alignment_rotation_turns_about_the_contact_so_the_contact_moves_by_eq_4_1_only():
    """Eq. (4.2) turns the sensor over the contact: the contact centroid moves by exactly the tracking and
    force terms of eq. (4.1), whatever theta is. Turning about the end-effector origin (``"origin"``, the
    old behaviour) swings the contact by K_theta theta times the lever arm (~7 cm here, 18 cm on the
    simulated sensor, where it pushed the membrane into a shelf's side panel at the corner)."""
    params = ContourParameters(tracking_step=0.01, force_gain=0.002, alignment_gain=0.5, desired_force=5.0)
    pose = looking_down([0.0, 0.0, 0.1])
    line = np.linspace(-0.02, 0.02, 50)
    pts = np.column_stack([0.01 + line, np.full(50, 0.005), 0.07 + 0.6 * line])  # edge tilted ~31 deg
    world = pts @ pose[:3, :3].T + pose[:3, 3]
    cmd = contour_following_step(pts, pose, force=3.0, params=params)
    assert cmd.alignment_angle > 0.4
    eq41 = 0.01 * cmd.tangent - 0.002 * (5.0 - 3.0) * cmd.normal
    centroid_sensor = pts.mean(axis=0)
    moved = cmd.rotation @ centroid_sensor + cmd.position
    assert moved == pytest.approx(world.mean(axis=0) + eq41, abs=1e-12)
    assert cmd.translation == pytest.approx(cmd.position - pose[:3, 3])
    old = contour_following_step(pts, pose, 3.0, replace(params, rotation_pivot="origin"))
    assert old.position == pytest.approx(pose[:3, 3] + eq41, abs=1e-12)
    assert old.rotation == pytest.approx(cmd.rotation)
    swing = np.linalg.norm(old.rotation @ centroid_sensor + old.position - moved)
    lever = np.linalg.norm(world.mean(axis=0) - pose[:3, 3])
    assert swing > 0.5 * params.alignment_gain * cmd.alignment_angle * lever
    with pytest.raises(ValueError, match="rotation_pivot"):
        replace(params, rotation_pivot="pole")


def test_run_metrics_on_a_synthetic_log():
    pos = np.column_stack([np.arange(6) * 0.01, np.zeros(6), np.zeros(6)])
    contact = np.array([False, True, True, False, True, True])
    force = np.array([0.0, 1.0, 3.0, 0.0, 2.0, 2.0])
    housing = np.array([False, False, True, True, False, False])
    m = contour_run_metrics(pos, contact, force, 2.0, housing, direction=(1.0, 0.0, 0.0))
    assert m.contact_fraction == pytest.approx(4 / 5)
    assert m.force_rms_error == pytest.approx(np.sqrt(2 / 4))
    assert m.path_length == pytest.approx(0.05)
    assert m.distance_along == pytest.approx(0.05)
    assert m.housing_contact_steps == 2
    with pytest.raises(ValueError, match="in_contact"):
        contour_run_metrics(pos, contact[:-1], force, 2.0)
