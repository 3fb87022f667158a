"""Mixed-manipulation LfD (thesis §5.5): scenes, object motion, scripted teacher, 4-state HMM + GMRa."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.contour_sim import build_fast_simulation
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
    """6 demonstrations per subtask, 6 unseen starts (3 capsules, 3 prism), 35 steps each (~35 s)."""
    sim = build_fast_simulation(cap_divisions=20, camera_scale=0.5, core_fraction=0.7)
    return mixed_manipulation_experiment(sim, n_demonstrations=6, n_rollouts=6, rollout_steps=35, seed=0)


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


def test_objects_move_only_in_contact_with_the_membrane(teacher_runs):
    assert _assert_moves_only_in_contact(teacher_runs) > 30


@pytest.mark.slow
def test_learned_policy_succeeds_on_unseen_starts(small_experiment):
    rep = small_experiment["report"]
    assert rep["hmm_states"] == 4 and rep["teacher_successes"] == rep["n_demonstrations"] == 12
    # measured (seed 0, 2-core CPU): 6/6 — capsules cross the edge at |x| <= 0.024 m (walls at 0.05 m), prism
    # yaw errors 0.6-2.8 deg (tolerance 5 deg). With 4 demonstrations per subtask it is 3/6: the capsules
    # succeed, the prism stops 6-13 deg short (too few demonstrations for the 9-D regression of omega_z).
    assert rep["successes"] == 6
    assert rep["successes_by_task"] == {
        "capsule": {"successes": 3, "trials": 3},
        "prism": {"successes": 3, "trials": 3},
    }
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
    policy = fit_manipulation_policy(teacher_runs)
    with pytest.raises(ValueError):
        rollout_manipulation(sim, WORLD, PALM, policy, PRISM, np.zeros(3), np.eye(4), 0)
    with pytest.raises(ValueError):
        policy.action(np.zeros(6))  # the policy takes the 9-D input


@pytest.mark.slow
def test_script_writes_report_and_figure(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "scripts" / "lfd_mixed_manipulation.py"), "n_demonstrations=1",
        "n_rollouts=2", "rollout_steps=5", "sensor.cap_divisions=8", "sensor.camera_scale=0.25",
        f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=tmp_path, capture_output=True, timeout=900)
    report = json.loads((tmp_path / "lfd_mixed_manipulation.json").read_text())
    assert report["n_demonstrations"] == 2 and report["trials"] == 2
    assert len(report["teacher_outcomes"]) == 2 and len(report["rollouts"]) == 2
    assert "wall_time_s" in report
    assert (tmp_path / "lfd_mixed_manipulation.png").stat().st_size > 1000
