"""DefGraspSim experiments (pickup, reorientation, linear / angular acceleration) as quasi-static FEM
problems, the 7 performance metrics and the 7 grasp features: analytic checks of the pure functions, and
physics checks of the experiments on a grasp through the centre of mass of a 30 mm box (where Coulomb's law
gives the answers in closed form)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets import fem
from defgraspnets.grasp import features as feat
from defgraspnets.grasp import metrics as met
from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.experiments import (
    ExperimentSettings,
    GraspExperiments,
    GraspFailure,
    pickup_grasp_force,
    reorientation_grasp_force,
    reorientation_gravity,
    sphere_directions,
)
from defgraspnets.grasp.gripper import FRANKA_HAND
from defgraspnets.grasp.sampler import GraspSet
from defgraspnets.grasp.squeeze import FINGER_NAMES

ROOT = Path(__file__).resolve().parents[1]
HALF = 0.015  # half edge of the 30 mm box [m]
MATERIAL = fem.Material(2e5, 0.3, 1000.0)
G = fem.STANDARD_GRAVITY


def centered_grasp() -> GraspSet:
    """One grasp of the box centred at the origin: closing axis (gripper y) along object x, approach
    (gripper z) along object +z, pads centred on the two x faces (the grasp axis passes through the COM)."""
    R = np.column_stack([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # gripper x, y, z
    T = np.eye(4)
    T[:3, :3] = R
    c = FRANKA_HAND.max_finger_opening - HALF
    contacts = np.array([[[HALF, 0, 0], [-HALF, 0, 0]]])
    return GraspSet(
        poses=T[None],
        contact_points=contacts,
        contact_normals=np.array([[[1.0, 0, 0], [-1.0, 0, 0]]]),
        axes=R[None, :, 1],
        angles=np.zeros(1),
        widths=np.array([2 * HALF]),
        closing_distances=np.array([[c, c]]),
        axis_ids=np.zeros(1, dtype=int),
        far_side=np.zeros(1, dtype=bool),
        friction_coefficient=0.7,
        seed=None,
    )


@pytest.fixture(scope="module")
def box():
    return structured_box((2 * HALF,) * 3, (4, 4, 4))


@pytest.fixture(scope="module")
def experiments(box):
    return GraspExperiments(box, centered_grasp(), MATERIAL, device="cpu")


@pytest.fixture(scope="module")
def pickup(experiments):
    return experiments.pickup()


# ---------------------------------------------------------------------------------------------- metrics
def test_rigid_motion_has_no_deformation_and_kabsch_recovers_it():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, 3)) * 0.01
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    t = np.array([0.02, -0.01, 0.5])
    x = X @ R.T + t
    w = rng.uniform(0.5, 2.0, size=40)
    R_fit, t_fit = met.best_rigid_transform(X, x, w)
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, t, atol=1e-12)
    assert met.max_deformation(X, x, w) < 1e-12
    # a deformation orthogonal to every rigid motion survives: a 1 % stretch along z of a grid symmetric
    # about its centre (mirror symmetry makes the stretch orthogonal to the rotations)
    g = np.stack(np.meshgrid(*[np.linspace(-0.01, 0.01, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    moved = (g * [1.0, 1.0, 1.01]) @ R.T + t
    np.testing.assert_allclose(met.rigid_removed_deformation(g, moved), 0.01 * np.abs(g[:, 2]), atol=1e-15)
    # batched: (B, N, 3) with a reflection-free fit even for mirrored data
    both = np.stack([x, X * [1, 1, -1]])
    R_b, _ = met.best_rigid_transform(X, both)
    assert np.allclose(np.linalg.det(R_b), 1.0)
    with pytest.raises(ValueError, match="do not match"):
        met.best_rigid_transform(X, x[:5])
    with pytest.raises(ValueError, match="weights"):
        met.best_rigid_transform(X, x, -w)


def test_von_mises_of_standard_stress_states():
    s = 1.5e3
    uniaxial = np.diag([s, 0, 0])
    shear = np.array([[0, s, 0], [s, 0, 0], [0, 0, 0]])
    hydro = -s * np.eye(3)
    vm = met.von_mises_stress(np.stack([uniaxial, shear, hydro]))
    np.testing.assert_allclose(vm, [s, np.sqrt(3) * s, 0.0], atol=1e-9)
    assert met.max_von_mises_stress(np.stack([uniaxial, shear])[None]) == pytest.approx(np.sqrt(3) * s)
    with pytest.raises(ValueError, match="3, 3"):
        met.von_mises_stress(np.zeros((4, 3)))


def test_instability_and_controllability_aggregate_as_defined():
    a = np.array([[10.0, 20.0, 50.0, np.nan], [np.nan] * 4])
    out = met.instability(a, limit=50.0)
    assert out[0] == pytest.approx(80.0 / 3) and np.isnan(out[1])
    with pytest.raises(ValueError, match=r"\[0, 50"):
        met.instability([60.0], limit=50.0)
    with pytest.raises(ValueError, match="limit"):
        met.instability([1.0], limit=0.0)
    X = np.random.default_rng(1).normal(size=(10, 3))
    states = np.stack([X, X * [1.0, 1.0, 1.1], np.full_like(X, np.nan)])  # the last state was not reached
    expected = met.max_deformation(X, X * [1.0, 1.0, 1.1])
    assert met.deformation_controllability(X, states) == pytest.approx(expected)
    assert np.isnan(met.deformation_controllability(X, np.full((2, 10, 3), np.nan)))
    rec = met.performance_metrics(False, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    assert len(rec) == 7 and rec["max_von_mises_stress_pa"] is None and rec["linear_instability_m_s2"] == 4.0


# ---------------------------------------------------------------------------------------------- features
def test_features_of_a_hand_made_grasp():
    """Two fingers facing each other along x, patches offset by 3 mm in z from a COM at the origin."""
    frames = np.tile(np.eye(4), (1, 2, 1, 1))
    # right finger at x = -0.01 closing along +x (local y = +x), left at +0.01 closing along -x;
    # local z (towards the fingertip) = object +z
    frames[0, 1, :3, :3] = np.column_stack([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    frames[0, 0, :3, :3] = np.column_stack([[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    frames[0, 0, :3, 3] = [0.01, 0, 0]
    frames[0, 1, :3, 3] = [-0.01, 0, 0]
    surface = np.array(
        [[[0.01, -0.002, 0.003], [0.01, 0.002, 0.003], [-0.01, 0.0, 0.003], [0.0, 0.0, -0.01]]]
    )
    forces = np.zeros((1, 2, 4))
    forces[0, 0, :2] = 1.0
    forces[0, 1, 2] = 2.0
    points = np.array([[[0.0, 0.0, 0.01], [0.0, 0.0, -0.01]]])
    f = feat.grasp_features(
        surface, forces, points, np.ones(2), frames, np.array([1e-4]), np.array([0.0202]), pad_length=0.02
    )
    assert set(f) == set(feat.FEATURE_NAMES)
    np.testing.assert_allclose(f["pure_dist"], np.sqrt(0.01**2 + 0.003**2))
    np.testing.assert_allclose(f["perp_dist"], 0.003)
    np.testing.assert_allclose(f["num_contacts"], 1.5)
    np.testing.assert_allclose(f["edge_dist"], 0.01 - 0.003)
    np.testing.assert_allclose(f["squeeze_dist"], 2e-4)
    np.testing.assert_allclose(f["gripper_sep"], 0.02)
    np.testing.assert_allclose(f["grav_align"], np.pi / 2)
    lengths = feat.contact_patch_lengths(surface, forces, frames)
    np.testing.assert_allclose(lengths, [[0.004, 0.0]])
    with pytest.raises(ValueError, match="two fingers"):
        feat.contact_patch_centers(surface, forces[:, :1])
    with pytest.raises(ValueError, match=">= 0"):
        feat.contact_patch_centers(surface, -forces)


# ---------------------------------------------------------------------------------------------- set-up
def test_directions_forces_and_gravity_states():
    d = sphere_directions(16)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(d[0::2], -d[1::2])  # opposite pairs
    cos = d @ d.T
    np.fill_diagonal(cos, -1)
    assert np.degrees(np.arccos(cos.max())) > 30  # regularly spread: no two closer than 30 degrees
    assert abs(d.sum(axis=0)).max() < 1e-12
    g = reorientation_gravity([[1.0, 0, 0], [0, 0, 2.0]], np.pi * np.arange(1, 5) / 4)
    np.testing.assert_allclose(np.linalg.norm(g, axis=-1), G)
    np.testing.assert_allclose(g[0, -1], [0, 0, G], atol=1e-12)  # upside down about x
    np.testing.assert_allclose(g[1], np.tile([0, 0, -G], (4, 1)), atol=1e-12)  # about the vertical: unchanged
    np.testing.assert_allclose(g[0, 1], [0, -G, 0], atol=1e-12)  # R_x(90)^T (0, 0, -g)
    assert pickup_grasp_force(0.027, 0.7) == pytest.approx(1.3 * 0.027 * G / 0.7)
    np.testing.assert_allclose(reorientation_grasp_force(2.0, [0.0, 0.005], [0.01, 0.01], 1e-3), [2.0, 4.0])
    with pytest.raises(ValueError, match="even"):
        sphere_directions(5)
    with pytest.raises(ValueError, match="friction"):
        pickup_grasp_force(0.027, 0.0)


def test_bad_settings_and_inputs_are_named(box):
    with pytest.raises(ValueError, match="num_directions"):
        ExperimentSettings(num_directions=3)
    with pytest.raises(ValueError, match="friction"):
        ExperimentSettings(friction=-0.1)
    with pytest.raises(ValueError, match="acceleration_steps"):
        ExperimentSettings(acceleration_steps=0)
    with pytest.raises(ValueError, match="min_finger_force_fraction"):
        ExperimentSettings(min_finger_force_fraction=1.5)
    grasp = centered_grasp()
    with pytest.raises(ValueError, match="no grasps"):
        GraspExperiments(box, grasp[np.zeros(0, dtype=int)], MATERIAL, device="cpu")
    with pytest.raises(TypeError, match="Material"):
        GraspExperiments(box, grasp, [MATERIAL], device="cpu")
    with pytest.raises(ValueError, match="directions_per_solver"):
        GraspExperiments(box, grasp, MATERIAL, device="cpu", directions_per_solver=0)
    ex = GraspExperiments(box, grasp, MATERIAL, device="cpu")
    with pytest.raises(ValueError, match="kind"):
        ex.acceleration("twist")
    with pytest.raises(ValueError, match="non-zero"):
        ex.acceleration("linear", [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="shake"):
        ex.run(("pickup", "shake"))
    with pytest.raises(ValueError, match="positive"):
        ex.reorientation([-1.0])


# ---------------------------------------------------------------------------------------------- physics
def test_pickup_holds_by_friction_and_strain_energy_is_half_the_work(experiments, pickup, box):
    """mu F_p = 1.3 m g: the pads carry the weight; the skin under the pads sticks (slide ~ 0); the grasp's
    strain energy is half the work of the contact forces (Clapeyron, U = u^T K u / 2 = f^T u / 2)."""
    m = box.mass(MATERIAL.density)
    assert experiments.mass == pytest.approx(m)
    assert pickup.grasp_force == pytest.approx(1.3 * m * G / 0.7)
    assert pickup.success.all() and pickup.failure[0] == GraspFailure.HELD
    assert pickup.slide[0] < 1e-5
    eq = pickup.picked
    # the pads carry the weight: vertical friction forces sum to m g
    lift = sum(eq.contact_friction_force[n][0, :, 2].sum() for n in FINGER_NAMES)
    assert lift == pytest.approx(m * G, rel=1e-3)
    # a grasp through the COM: F_slip = F_p, features as designed
    f = pickup.features
    assert f["perp_dist"][0] < 1e-9 and f["grav_align"][0] == pytest.approx(np.pi / 2)
    assert f["num_contacts"][0] == 9  # the 3 x 3 face vertices under each 15.5 mm pad
    assert f["gripper_sep"][0] == pytest.approx(2 * HALF - f["squeeze_dist"][0])
    assert pickup.slip_force[0] == pytest.approx(pickup.grasp_force)
    # Clapeyron on the squeezed state (linear response: flat pads on flat faces, contact area fixed)
    sq = pickup.squeezed
    surf = box.surface_vertices
    u = sq.displacement[0, surf]
    work = 0.0
    for k, name in enumerate(FINGER_NAMES):
        n = experiments.finger_frames[0, k, :3, 1]
        force = sq.contact_normal_force[name][0, :, None] * n + sq.contact_friction_force[name][0]
        work += np.einsum("sj,sj->", force, u)
    assert sq.strain_energy[0] == pytest.approx(0.5 * work, rel=1e-3)
    assert pickup.strain_energy[0] > sq.strain_energy[0]  # the weight adds shear
    assert 0 < pickup.max_deformation[0] < 1e-3 and pickup.max_von_mises[0] > 0


def test_pickup_fails_when_friction_cannot_carry_the_weight(box):
    """With mu F = 0.5 m g < m g no equilibrium held by friction exists: the object slides out."""
    ex = GraspExperiments(
        box, centered_grasp(), MATERIAL, ExperimentSettings(safety_factor=0.5), device="cpu"
    )
    result = ex.pickup()
    assert not result.success[0]
    assert result.failure[0] in (GraspFailure.NO_EQUILIBRIUM, GraspFailure.SLID)


def test_linear_acceleration_thresholds_match_coulomb(experiments):
    """Zero gravity, total normal force F: tangential loads slide the pads at a = mu F / m, loads along the
    closing axis unload a finger at a = F / m; a diagonal direction fails at the smaller of the two. Opposite
    directions of the symmetric grasp give the same threshold."""
    dirs = [[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1], [0, 1, 0], [0, -1, 0], [1, 1, 0]]
    res = experiments.acceleration("linear", dirs)
    a = res.threshold[0]
    F, m, mu = experiments.pickup_force, experiments.mass, 0.7
    step = res.limit / experiments.settings.acceleration_steps
    tol = step / 8 + 0.02 * mu * F / m  # the solver's bisection resolution and 2 %
    coulomb = mu * F / m
    # no equilibrium can carry more than the Coulomb capacity; the measured limit is close to it
    assert np.all(a[:4] <= coulomb * 1.01) and np.all(a[:4] >= coulomb - tol)
    assert np.all(a[4:6] <= F / m * 1.01) and np.all(a[4:6] >= F / m - tol)
    diagonal = min(coulomb * np.sqrt(2), F / m * np.sqrt(2))  # x: tangential, y: normal, each a / sqrt 2
    assert diagonal - tol <= a[6] <= diagonal * 1.01
    assert abs(a[0] - a[1]) <= step / 8 and abs(a[2] - a[3]) <= step / 8 and abs(a[4] - a[5]) <= step / 8
    assert np.all(res.failure[0] != GraspFailure.HELD)
    assert res.instability[0] == pytest.approx(a.mean())


def test_a_lost_pair_frees_its_problem_for_the_next(box, monkeypatch):
    """The acceleration test streams its (grasp, direction) pairs through G x directions_per_solver
    problems: with one problem, the pair along the pads (they slide at mu F / m) is solved level by level
    until it is lost and no further, then the pair along the closing axis (a finger unloads at F / m) takes
    the problem; the thresholds, failures and Newton iterations are those of both pairs in one batch."""
    from defgraspnets.grasp import experiments as exp_module

    events = []
    real_hold, real_copy = exp_module.hold_state, fem.QuasiStaticSolver.copy_state_from

    def hold(*args, **kwargs):
        hs = real_hold(*args, **kwargs)
        events.append(("level held", bool(hs.held.all()), len(hs.held)))
        return hs

    def copy(self, other, rows, into=None):
        events.append(("start", None, len(rows)))
        return real_copy(self, other, rows, into)

    settings = ExperimentSettings(acceleration_steps=16)
    dirs = [[1, 0, 0], [0, 1, 0]]
    both = GraspExperiments(box, centered_grasp(), MATERIAL, settings, device="cpu", directions_per_solver=2)
    together = both.acceleration("linear", dirs)
    one = GraspExperiments(box, centered_grasp(), MATERIAL, settings, device="cpu", directions_per_solver=1)
    one.acceleration("linear", dirs[:1])  # squeezed before the counting starts
    monkeypatch.setattr(exp_module, "hold_state", hold)
    monkeypatch.setattr(fem.QuasiStaticSolver, "copy_state_from", copy)
    res = one.acceleration("linear", dirs)
    assert all(n == 1 for _, _, n in events)  # one problem: one pair at a time
    starts = [i for i, e in enumerate(events) if e[0] == "start"]
    assert len(starts) == 2 and starts[0] == 0
    first = [held for _, held, _ in events[1 : starts[1]]]  # the first pair's levels checked
    step = res.limit / settings.acceleration_steps
    assert res.failure[0, 0] != GraspFailure.HELD and res.threshold[0, 0] < res.threshold[0, 1]
    # checked at every level it reached and no further: the levels below its threshold (all held) and,
    # where a hold criterion (not a missing equilibrium) failed, the level that failed it
    lost_by_check = res.failure[0, 0] != GraspFailure.NO_EQUILIBRIUM
    assert len(first) == int(np.floor(res.threshold[0, 0] / step)) + int(lost_by_check)
    assert all(first[:-1]) and first[-1] != lost_by_check
    assert len(events) - starts[1] - 1 <= settings.acceleration_steps
    for name in ("threshold", "failure", "solver_status", "newton_iterations"):
        assert np.array_equal(getattr(res, name), getattr(together, name), equal_nan=True), name
    assert np.all(res.newton_iterations > 0)


def test_angular_acceleration_thresholds_are_symmetric(experiments):
    """Twist about the closing axis (torsional friction) and about the approach axis, both signs."""
    res = experiments.acceleration("angular", [[0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    a = res.threshold[0]
    step = res.limit / experiments.settings.acceleration_steps
    assert np.all((a > 0) & (a <= res.limit))
    assert abs(a[0] - a[1]) <= step / 8 + 0.02 * a[0] and abs(a[2] - a[3]) <= step / 8 + 0.02 * a[2]
    # torsion is resisted by friction alone: an upper bound is the torque of mu F acting at the farthest
    # contact vertex (the pad corner, sqrt(2) 7.5 mm) against the moment of inertia about the axis, m a^2 / 6
    I = experiments.mass * (2 * HALF) ** 2 / 6
    bound = 0.7 * experiments.pickup_force * np.sqrt(2) * 0.0075 / I
    assert a[0] <= bound * 1.01


def test_reorientation_holds_every_state_and_records_fields(box):
    """At F_slip (= F_p here) the grasp through the COM holds the object in all 4 x 4 states; gravity turned
    upside down deforms it as much as the upright pickup."""
    ex = GraspExperiments(box, centered_grasp(), MATERIAL, ExperimentSettings(num_directions=4), device="cpu")
    p = ex.pickup()
    r = ex.reorientation(p.slip_force)
    assert r.held.shape == (1, 4, 4) and r.held.all()
    assert np.all(np.isfinite(r.deformation)) and np.all(r.max_von_mises > 0)
    assert r.controllability[0] == pytest.approx(np.nanmax(r.deformation))
    assert r.controllability[0] >= p.max_deformation[0] * 0.9


def test_off_axis_grasp_pivots_at_pickup_force_but_holds_at_slip_force(box):
    """A horizontal grasp 5 mm beside the centre of mass: F_p's friction carries the weight but not its
    moment about the grasp axis (rotational slip); F_slip = F_p (1 + 2 d / L) holds it in every state."""
    from defgraspnets.grasp.sampler import sample_antipodal_grasps

    grasp = sample_antipodal_grasps(box, 2, rotations_per_axis=1, seed=3)[1:]
    ex = GraspExperiments(box, grasp, MATERIAL, ExperimentSettings(num_directions=2), device="cpu")
    p = ex.pickup()
    d = p.features["perp_dist"][0]
    assert 0.003 < d < 0.008 and p.features["grav_align"][0] == pytest.approx(np.pi / 2)
    assert not p.success[0] and p.failure[0] in (GraspFailure.NO_EQUILIBRIUM, GraspFailure.SLID)
    assert p.slip_force[0] > 1.5 * p.grasp_force
    r = ex.reorientation(p.slip_force)
    assert r.held.all() and np.all(r.failure == GraspFailure.HELD)


def _squeeze_every_replica(self, replicas, desc):
    """GraspExperiments._squeezed as it was before the squeeze was shared: every replica squeezed itself."""
    from defgraspnets.grasp.squeeze import squeeze_ramp

    rows = np.repeat(np.arange(self.num_grasps), replicas)
    solver = self._solver(rows)
    eqs = squeeze_ramp(solver, self.pickup_force, self.settings.squeeze_steps)
    return solver, eqs[-1], self.finger_frames[rows][:, :, :3, 1], rows


@pytest.fixture(scope="module")
def two_grasps(box):
    from defgraspnets.grasp.sampler import sample_antipodal_grasps

    return sample_antipodal_grasps(box, 2, rotations_per_axis=1, seed=3)


def _acceleration_stepwise(ex: GraspExperiments, kind: str, dirs) -> tuple:
    """The acceleration test as it was before the pairs were streamed and the squeeze shared: a batch of
    every grasp x direction replica, each squeezed itself, loaded step by step with solve() (every problem
    waits for the batch at each step; a pair whose hold failed keeps its load)."""
    s = ex.settings
    dirs = np.asarray(dirs, dtype=np.float64)
    D, G = len(dirs), ex.num_grasps
    limit = s.max_linear_acceleration if kind == "linear" else s.max_angular_acceleration
    solver, reference, closing, rows = _squeeze_every_replica(ex, D, kind)
    world = np.einsum("gij,dj->gdi", ex.grasps.poses[:, :3, :3], dirs).reshape(G * D, 3)
    center = ex.finger_frames[:, :, :3, 3].mean(axis=1)[rows]
    held = reference.converged.copy()
    failure = np.where(held, GraspFailure.HELD, GraspFailure.NOT_GRASPED).astype(np.int64)
    threshold = np.where(held, limit, np.nan)
    level, margin, newton = np.zeros(G * D), np.ones(G * D), np.zeros(G * D, dtype=np.int64)
    for k in range(1, s.acceleration_steps + 1):
        target = limit * k / s.acceleration_steps
        previous = level.copy()
        level = np.where(held, target, level)
        vec = level[:, None] * world
        load = (
            fem.BodyLoad(linear_acceleration=vec)
            if kind == "linear"
            else fem.BodyLoad(angular_acceleration=vec, rotation_center=center)
        )
        eq = solver.solve(body_load=load)
        newton += eq.newton_iterations
        hs = ex._hold(eq, reference, closing, ex.pickup_force)
        newly = held & ~hs.held
        no_eq = newly & (hs.failure == GraspFailure.NO_EQUILIBRIUM)
        threshold[no_eq] = previous[no_eq] + eq.load_fraction[no_eq] * (target - previous[no_eq])
        other = newly & ~no_eq
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.clip(margin / (margin - hs.margin), 0.0, 1.0)
        threshold[other] = (previous + np.nan_to_num(t, nan=0.0) * (target - previous))[other]
        failure[newly] = hs.failure[newly]
        held &= hs.held
        margin = np.where(held, hs.margin, margin)
    shape = (G, D)
    return (
        threshold.reshape(shape),
        failure.reshape(shape),
        solver.status.reshape(shape),
        newton.reshape(shape),
    )


# the streaming is the same for both kinds; they differ in the load, which has its own test for the angular
# kind (test_angular_acceleration_thresholds_are_symmetric): the angular one runs with the slow tests
@pytest.mark.parametrize("kind", ["linear", pytest.param("angular", marks=pytest.mark.slow)])
def test_streamed_pairs_give_the_stepwise_batch_of_self_squeezed_replicas(box, two_grasps, monkeypatch, kind):
    """The G grasps are squeezed once and each (grasp, direction) pair streams its load steps from a copy
    of that state: thresholds, failures, solver statuses and Newton iterations equal bit for bit those of
    one batch of self-squeezed replicas stepped together (a lost pair spends no iteration after its loss),
    for 1 and 2 directions per solver; the squeeze runs once per GraspExperiments."""
    from defgraspnets.grasp import experiments as exp_module

    settings = ExperimentSettings(acceleration_steps=4, squeeze_steps=3)
    dirs = (
        [[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]
        if kind == "linear"
        else [[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]]
    )
    ramps = []
    real_ramp = exp_module.squeeze_ramp
    monkeypatch.setattr(
        exp_module, "squeeze_ramp", lambda s, *a, **k: ramps.append(s.batch_size) or real_ramp(s, *a, **k)
    )
    shared = GraspExperiments(box, two_grasps, MATERIAL, settings, device="cpu", directions_per_solver=2)
    new = shared.acceleration(kind, dirs)
    again = shared.acceleration(kind, dirs[:1])
    assert ramps == [2]  # one squeeze of the 2 grasps for both tests
    single = GraspExperiments(box, two_grasps, MATERIAL, settings, device="cpu", directions_per_solver=1)
    alone = single.acceleration(kind, dirs)
    old = _acceleration_stepwise(single, kind, dirs)
    for name, want in zip(("threshold", "failure", "solver_status", "newton_iterations"), old):
        assert np.array_equal(getattr(new, name), want, equal_nan=True), name
        assert np.array_equal(getattr(alone, name), want, equal_nan=True), name
        assert np.array_equal(getattr(again, name), want[:, :1], equal_nan=True), name
    assert np.all(new.newton_iterations > 0)
    assert (new.failure != GraspFailure.HELD).any()  # some pair is lost within the limit


def _reorientation_stepwise(ex: GraspExperiments, grasp_force) -> dict:
    """The reorientation as it was before the pairs were streamed and the squeeze shared: a batch of every
    grasp x axis replica, each squeezed itself, raised to F_slip, picked up and turned step by step with
    solve() (a lost pair goes on being loaded; its later states are not recorded)."""
    s = ex.settings
    G, N = ex.num_grasps, ex.mesh.num_vertices
    axes = sphere_directions(s.num_directions)
    A, J, sub = len(axes), s.reorientation_angles, s.reorientation_substeps
    solver, _, closing, rows = _squeeze_every_replica(ex, A, "reorientation")
    force = np.broadcast_to(np.asarray(grasp_force, dtype=np.float64), (G,))[rows]
    reference = solver.solve(targets={"grip": force})
    held = reference.converged.copy()
    failure = np.where(held, GraspFailure.HELD, GraspFailure.NOT_GRASPED).astype(np.int64)
    ex._gravity_ramp(solver, reference, closing, force, held, failure, "pickup")
    fine = np.pi * np.arange(1, J * sub + 1) / (J * sub)
    gravity = reorientation_gravity(axes, fine, s.gravity)
    out = {"held": np.zeros((G * A, J), dtype=bool), "positions": np.full((G * A, J, N, 3), np.nan)}
    out["von_mises"] = np.full((G * A, J, N), np.nan)
    out["max_von_mises"] = np.full((G * A, J), np.nan)
    for step in range(J * sub):
        eq = solver.solve(body_load=fem.BodyLoad(gravity=np.tile(gravity[:, step], (G, 1))))
        hs = ex._hold(eq, reference, closing, force)
        newly = held & ~hs.held
        failure[newly] = hs.failure[newly]
        held &= hs.held
        if (step + 1) % sub == 0:
            j = (step + 1) // sub - 1
            out["held"][:, j] = held
            out["positions"][held, j] = eq.positions[held]
            out["von_mises"][held, j] = eq.von_mises[held]
            out["max_von_mises"][held, j] = met.max_von_mises_stress(eq.tet_stress)[held]
    out["failure"] = failure
    return {k: v.reshape(G, A, *v.shape[1:]) for k, v in out.items()}


def test_shared_squeeze_gives_the_same_reorientation_and_pickup(box, two_grasps, monkeypatch):
    """Pickup from the shared squeeze equals pickup of a self-squeezed solver; the reorientation's (grasp,
    axis) pairs, streamed from the shared squeeze, hold, fail and record bit for bit the states of one
    stepped batch of self-squeezed replicas."""
    settings = ExperimentSettings(num_directions=2, reorientation_angles=2, squeeze_steps=3, pickup_steps=2)
    shared = GraspExperiments(box, two_grasps, MATERIAL, settings, device="cpu")
    p_new = shared.pickup()
    # half of F_slip: the turned object slips in some states (lost pairs), holds in others
    weak = 0.5 * p_new.slip_force
    r_new = shared.reorientation(weak)
    monkeypatch.setattr(GraspExperiments, "_squeezed", _squeeze_every_replica)
    old_ex = GraspExperiments(box, two_grasps, MATERIAL, settings, device="cpu")
    p_old = old_ex.pickup()
    for name in ("success", "failure", "slide", "slip_force", "max_deformation", "strain_energy"):
        assert np.array_equal(getattr(p_new, name), getattr(p_old, name), equal_nan=True), name
    assert np.array_equal(p_new.squeezed.displacement, p_old.squeezed.displacement)
    r_old = _reorientation_stepwise(old_ex, weak)
    for name, want in r_old.items():
        assert np.array_equal(getattr(r_new, name), want, equal_nan=True), name
    assert r_new.held.any() and (r_new.failure != GraspFailure.HELD).any()
    g, a, k = np.argwhere(r_new.held)[0]
    deformation = met.rigid_removed_deformation(box.points, r_new.positions[g, a, k][None], old_ex.masses)
    assert np.array_equal(r_new.deformation[g, a, k], deformation[0])


def test_a_grasp_whose_squeeze_failed_is_not_grasped_in_every_pair(box, two_grasps):
    """A grasp with no equilibrium at F_p (flagged by its squeeze) is NOT_GRASPED on every axis and
    direction, records no state and no threshold, and the other grasp's pairs are unaffected."""
    settings = ExperimentSettings(num_directions=2, reorientation_angles=2, squeeze_steps=3, pickup_steps=2)
    ex = GraspExperiments(box, two_grasps, MATERIAL, settings, device="cpu")
    good_r = ex.reorientation(ex.pickup_force)
    good_a = ex.acceleration("linear", [[1.0, 0, 0]])
    squeezed, at_fp = ex._squeeze()  # the cached squeeze: as if grasp 1's had failed
    squeezed.status[1] = at_fp.status[1] = fem.SolveStatus.NOT_CONVERGED
    r = ex.reorientation(ex.pickup_force)
    a = ex.acceleration("linear", [[1.0, 0, 0]])
    assert np.all(r.failure[1] == GraspFailure.NOT_GRASPED) and not r.held[1].any()
    assert np.all(np.isnan(r.positions[1]))
    assert a.failure[1, 0] == GraspFailure.NOT_GRASPED and np.isnan(a.threshold[1, 0])
    assert a.solver_status[1, 0] == fem.SolveStatus.NOT_CONVERGED
    for name in ("held", "failure", "positions", "von_mises"):
        assert np.array_equal(getattr(r, name)[0], getattr(good_r, name)[0], equal_nan=True), name
    assert np.array_equal(a.threshold[0], good_a.threshold[0])


# ---------------------------------------------------------------------------------------------- script
def test_grasp_experiments_script(tmp_path):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "grasp_experiments.py"),
        "num_grasps=1",
        "experiments=[pickup,linear]",
        "settings.num_directions=2",
        "settings.acceleration_steps=4",
        "progress=false",
        f"out_dir={out}",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((out / "metrics.json").read_text())
    assert report["object"] == "box_30x30x30" and report["mass_kg"] == pytest.approx(0.027)
    grasp = report["grasps"][0]
    assert len(grasp["metrics"]) == 7 and set(grasp["features"]) == set(feat.FEATURE_NAMES)
    assert len(grasp["linear_thresholds"]) == 2 and grasp["metrics"]["angular_instability_rad_s2"] is None
    assert (out / "experiments.png").stat().st_size > 10_000
    typo = subprocess.run(
        [*cmd[:2], "num_grasp=1", f"hydra.run.dir={tmp_path / 'run2'}"], capture_output=True, text=True
    )
    assert typo.returncode != 0 and "num_grasp" in typo.stderr
