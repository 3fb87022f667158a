"""Figures of the closed-loop experiments (tactile.loop_plots) from small synthetic records: each figure
plots the data it is given and is written as a non-empty PNG; the F~-force correlation the force-proxy
figure draws (contour_sim.force_proxy_correlation)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.closed_loops import ClosedLoopRun
from defgraspnets.tactile.contour import ContourRunMetrics
from defgraspnets.tactile.contour_sim import (
    ContourRun,
    ContourScene,
    contour_following_study,
    force_proxy_correlation,
    pole_positions,
)
from defgraspnets.tactile.fast_membrane import DEFAULT_CALIBRATION
from defgraspnets.tactile.lfd.manipulation import (
    CAPSULES,
    PRISM,
    ManipulationRun,
    ManipulationWorld,
    PalmGeometry,
)
from defgraspnets.tactile.loop_plots import (
    contour_trajectories_figure,
    force_proxy_figure,
    mixed_manipulation_figure,
    pose_correction_figure,
    save_figure,
)
from defgraspnets.tactile.sdf import TubeSDF

HEIGHT = 0.18  # [m] pole height of the synthetic sensor


def _assert_png(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 1000


# ------------------------------------------------------------------ contour following
def _contour_run(offset: float, slope: float = 500.0, intercept: float = 0.1) -> ContourRun:
    T = 6
    poses = np.broadcast_to(np.eye(4), (T, 4, 4)).copy()
    poses[:, :3, 3] = np.c_[np.full(T, offset), np.linspace(0.0, 0.05, T), np.zeros(T)]
    contact = np.array([False, True, True, True, False, True])
    proxy = np.where(contact, np.linspace(0.001, 0.006, T), 0.0)
    force = np.where(contact, slope * proxy + intercept, 0.0)
    metrics = ContourRunMetrics(
        contact_fraction=0.8, force_rms_error=0.001, path_length=0.05, distance_along=0.05,
        housing_contact_steps=1,
    )  # fmt: skip
    return ContourRun(poses, contact, np.zeros(T, bool), proxy, force, np.full(T, 10), metrics)


def _contour_scene(name: str, offset: float) -> ContourScene:
    path = np.array([[offset, -0.01, HEIGHT], [offset, 0.06, HEIGHT]])
    return ContourScene(
        name=name, sdf=TubeSDF(path, 0.00635), start_pose=np.eye(4), mode="edge",
        search_direction=(0, 0, -1), travel_direction=(0, 1, 0), progress_direction=(0, 1, 0), steps=6,
        path=path,
    )  # fmt: skip


@pytest.fixture
def contour():
    runs = {"a": _contour_run(0.0), "b": _contour_run(0.02)}
    scenes = {"a": _contour_scene("a", 0.0), "b": _contour_scene("b", 0.02)}
    return runs, scenes


def test_force_proxy_correlation_fits_the_in_contact_steps(contour):
    runs, _ = contour
    c = force_proxy_correlation(runs.values())
    assert c["samples"] == 8  # 4 in-contact steps per run
    assert c["pearson_r"] == pytest.approx(1.0)
    assert c["fit_N_per_m"] == pytest.approx(500.0)
    assert c["fit_intercept_N"] == pytest.approx(0.1)
    assert c["fem_pearson_r"] is None
    with_cal = force_proxy_correlation(runs.values(), DEFAULT_CALIBRATION)
    key = "fem_pearson_r_force_vs_contact_depth_proxy"
    assert with_cal["fem_pearson_r"] == DEFAULT_CALIBRATION.provenance.get(key)


def test_contour_study_rejects_unknown_scenes():
    sim = SimpleNamespace(model=SimpleNamespace(outer_reference=np.array([[0.0, 0.0, HEIGHT]])))
    with pytest.raises(ValueError, match="unknown scenes"):
        contour_following_study(sim, ["moon"], params=None, log=None)


def test_contour_trajectories_figure_plots_path_and_pole(contour, tmp_path):
    runs, scenes = contour
    fig = contour_trajectories_figure(runs, scenes, HEIGHT)
    assert len(fig.axes) == 2
    for ax, (name, run) in zip(fig.axes, runs.items()):
        np.testing.assert_allclose(np.array(ax.lines[0].get_data_3d()).T, scenes[name].path)
        np.testing.assert_allclose(np.array(ax.collections[0]._offsets3d).T, pole_positions(run, HEIGHT))
        assert ax.get_title() == f"{name}: contact 0.80, housing 1"
    path = save_figure(fig, tmp_path / "sub" / "trajectories.png")
    _assert_png(path)


def test_force_proxy_figure_plots_contact_samples_and_fit(contour, tmp_path):
    runs, _ = contour
    corr = force_proxy_correlation(runs.values())
    fig = force_proxy_figure(runs, corr)
    (ax,) = fig.axes
    for scatter, run in zip(ax.collections, runs.values()):
        c = run.in_contact
        np.testing.assert_allclose(scatter.get_offsets(), np.c_[run.depth_proxy[c], run.normal_force[c]])
    x, y = ax.lines[0].get_data()
    assert x[0] == 0.0 and x[-1] == pytest.approx(0.006)
    np.testing.assert_allclose(y, 500.0 * x + 0.1, rtol=1e-9, atol=1e-9)
    assert ax.get_title() == "F~ vs force, Pearson r = 1.000"
    _assert_png(save_figure(fig, tmp_path / "force_proxy.png"))


# ------------------------------------------------------------------ pose correction
def _closed_loop_run(n: int, push) -> ClosedLoopRun:
    poses = np.broadcast_to(np.eye(4), (n + 1, 4, 4)).copy()
    for k in range(n + 1):
        poses[k, :3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.01 * k]).as_matrix()
        poses[k, :3, 3] = [0.001 * k, -0.0005 * k, 0.0002 * k]
    rng = np.random.default_rng(n)
    true_w = rng.normal(size=(n, 6))
    return ClosedLoopRun(
        poses=poses, true_wrench=true_w, estimated_wrench=true_w + 0.1, contact=np.ones(n, bool),
        indentation=np.full(n, 0.003), push_direction=None if push is None else np.asarray(push, float),
    )  # fmt: skip


def test_pose_correction_figure_plots_wrench_and_motion(tmp_path):
    runs = {"axial": _closed_loop_run(3, (1.0, 0.0, 0.0)), "forearm_shear": _closed_loop_run(2, None)}
    fig = pose_correction_figure(runs)
    assert len(fig.axes) == 4  # 2 rows x 2 runs, row-major
    top, bottom = fig.axes[:2], fig.axes[2:]
    for k, run in enumerate(runs.values()):
        np.testing.assert_allclose(
            top[k].lines[0].get_ydata(), np.linalg.norm(run.true_wrench[:, :3], axis=1)
        )
        np.testing.assert_allclose(
            top[k].lines[1].get_ydata(), np.linalg.norm(run.estimated_wrench[:, :3], axis=1)
        )
        lines = bottom[k].lines
        assert len(lines) == (5 if run.push_direction is not None else 4)
        np.testing.assert_allclose(lines[-1].get_ydata(), np.degrees(np.linalg.norm(run.rotation, axis=1)))
        np.testing.assert_allclose(lines[-4].get_ydata(), 1e3 * run.displacement[:, 0])
    np.testing.assert_allclose(bottom[0].lines[0].get_ydata(), [0.0, 1.0, 2.0, 3.0])  # along +x, mm
    assert [ax.get_title() for ax in top] == ["axial", "forearm_shear"]
    _assert_png(save_figure(fig, tmp_path / "pose_correction.png"))


# ------------------------------------------------------------------ mixed manipulation
def _manipulation_run(obj, object_poses, dt=0.2) -> ManipulationRun:
    T = len(object_poses)
    palm = PalmGeometry(radius=0.05, pole_height=HEIGHT)
    poses = np.stack([palm.pose([x, y, 0.03]) for x, y, _ in object_poses])
    return ManipulationRun(
        obj=obj, poses=poses, inputs=np.zeros((T, 9)), in_contact=np.ones(T, bool),
        housing_contact=np.zeros(T, bool), object_poses=np.asarray(object_poses, float),
        on_table=np.ones(T, bool), modes=("press",) * (T - 1), weights=np.zeros((T, 0)), wall_overlap=False,
        dt=dt,
    )  # fmt: skip


def test_mixed_manipulation_figure_plots_paths_outcomes_and_yaw(tmp_path):
    capsule = _manipulation_run(CAPSULES[0], [[0.0, -0.2, 0.0], [0.0, -0.1, 0.0], [0.01, 0.02, 0.0]])
    prism = _manipulation_run(PRISM, [[0.1, -0.2, 0.5], [0.1, -0.2, 0.3], [0.1, -0.2, 0.05]])
    bad_prism = _manipulation_run(PRISM, [[0.1, -0.2, 3.0], [0.1, -0.2, 2.5], [0.1, -0.2, 2.0]])
    result = {
        "demonstrations": [capsule, prism],
        "rollouts": [bad_prism, capsule],
        "palm": PalmGeometry(radius=0.05, pole_height=HEIGHT),
        "world": ManipulationWorld(),
        "report": {
            "teacher_outcomes": [{"success": True}, {"success": True}],
            "rollouts": [{"success": False}, {"success": True}],
            "successes": 1,
            "trials": 2,
            "yaw_tolerance_deg": 5.0,
            "dt_s": 0.2,
        },
    }
    fig = mixed_manipulation_figure(result)
    demo_ax, roll_ax, yaw_ax = fig.axes
    for ax, runs in ((demo_ax, result["demonstrations"]), (roll_ax, result["rollouts"])):
        assert len(ax.patches) == 2  # the corridor walls
        lines = ax.lines[1:]  # after the table edge
        assert len(lines) == 3 * len(runs)
        for i, run in enumerate(runs):
            pole, obj, end = lines[3 * i : 3 * i + 3]
            np.testing.assert_allclose(pole.get_xdata(), run.object_poses[:, 0], atol=1e-12)
            np.testing.assert_allclose(obj.get_ydata(), run.object_poses[:, 1])
            np.testing.assert_allclose(end.get_xydata()[0], run.object_poses[-1, :2])
    assert roll_ax.lines[3].get_marker() == "x" and roll_ax.lines[3].get_color() == "r"  # failed prism
    assert demo_ax.lines[3].get_marker() == "o"
    demo_yaw, roll_yaw = yaw_ax.lines  # one prism per group
    np.testing.assert_allclose(demo_yaw.get_xdata(), [0.0, 0.2, 0.4])
    np.testing.assert_allclose(demo_yaw.get_ydata(), np.rad2deg([0.5, 0.3, 0.05]))
    np.testing.assert_allclose(roll_yaw.get_ydata(), np.rad2deg(np.array([3.0, 2.5, 2.0]) - np.pi))
    assert yaw_ax.get_title() == "prism; policy 1/2 successes overall"
    _assert_png(save_figure(fig, tmp_path / "lfd_mixed_manipulation.png"))
