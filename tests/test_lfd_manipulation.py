"""Mixed-manipulation LfD (thesis §5.5): scenes, object motion, scripted teacher, 4-state HMM + GMRa."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.contour_sim import build_fast_simulation
from defgraspnets.tactile.lfd.experiments import demonstration_action_error
from defgraspnets.tactile.lfd.manipulation import (
    CAPSULES,
    PRISM,
    ExtrudedFootprintSDF,
    ManipulationObject,
    ManipulationWorld,
    PalmGeometry,
    TeacherParameters,
    demonstrate,
    evaluate_success,
    fit_manipulation_policy,
    mirror_start,
    mixed_manipulation_experiment,
    move_object,
    rollout_manipulation,
    sample_start,
)
from defgraspnets.tactile.pushing import Capsule, Rectangle

ROOT = Path(__file__).resolve().parents[1]
PALM = PalmGeometry(radius=0.0528, pole_height=0.183)  # the inflated dome of build_fast_simulation
WORLD = ManipulationWorld()


@pytest.fixture(scope="module")
def teacher_runs():
    """Scripted demonstrations on a coarser sensor (cap 12): 4 capsules of 10-50 mm and 2 prism starts."""
    sim = build_fast_simulation(cap_divisions=12, camera_scale=0.5, core_fraction=0.7)
    palm = PalmGeometry.from_simulation(sim)
    rng = np.random.default_rng(3)
    objs = (CAPSULES[0], CAPSULES[3], CAPSULES[6], CAPSULES[7], PRISM, PRISM)
    teacher = TeacherParameters()
    return [demonstrate(sim, WORLD, palm, o, *sample_start(o, palm, WORLD, rng), teacher) for o in objs]


@pytest.fixture(scope="module")
def small_experiment():
    """6 demonstrations per subtask, 6 unseen starts (3 capsules, 3 prism), 45 steps each (~45 s)."""
    sim = build_fast_simulation(cap_divisions=20, camera_scale=0.5, core_fraction=0.7)
    return mixed_manipulation_experiment(sim, n_demonstrations=6, n_rollouts=6, rollout_steps=45, seed=0)


def _assert_moves_only_in_contact(runs) -> int:
    """The object moves from t to t + 1 only if the membrane touches at t or t + 1; returns the moves."""
    moved_steps = 0
    for run in runs:
        moved = np.linalg.norm(np.diff(run.object_poses, axis=0), axis=1) > 0
        touching = run.in_contact[:-1] | run.in_contact[1:]
        assert not (moved & ~touching).any(), run.obj.name
        moved_steps += int(moved.sum())
        first = int(np.argmax(run.in_contact))  # nothing moves before the move that makes the first contact
        assert first > 0 and (run.object_poses[:first] == run.object_poses[0]).all()
    return moved_steps


def test_extruded_footprint_sdf_is_exact_above_and_beside_the_object():
    sdf = ExtrudedFootprintSDF(Capsule(0.01), (0.1, -0.2, 0.3), 0.015)
    pts = np.array([[0.1, -0.2, 0.025], [0.13, -0.2, 0.005], [0.1, -0.2, 0.0075]])
    np.testing.assert_allclose(sdf.distance(pts), [0.01, 0.02, -0.0075], atol=1e-12)
    with pytest.raises(ValueError):
        ExtrudedFootprintSDF(Capsule(0.01), (0.0, 0.0, 0.0), 0.0)


def test_palm_geometry_matches_the_fast_membrane_dome():
    sim = build_fast_simulation(cap_divisions=8, camera_scale=0.25)
    palm = PalmGeometry.from_simulation(sim)
    # inflated 50 mm inner radius + 3 mm shell; pole height of the sensor frame
    assert 0.051 < palm.radius < 0.055
    assert palm.pole_height == pytest.approx(sim.model.outer_reference[:, 2].max())
    assert palm.section_radius(0.01, 0.005) == 0.0  # the dome lies above z
    assert palm.section_radius(0.0, 0.004) == pytest.approx(
        np.sqrt(palm.radius**2 - (palm.radius - 0.004) ** 2)
    )


def test_object_does_not_move_without_contact_and_a_central_push_translates_it():
    obj = CAPSULES[3]  # 25 mm disc, 15 mm high
    pose = np.array([0.0, -0.15, 0.2])
    far = PALM.pose([0.0, -0.25, 0.006])
    out = move_object(
        WORLD, PALM, obj, pose, True, far, PALM.pose([0.0, -0.24, 0.006]), 0.0, np.empty((0, 2))
    )
    assert out.mode == "free" and np.array_equal(out.pose, pose)
    # dome section at the object's top minus the push indentation, just touching the disc from behind
    r = PALM.section_radius(0.006, obj.height - WORLD.push_indentation)
    start = PALM.pose([0.0, pose[1] - obj.shape.radius - r - 1e-4, 0.006])
    end = start.copy()
    end[1, 3] += 0.01
    out = move_object(WORLD, PALM, obj, pose, True, start, end, 0.0, np.empty((0, 2)))
    assert out.mode == "push"
    # a central push of a disc: pure translation along the push, by the push minus the initial gap
    np.testing.assert_allclose(out.pose[:2], [0.0, pose[1] + 0.01 - 1e-4], atol=2e-4)
    # the pusher moving away leaves it
    back = move_object(WORLD, PALM, obj, out.pose, True, end, start, 0.0, np.empty((0, 2)))
    assert back.mode == "free" and np.array_equal(back.pose, out.pose)


def test_pressed_prism_turns_with_the_palm_only_when_friction_can_hold_it():
    pose = np.array([0.0, -0.2, np.deg2rad(20.0)])
    a = PALM.pose([0.0, -0.2, 0.015])
    b = a.copy()
    b[:3, :3] = Rotation.from_euler("z", -0.1).as_matrix() @ a[:3, :3]
    patch = np.array([[0.0, -0.2], [0.02, -0.2], [-0.02, -0.2], [0.0, -0.195]])
    held = move_object(WORLD, PALM, PRISM, pose, True, a, b, 1.0, patch)
    assert held.mode == "stick" and held.pose[2] == pytest.approx(pose[2] - 0.1)
    np.testing.assert_allclose(held.pose[:2], pose[:2], atol=1e-12)  # turned about the pole above its centre
    # a light touch cannot overcome the table's friction torque: the prism stays
    slip = move_object(WORLD, PALM, PRISM, pose, True, a, b, 0.01, patch)
    assert slip.mode == "slip" and np.array_equal(slip.pose, pose)
    none = move_object(WORLD, PALM, PRISM, pose, True, a, b, 0.0, np.empty((0, 2)))
    assert none.mode == "free" and np.array_equal(none.pose, pose)


def test_teacher_succeeds_on_all_its_demonstrations(teacher_runs):
    for run in teacher_runs:
        outcome = evaluate_success(run, WORLD)
        assert outcome["success"], outcome
        assert not run.housing_contact.any() and not run.wall_overlap
        if run.obj.kind == "capsule":
            assert outcome["off_table"] and outcome["through_corridor"]
            assert run.in_contact[-1] == 0  # post-pushing: contact lost after the fall
        else:
            assert outcome["final_yaw_error_deg"] <= 1.0 and outcome["shift_m"] < 0.005
        obs = run.demonstration().observations
        assert obs.shape == (len(run.poses) - 1, 15) and np.isfinite(obs).all()


def test_teacher_holds_the_aligned_prism_before_it_ends(teacher_runs):
    """The demonstrations show where to stop: the last ``align_hold_steps`` actions press the aligned prism
    with zero yaw rate (it does not turn), and the capsule's retraction keeps its own ``hold_steps``."""
    tp = TeacherParameters()
    assert tp.align_hold_steps != tp.hold_steps  # the two phases are counted separately
    for run in teacher_runs:
        twist = run.demonstration().observations[:, 9:]
        if run.obj.kind == "capsule":
            np.testing.assert_allclose(twist[-tp.hold_steps :, 2], tp.retract_speed)
            assert not np.isclose(twist[-tp.hold_steps - 1, 2], tp.retract_speed)
            continue
        psi = (run.object_poses[:, 2] + np.pi / 2) % np.pi - np.pi / 2
        held = slice(len(twist) - tp.align_hold_steps, None)
        assert (twist[held, 5] == 0).all() and run.in_contact[held].all()
        assert (np.abs(psi[held]) <= tp.align_tolerance).all()
        np.testing.assert_array_equal(run.object_poses[held, 2], run.object_poses[-1, 2])
        assert twist[len(twist) - tp.align_hold_steps - 1, 5] != 0  # turning until then


