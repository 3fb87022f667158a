"""Closed loops of thesis §3.5 on the coarse FEM sensor with the oracle wrench: pose correction yields to
a fixed fingertip (force falls, sensor moves along the push, turns with the torque); forearm support
follows a sheared / twisted forearm (slow)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from defgraspnets.tactile.closed_loops import (
    CNNWrenchEstimator,
    CorrectionGains,
    Fingertip,
    check_estimator,
    make_estimator,
    oracle_estimator,
    place_fingertip,
    pose_correction_runs,
    pose_correction_step,
    read_fingertip,
    run_forearm_support,
    run_pose_correction,
    shear_twist_schedule,
)
from defgraspnets.tactile.datasets import make_simulator
from defgraspnets.tactile.indenters import CapsuleIndenter, PokeCommand, SphereIndenter
from defgraspnets.tactile.membrane import build_membrane

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sensor():
    return build_membrane(cap_divisions=8, layers=2)


@pytest.fixture(scope="module")
def sim(sensor):
    return make_simulator(sensor, SphereIndenter(radius=0.01), 1500.0, True, intrinsics=None)


# ------------------------------------------------------------------ the law (no FEM)
def test_step_moves_along_world_force_and_turns_in_body_frame():
    S = np.eye(4)
    S[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # sensor turned 90 deg about z
    S[:3, 3] = [0.1, 0.2, 0.3]
    gains = CorrectionGains(max_translation=1.0, max_rotation=1.0)
    out = pose_correction_step(S, [0.01, 0.0, 0.0, 0.0, 0.0, 0.0], gains)
    # 0.1 m/N x 0.01 N along sensor x = world +y
    np.testing.assert_allclose(out[:3, 3], [0.1, 0.201, 0.3], atol=1e-12)
    np.testing.assert_allclose(out[:3, :3], S[:3, :3], atol=1e-12)
    out = pose_correction_step(S, [0.0, 0.0, 0.0, 0.0, 0.0, 0.01], gains)
    turn = S[:3, :3].T @ out[:3, :3]  # body-frame rotation: 2 rad/(N m) x 0.01 N m about z
    np.testing.assert_allclose(turn[:2, :2], [[np.cos(0.02), -np.sin(0.02)], [np.sin(0.02), np.cos(0.02)]])
    np.testing.assert_allclose(out[:3, 3], S[:3, 3])


def test_step_clamps_keep_direction():
    gains = CorrectionGains(max_translation=0.001, max_rotation=0.01)
    out = pose_correction_step(np.eye(4), [3.0, 0.0, -4.0, 0.0, 1.0, 0.0], gains)
    np.testing.assert_allclose(out[:3, 3], [0.0006, 0.0, -0.0008], atol=1e-12)
    assert np.isclose(np.arccos(out[0, 0]), 0.01) and out[0, 2] > 0  # +y turn, clamped to 0.01 rad


@pytest.mark.parametrize(
    "pose, wrench",
    [(np.eye(3), np.zeros(6)), (np.eye(4), np.zeros(5)), (np.eye(4), [np.nan, 0, 0, 0, 0, 0])],
)
def test_step_rejects_bad_input(pose, wrench):
    with pytest.raises(ValueError):
        pose_correction_step(pose, wrench)


def test_bad_input_rejected(sim):
    with pytest.raises(ValueError):
        CorrectionGains(force_gain=-0.1)
    with pytest.raises(ValueError):
        Fingertip([0.0, 0.0, 0.2], [0.0, 0.0, 0.0])
    tip = Fingertip([0.0, 0.0, 0.2], [0.0, 0.0, -1.0])
    with pytest.raises(ValueError):
        run_pose_correction(sim, tip, steps=0)
    with pytest.raises(ValueError):
        run_pose_correction(sim, tip, sensor_pose=2 * np.eye(4))
    with pytest.raises(TypeError):
        run_pose_correction(object(), tip)
    with pytest.raises(TypeError):
        CNNWrenchEstimator(object())
    with pytest.raises(FileNotFoundError, match="not found"):
        CNNWrenchEstimator.from_checkpoint(ROOT / "checkpoints" / "does_not_exist.ckpt")


def test_estimator_choice_checked_before_simulation(tmp_path):
    assert make_estimator("oracle", sim=None) is oracle_estimator  # no checkpoint needed
    check_estimator("oracle", ckpt_path=tmp_path / "missing.ckpt", cnn_reference="bogus")
    with pytest.raises(ValueError, match="estimator must be"):
        check_estimator("kalman")
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        check_estimator("cnn", tmp_path / "missing.ckpt")
    ckpt = tmp_path / "present.ckpt"
    ckpt.write_bytes(b"")
    with pytest.raises(ValueError, match="cnn_reference"):
        make_estimator("cnn", None, ckpt, cnn_reference="bogus")


# ------------------------------------------------------------------ pose correction on the FEM sensor
def test_out_of_reach_fingertip_reads_zero(sim):
    tip = Fingertip([0.0, 0.0, 0.5], [0.0, 0.0, -1.0])  # 0.3 m above the pole
    reading, depth = read_fingertip(sim, np.eye(4), tip, render=False)
    assert depth == 0.0 and reading.converged
    np.testing.assert_array_equal(reading.base_wrench, np.zeros(6))


def test_axial_poke_sensor_yields(sim):
    tip = place_fingertip(sim, PokeCommand(0.0, 0.0, 0.0, 0.004))
    run = run_pose_correction(sim, tip, oracle_estimator, steps=3)
    assert run.stopped == "" and run.contact.all()
    force = run.force_magnitude
    assert force[0] > 0.3  # a real poke (~0.74 N at 4 mm)
    assert np.all(np.diff(force) < 0), force  # compliance: the contact force falls every step
    along = run.displacement @ run.push_direction
    assert np.all(np.diff(along) > 0) and along[-1] > 0.002, along  # moves away along the push (-z)
    assert np.all(np.diff(run.indentation) < 0)
    np.testing.assert_array_equal(run.estimated_wrench, run.true_wrench)  # oracle


def test_tilted_poke_turns_with_torque(sim):
    # fingertip pushing at the pole along -(sin 0.4 e_x + cos 0.4 e_z): F_x < 0 at 0.19 m above the base
    # gives tau_y < 0, and the sensor must turn about -y (top away from the finger)
    tip = place_fingertip(sim, PokeCommand(0.0, 0.0, 0.4, 0.004))
    run = run_pose_correction(sim, tip, oracle_estimator, steps=2)
    assert run.stopped == ""
    tau_y = run.true_wrench[0, 4]
    assert tau_y < -0.01, run.true_wrench[0]
    rot = run.rotation
    assert np.sign(rot[1, 1]) == np.sign(tau_y) and abs(rot[1, 1]) > 0.5 * CorrectionGains().max_rotation
    assert abs(rot[-1, 1]) > abs(rot[1, 1])
    assert run.force_magnitude[1] < run.force_magnitude[0]
    assert (run.displacement @ run.push_direction)[-1] > 0
    # the contact point yields: work of the applied wrench on the first step is positive
    w = run.true_wrench[0]
    dp = run.poses[0, :3, :3].T @ (run.positions[1] - run.positions[0])
    assert w[:3] @ dp + w[3:] @ rot[1] > 0


def test_pose_correction_runs_report_each_poke(sim):
    pokes = {"axial": {"phi": 0.0, "contact_radius": 0.0, "theta": 0.0, "depth": 0.003}}
    lines = []
    runs, entries = pose_correction_runs(sim, pokes, steps=1, log=lines.append)
    assert list(runs) == list(entries) == ["axial"]
    entry = entries["axial"]
    assert entry["poke"] == pokes["axial"] and entry["wall_time_s"] > 0
    assert {k: v for k, v in entry.items() if k not in ("poke", "wall_time_s")} == runs["axial"].to_dict()
    assert len(lines) == 1 and lines[0].startswith("axial: |F| [")


# ------------------------------------------------------------------ forearm support (slow)
@pytest.mark.slow
def test_forearm_shear_and_twist_followed(sensor):
    arm = make_simulator(sensor, CapsuleIndenter(radius=0.04, length=0.2), 1500.0, True, intrinsics=None)
    shear = run_forearm_support(arm, shear_twist_schedule(2, (0.0, 0.002, 0.0)), depth=0.004)
    assert shear.stopped == ""
    assert shear.true_wrench[0, 1] > 0  # the dragged membrane pushes the sensor along +y
    assert shear.displacement[-1, 1] > 0.0005, shear.displacement
    twist = run_forearm_support(arm, shear_twist_schedule(2, twist_per_step=0.05), depth=0.004)
    assert twist.stopped == ""
    assert twist.true_wrench[0, 5] > 0 and twist.rotation[-1, 2] > 0.002, twist.rotation


@pytest.mark.slow
def test_script_oracle_writes_outputs(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "scripts" / "pose_correction.py"), "steps=2", "pokes.tilted.depth=0.003",
        f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=tmp_path, capture_output=True, timeout=900)
    assert (tmp_path / "pose_correction.json").is_file() and (tmp_path / "pose_correction.png").is_file()


def test_script_missing_checkpoint_is_clear(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "scripts" / "pose_correction.py"), "estimator=cnn",
        f"ckpt_path={tmp_path / 'missing.ckpt'}", f"hydra.run.dir={tmp_path}",
    ]  # fmt: skip
    res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode != 0
    assert "checkpoint not found" in res.stderr + res.stdout
