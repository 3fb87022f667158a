"""Figures of the closed-loop tactile experiments, written as PNG files (Agg backend).

- contour following (thesis ch. 4, :mod:`defgraspnets.tactile.contour_sim`): the membrane pole's path along
  each scene (:func:`contour_trajectories_figure`) and ``F~`` against the true contact force (Fig. 4.4
  analogue, :func:`force_proxy_figure`);
- pose correction and forearm support (thesis §3.5, Figs 3.9-3.10, :mod:`defgraspnets.tactile.closed_loops`):
  wrench and sensor motion per control step (:func:`pose_correction_figure`);
- edge-following LfD (thesis §5.4, :mod:`defgraspnets.tactile.lfd.experiments`): the demonstrations on the
  straight pipes, the policy's rollout on the curved pipe and its HMM state weights
  (:func:`edge_following_figure`);
- mixed-manipulation LfD (thesis §5.5, :mod:`defgraspnets.tactile.lfd.manipulation`): object and palm
  paths of demonstrations and rollouts, prism yaw over time (:func:`mixed_manipulation_figure`).

Each ``*_figure`` function builds and returns a :class:`matplotlib.figure.Figure` from the experiment's
records (so its plotted data can be inspected); :func:`save_figure` writes and closes it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from defgraspnets.tactile.contour_sim import ContourRun, ContourScene, pole_positions

if TYPE_CHECKING:
    from defgraspnets.tactile.closed_loops import ClosedLoopRun

__all__ = [
    "contour_trajectories_figure",
    "edge_following_figure",
    "force_proxy_figure",
    "mixed_manipulation_figure",
    "pose_correction_figure",
    "save_figure",
]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (PNG, parent folders created) and close it; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path


# ------------------------------------------------------------------------------ contour following
def contour_trajectories_figure(
    runs: Mapping[str, ContourRun], scenes: Mapping[str, ContourScene], height: float
):
    """One 3-D panel per run: the scene's edge / surface line (black) and the membrane pole (sensor-frame
    point ``(0, 0, height)``, [m]) at every step, blue in contact, red without."""
    plt = _pyplot()
    fig = plt.figure(figsize=(5 * len(runs), 5))
    for k, (name, run) in enumerate(runs.items()):
        ax = fig.add_subplot(1, len(runs), k + 1, projection="3d")
        path = scenes[name].path
        ax.plot(*path.T, "k-", lw=3, alpha=0.4, label="edge / surface line")
        pole = pole_positions(run, height)
        c = np.where(run.in_contact, "tab:blue", "tab:red")
        ax.scatter(*pole.T, c=c, s=8, label="membrane pole (red: no contact)")
        ax.set_title(
            f"{name}: contact {run.metrics.contact_fraction:.2f}, housing {run.metrics.housing_contact_steps}"
        )
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.set_aspect("equal")
    fig.axes[0].legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    return fig


def force_proxy_figure(runs: Mapping[str, ContourRun], correlation: Mapping):
    """Fig. 4.4 analogue: ``F~`` (eq. 4.6) [m] against the true contact force [N] over the in-contact steps
    of each run, and the line of ``correlation`` (``fit_N_per_m``, ``fit_intercept_N`` and ``pearson_r`` of
    :func:`~defgraspnets.tactile.contour_sim.force_proxy_correlation`)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 4))
    for name, run in runs.items():
        ax.scatter(run.depth_proxy[run.in_contact], run.normal_force[run.in_contact], s=10, label=name)
    proxy = np.concatenate([r.depth_proxy[r.in_contact] for r in runs.values()])
    xs = np.linspace(0, proxy.max(), 10)
    ax.plot(xs, correlation["fit_N_per_m"] * xs + correlation["fit_intercept_N"], "k--", lw=1)
    ax.set_xlabel("F~ (eq. 4.6, indented pixels) [m]")
    ax.set_ylabel("contact force [N]")
    ax.set_title(f"F~ vs force, Pearson r = {correlation['pearson_r']:.3f}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------ pose correction
def pose_correction_figure(runs: Mapping[str, ClosedLoopRun]):
    """Two rows, one column per run: top, |F| of the true and estimated wrench and 10 max|tau| [N] per
    control step; bottom, the sensor's displacement [mm] (along the push, when the run has one, and per
    world axis) and its total rotation [deg] after each step."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, len(runs), figsize=(4.2 * len(runs), 6.5), squeeze=False)
    for k, (name, run) in enumerate(runs.items()):
        steps = np.arange(len(run.contact))
        ax = axes[0, k]
        ax.plot(steps, np.linalg.norm(run.true_wrench[:, :3], axis=1), "o-", label="|F| true")
        ax.plot(steps, np.linalg.norm(run.estimated_wrench[:, :3], axis=1), "x--", label="|F| estimated")
        ax.plot(steps, 10 * np.abs(run.true_wrench[:, 3:]).max(axis=1), "s:", label="10 max|tau| true [N m]")
        ax.set_title(name)
        ax.set_xlabel("control step (1 Hz)")
        ax.set_ylabel("force [N]")
        ax.legend(fontsize=7)
        ax = axes[1, k]
        sk = np.arange(len(run.poses))
        if run.push_direction is not None:
            ax.plot(sk, 1e3 * run.displacement @ run.push_direction, "o-", label="along push [mm]")
        for i, axis in enumerate("xyz"):
            ax.plot(sk, 1e3 * run.displacement[:, i], ".-", lw=0.8, label=f"{axis} [mm]")
        ax.plot(sk, np.degrees(np.linalg.norm(run.rotation, axis=1)), "k--", label="|rotation| [deg]")
        ax.set_xlabel("pose index (after step k)")
        ax.set_ylabel("sensor displacement [mm] / rotation [deg]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------ edge-following LfD
def edge_following_figure(result: Mapping):
    """Three panels of an :func:`~defgraspnets.tactile.lfd.experiments.edge_following_experiment` result:
    the membrane pole of each demonstration on its straight pipe (3-D, [m]), the policy's rollout on the
    unseen curved pipe (pipe axis black, pole blue in contact, red without), and the forward-variable
    weights of the HMM states over the rollout's steps (the GMR mixing weights of eq. 5.18)."""
    plt = _pyplot()
    report, height = result["report"], result["height"]
    fig = plt.figure(figsize=(16, 5))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    for k, demo in enumerate(result["demonstrations"]):
        pole = demo.poses[:, :3, :3] @ np.array([0.0, 0.0, height]) + demo.poses[:, :3, 3]
        ax.plot(*pole.T, "-", lw=1, label=f"demo {k}")
        ax.scatter(*pole[~demo.in_contact].T, c="tab:red", s=6)
    ax.set_title(f"{report['n_demonstrations']} teacher demonstrations (straight pipes)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(fontsize=7, loc="upper left")
    ax = fig.add_subplot(1, 3, 2, projection="3d")
    rollout = result["rollout"]
    ax.plot(*result["scene"].path.T, "k-", lw=3, alpha=0.4, label="curved pipe (unseen)")
    pole = rollout.pole_positions(height)
    ax.scatter(*pole.T, c=np.where(rollout.in_contact, "tab:blue", "tab:red"), s=8, label="membrane pole")
    ax.set_title(
        f"policy rollout: contact {report['rollout_contact_fraction']:.2f}, "
        f"{report['rollout_distance_along_pipe_m']:.2f} m along the pipe"
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(fontsize=7, loc="upper left")
    ax = fig.add_subplot(1, 3, 3)
    for j in range(rollout.weights.shape[1]):
        ax.plot(rollout.weights[:, j], "-", label=f"state {j}")
    ax.plot(rollout.in_contact.astype(float), "k:", lw=1, label="in contact")
    ax.set_xlabel("rollout step (1 Hz)")
    ax.set_ylabel("forward-variable weight h_j")
    ax.set_title(f"{report['hmm_states']}-state HMM, GMR weights")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------ mixed manipulation LfD
def mixed_manipulation_figure(result: Mapping):
    """Three panels of a :func:`~defgraspnets.tactile.lfd.manipulation.mixed_manipulation_experiment`
    result: the demonstrations and the policy rollouts seen from above (walls grey, table edge at y = 0;
    object centroid solid, palm pole dotted; capsules blue, prism orange; final position o, or a red x
    for a failure), and the prism's yaw modulo 180 deg over time with the success tolerance band."""
    from matplotlib.patches import Rectangle

    plt = _pyplot()
    report, palm, world = result["report"], result["palm"], result["world"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))
    panels = (
        ("demonstrations", result["demonstrations"], report["teacher_outcomes"]),
        ("policy rollouts (unseen starts)", result["rollouts"], report["rollouts"]),
    )
    for ax, (title, runs, outcomes) in zip(axes[:2], panels, strict=True):
        for wall in world.walls():
            c, h = np.asarray(wall.center), np.asarray(wall.half_extents)
            ax.add_patch(Rectangle(c[:2] - h[:2], 2 * h[0], 2 * h[1], color="0.6"))
        ax.axhline(0.0, color="k", lw=1.5)
        for run, outcome in zip(runs, outcomes, strict=True):
            ok = outcome["success"]
            color = "tab:blue" if run.obj.kind == "capsule" else "tab:orange"
            pole = np.array([palm.pole(p) for p in run.poses])
            ax.plot(pole[:, 0], pole[:, 1], ":", color=color, lw=0.8)
            ax.plot(run.object_poses[:, 0], run.object_poses[:, 1], "-", color=color, lw=1.5)
            ax.plot(*run.object_poses[-1, :2], "o" if ok else "x", color=color if ok else "r", ms=5)
        ax.set_title(f"{title}\ncapsules (blue), prism (orange); red x = failure", fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m] (table edge at y = 0)")
        ax.set_aspect("equal")
    ax = axes[2]
    dt = report["dt_s"]
    for runs, style, label in (
        (result["demonstrations"], "-", "demo"),
        (result["rollouts"], "--", "rollout"),
    ):
        first = True
        for run in runs:
            if run.obj.kind != "prism":
                continue
            yaw = np.rad2deg((run.object_poses[:, 2] + np.pi / 2) % np.pi - np.pi / 2)
            ax.plot(np.arange(len(yaw)) * dt, yaw, style, color="k" if style == "-" else "tab:orange",
                    lw=1, label=label if first else None)  # fmt: skip
            first = False
    tol = report["yaw_tolerance_deg"]
    ax.axhspan(-tol, tol, color="tab:green", alpha=0.2, label=f"+-{tol:g} deg")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("prism yaw mod 180 [deg]")
    ax.set_title(f"prism; policy {report['successes']}/{report['trials']} successes overall")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