def test_objects_move_only_in_contact_with_the_membrane(teacher_runs):
    assert _assert_moves_only_in_contact(teacher_runs) > 30


def test_teacher_actions_are_functions_of_what_the_palm_senses(teacher_runs):
    """The learner sees only S = [c, lambda, e1]: the capsule is dragged pressed under the palm (it follows
    the palm, so c locates it and the steering toward the corridor axis is a function of c_x), and the prism
    is turned from its first contact on (no zero yaw rate while misaligned and touching)."""
    for run in teacher_runs:
        twist = run.demonstration().observations[:, 9:]
        contact = np.flatnonzero(run.in_contact[:-1] & run.on_table[:-1])
        if run.obj.kind == "capsule":
            moving = contact[np.linalg.norm(twist[contact, :2], axis=1) > 0]
            assert len(moving) > 10
            # every horizontal move of the palm carries the pressed capsule along (no flank pushing)
            assert all(run.modes[t] == "stick" for t in moving), run.modes
            np.testing.assert_allclose(
                run.object_poses[moving + 1, :2] - run.object_poses[moving, :2],
                run.poses[moving + 1, :2, 3] - run.poses[moving, :2, 3],
                atol=1e-9,
            )
            off_axis = moving[np.abs(run.inputs[moving, 0]) > 0.005]
            assert (np.sign(twist[off_axis, 0]) == -np.sign(run.inputs[off_axis, 0])).all()
        else:
            psi = (run.object_poses[:, 2] + np.pi / 2) % np.pi - np.pi / 2
            turning = contact[np.abs(psi[contact]) > TeacherParameters().align_tolerance]
            assert turning[0] == contact[0]  # turns at the first contact
            assert (np.sign(twist[turning, 5]) == -np.sign(psi[turning])).all()


