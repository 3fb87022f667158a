"""Closed-loop tactile contour following on four scenes (thesis ch. 4) with the fast membrane model.

    python scripts/contour_following.py
    python scripts/contour_following.py scenes=[shelf_corner] controller.alignment_gain=0.5

Config: configs/contour_following.yaml. Logic: :mod:`defgraspnets.tactile.contour_sim`. Outputs in the
run directory: contour_following.json (metrics per scene, F~ vs force correlation), trajectories.png,
force_proxy.png (the Fig. 4.4 analogue: F~ against the model's contact force over all in-contact steps).
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

log = logging.getLogger("contour_following")


@hydra.main(version_base="1.3", config_path="../configs", config_name="contour_following")
def main(cfg: DictConfig) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from defgraspnets.tactile.contour import ContourParameters
    from defgraspnets.tactile.contour_sim import (
        build_fast_simulation,
        pearson_r,
        pole_height,
        pole_positions,
        run_contour_following,
        run_report,
        standard_scenes,
    )
    from defgraspnets.tactile.fast_membrane import DEFAULT_CALIBRATION

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = build_fast_simulation(
        cfg.sensor.cap_divisions, cfg.sensor.gauge_pressure, cfg.sensor.camera_scale,
        deformation_threshold=cfg.sensor.deformation_threshold, core_fraction=cfg.sensor.core_fraction,
    )  # fmt: skip
    height = pole_height(sim)
    scenes = standard_scenes(height)
    unknown = sorted(set(cfg.scenes) - set(scenes))
    if unknown:
        raise ValueError(f"unknown scenes {unknown}; choose from {sorted(scenes)}")
    params = ContourParameters(**dict(cfg.controller))
    runs, report = {}, {"scenes": {}}
    for name in cfg.scenes:
        t = time.perf_counter()
        runs[name] = run = run_contour_following(
            sim, scenes[name], params, max_displacement=cfg.max_displacement
        )
        report["scenes"][name] = {
            **run_report(run, params.desired_force, scenes[name], height),
            "wall_time_s": time.perf_counter() - t,
        }
        log.info("%s: %s", name, report["scenes"][name])
    proxy = np.concatenate([r.depth_proxy[r.in_contact] for r in runs.values()])
    force = np.concatenate([r.normal_force[r.in_contact] for r in runs.values()])
    slope, intercept = np.polyfit(proxy, force, 1)
    report["force_proxy_correlation"] = {
        "pearson_r": pearson_r(proxy, force),
        "samples": int(proxy.size),
        "fit_N_per_m": float(slope),
        "fit_intercept_N": float(intercept),
        "fem_pearson_r": DEFAULT_CALIBRATION.provenance.get("fem_pearson_r_force_vs_contact_depth_proxy"),
    }
    report["fast_model_calibration"] = DEFAULT_CALIBRATION.to_dict()
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "contour_following.json").write_text(json.dumps(report, indent=2))

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
    fig.savefig(out / "trajectories.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5, 4))
    for name, run in runs.items():
        ax.scatter(run.depth_proxy[run.in_contact], run.normal_force[run.in_contact], s=10, label=name)
    xs = np.linspace(0, proxy.max(), 10)
    ax.plot(xs, slope * xs + intercept, "k--", lw=1)
    ax.set_xlabel("F~ (eq. 4.6, indented pixels) [m]")
    ax.set_ylabel("contact force [N]")
    ax.set_title(f"F~ vs force, Pearson r = {report['force_proxy_correlation']['pearson_r']:.3f}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "force_proxy.png", dpi=110)
    plt.close(fig)
    log.info("wrote %s (%.1f s)", out, report["wall_time_s"])
    return report


if __name__ == "__main__":
    main()
