"""Mixed-manipulation learning from demonstration in simulation (thesis §5.5).

    python scripts/lfd_mixed_manipulation.py
    python scripts/lfd_mixed_manipulation.py seed=1 n_rollouts=20 teacher.push_speed=0.03

Config: configs/lfd_mixed_manipulation.yaml. Logic: :mod:`defgraspnets.tactile.lfd.manipulation`. Outputs in
the run directory: lfd_mixed_manipulation.json (teacher and policy successes per task, per-start outcomes) and
lfd_mixed_manipulation.png (object and palm paths of the demonstrations and rollouts, prism yaw over time).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("lfd_mixed_manipulation")


@hydra.main(version_base="1.3", config_path="../configs", config_name="lfd_mixed_manipulation")
def main(cfg: DictConfig) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from defgraspnets.tactile.contour_sim import build_fast_simulation
    from defgraspnets.tactile.lfd.manipulation import (
        ManipulationWorld,
        TeacherParameters,
        mixed_manipulation_experiment,
    )

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = build_fast_simulation(
        cfg.sensor.cap_divisions, cfg.sensor.gauge_pressure, cfg.sensor.camera_scale,
        deformation_threshold=cfg.sensor.deformation_threshold, core_fraction=cfg.sensor.core_fraction,
    )  # fmt: skip
    world = ManipulationWorld(**dict(cfg.world))
    teacher = TeacherParameters(**dict(cfg.teacher))
    result = mixed_manipulation_experiment(
        sim, world, teacher, n_demonstrations=cfg.n_demonstrations, n_rollouts=cfg.n_rollouts,
        n_states=cfg.n_states, rollout_steps=cfg.rollout_steps, seed=cfg.seed,
        regularization=cfg.hmm_regularization, yaw_tolerance=np.deg2rad(cfg.yaw_tolerance_deg),
    )  # fmt: skip
    report = result["report"]
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "lfd_mixed_manipulation.json").write_text(json.dumps(report, indent=2))
    log.info(
        "teacher %d/%d, policy %d/%d %s (%.1f s)", report["teacher_successes"], report["n_demonstrations"],
        report["successes"], report["trials"], report["successes_by_task"], report["wall_time_s"],
    )  # fmt: skip

    palm = result["palm"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))
    titles = ("demonstrations", "policy rollouts (unseen starts)")
    for ax, runs, title in zip(axes[:2], (result["demonstrations"], result["rollouts"]), titles, strict=True):
        for wall in world.walls():
            c, h = np.asarray(wall.center), np.asarray(wall.half_extents)
            ax.add_patch(plt.Rectangle(c[:2] - h[:2], 2 * h[0], 2 * h[1], color="0.6"))
        ax.axhline(0.0, color="k", lw=1.5)
        for run, ok in zip(runs, [o["success"] for o in _outcomes(result, runs)], strict=True):
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
    for runs, style, label in (
        (result["demonstrations"], "-", "demo"),
        (result["rollouts"], "--", "rollout"),
    ):
        first = True
        for run in runs:
            if run.obj.kind != "prism":
                continue
            yaw = np.rad2deg((run.object_poses[:, 2] + np.pi / 2) % np.pi - np.pi / 2)
            ax.plot(np.arange(len(yaw)) * teacher.dt, yaw, style, color="k" if style == "-" else "tab:orange",
                    lw=1, label=label if first else None)  # fmt: skip
            first = False
    tol = cfg.yaw_tolerance_deg
    ax.axhspan(-tol, tol, color="tab:green", alpha=0.2, label=f"+-{tol:g} deg")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("prism yaw mod 180 [deg]")
    ax.set_title(f"prism; policy {report['successes']}/{report['trials']} successes overall")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "lfd_mixed_manipulation.png", dpi=110)
    plt.close(fig)
    log.info("wrote %s", out)
    return report


def _outcomes(result: dict, runs: list) -> list[dict]:
    rep = result["report"]
    return rep["teacher_outcomes"] if runs is result["demonstrations"] else rep["rollouts"]


if __name__ == "__main__":
    main()