def test_sample_start_places_the_palm_above_or_behind_the_capsule():
    obj = CAPSULES[4]
    above = sample_start(obj, PALM, WORLD, np.random.default_rng(7), capsule_approach="above")
    behind = sample_start(obj, PALM, WORLD, np.random.default_rng(7), capsule_approach="behind")
    np.testing.assert_array_equal(above[0], behind[0])  # same draws, same object pose
    assert np.linalg.norm(PALM.pole(above[1])[:2] - above[0][:2]) <= 0.003 * np.sqrt(2)
    assert PALM.pole(behind[1])[1] < behind[0][1] - obj.shape.radius
    with pytest.raises(ValueError):
        sample_start(obj, PALM, WORLD, np.random.default_rng(7), capsule_approach="left")
    with pytest.raises(ValueError):
        TeacherParameters(capsule_approach="left")


def test_mirror_start_reflects_object_and_palm_about_the_corridor_axis():
    obj_pose, sensor = sample_start(PRISM, PALM, WORLD, np.random.default_rng(11))
    m_pose, m_sensor = mirror_start(PALM, obj_pose, sensor)
    np.testing.assert_allclose(m_pose, obj_pose * [-1, 1, -1])
    np.testing.assert_allclose(PALM.pole(m_sensor), PALM.pole(sensor) * [-1, 1, 1], atol=1e-12)
    np.testing.assert_allclose(m_sensor[:3, :3], sensor[:3, :3])


def test_restarts_keep_the_policy_that_best_replays_the_demonstrations(teacher_runs):
    single = fit_manipulation_policy(teacher_runs, seed=1)
    best = fit_manipulation_policy(teacher_runs, seed=1, n_restarts=4)
    seqs = [single.normalizer.transform(r.demonstration().observations) for r in teacher_runs]
    # run 0 of the restarts is the single-run fit, so the kept replay error is never larger
    assert demonstration_action_error(best.hmm, seqs, 9) <= demonstration_action_error(single.hmm, seqs, 9)
    with pytest.raises(ValueError):
        fit_manipulation_policy(teacher_runs, n_restarts=0)


def test_flank_pushing_teacher_is_still_available():
    sim = build_fast_simulation(cap_divisions=12, camera_scale=0.5, core_fraction=0.7)
    palm = PalmGeometry.from_simulation(sim)
    obj = CAPSULES[3]
    start = sample_start(obj, palm, WORLD, np.random.default_rng(3), capsule_approach="behind")
    teacher = TeacherParameters(capsule_approach="behind", rotate_on_contact=False)
    run = demonstrate(sim, WORLD, palm, obj, *start, teacher)
    assert evaluate_success(run, WORLD)["success"] and "push" in run.modes and "stick" not in run.modes


@pytest.mark.slow
def test_learned_policy_succeeds_on_unseen_starts(small_experiment):
    rep = small_experiment["report"]
    assert rep["hmm_states"] == 4 and rep["teacher_successes"] == rep["n_demonstrations"] == 12
    # measured (seed 0, dragging teacher, 5 restarts, mirrored prism demonstrations, before the 8-step aligned
    # hold of session 13): 5/6 — prism yaw errors
    # 0.7-2.1 deg (tolerance 5 deg); the dragged capsules cross the edge at |x| <= 1.3 mm, the 35 mm one
    # stays on the table (6 demonstrations show only 6 of the 8 capsules). The dragging takes ~25 steps after
    # the ~8 of lowering, so 35 steps are too few for a capsule that starts far from the edge.
    assert rep["successes"] >= 5
    assert rep["successes_by_task"]["prism"] == {"successes": 3, "trials": 3}
    _assert_moves_only_in_contact(small_experiment["rollouts"])
    # the HMM separates the lowering (no contact) from contact: the start and contact states differ
    for run in small_experiment["rollouts"]:
        first = int(np.argmax(run.in_contact))
        assert np.argmax(run.weights[0]) != np.argmax(run.weights[first + 2])


def test_bad_input_is_rejected(teacher_runs):
    with pytest.raises(ValueError):
        ManipulationObject("x", Capsule(0.01), 0.01, 0.01, "sphere")
    with pytest.raises(ValueError):
        ManipulationObject("x", Rectangle(0.01, 0.01), -0.01, 0.01, "prism")
    with pytest.raises(ValueError):
        ManipulationWorld(corridor_width=0.0)
    with pytest.raises(ValueError):
        fit_manipulation_policy([])
    sim = build_fast_simulation(cap_divisions=8, camera_scale=0.25)
    with pytest.raises(ValueError):
        mixed_manipulation_experiment(sim, n_demonstrations=0)
    with pytest.raises(ValueError):
        mixed_manipulation_experiment(sim, mirror_demonstrations=("sphere",))
    policy = fit_manipulation_policy(teacher_runs)
    with pytest.raises(ValueError):
        rollout_manipulation(sim, WORLD, PALM, policy, PRISM, np.zeros(3), np.eye(4), 0)
    with pytest.raises(ValueError):
        policy.action(np.zeros(6))  # the policy takes the 9-D input


@pytest.mark.slow
def test_script_writes_report_and_figure(tmp_path):
    # cap 12: on the cap-8 membrane too few contact columns touch the 10 mm capsule for the pressed capsule
    # to stick to the palm, and the dragging teacher leaves it behind
    cmd = [
        sys.executable, str(ROOT / "scripts" / "lfd_mixed_manipulation.py"), "n_demonstrations=1",
        "n_rollouts=2", "rollout_steps=5", "sensor.cap_divisions=12", "sensor.camera_scale=0.25",
        f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=tmp_path, capture_output=True, timeout=900)
    report = json.loads((tmp_path / "lfd_mixed_manipulation.json").read_text())
    assert report["n_demonstrations"] == 2 and report["trials"] == 2
    assert len(report["teacher_outcomes"]) == 2 and len(report["rollouts"]) == 2
    assert "wall_time_s" in report
    assert (tmp_path / "lfd_mixed_manipulation.png").stat().st_size > 1000
