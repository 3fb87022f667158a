"""Closed-loop end-effector pose correction (thesis §3.5, Fig. 3.9) and forearm support (Fig. 3.10) on the
FEM sensor.

    python scripts/pose_correction.py
    python scripts/pose_correction.py estimator=cnn ckpt_path=checkpoints/wrench_poke.ckpt
    python scripts/pose_correction.py forearm.enabled=true

Config: configs/pose_correction.yaml. Logic: :mod:`defgraspnets.tactile.closed_loops`, figure:
:mod:`defgraspnets.tactile.loop_plots`. Outputs in the run directory: pose_correction.json (per run and step:
sensor pose, true and estimated wrench, contact, displacement along the push, rotation) and
pose_correction.png (force and displacement vs step).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import hydra.utils  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("pose_correction")


@hydra.main(version_base="1.3", config_path="../configs", config_name="pose_correction")
def main(cfg: DictConfig) -> dict:
    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.closed_loops import (
        CorrectionGains,
        check_estimator,
        forearm_support_runs,
        make_estimator,
        pose_correction_runs,
    )
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import CapsuleIndenter, SphereIndenter
    from defgraspnets.tactile.loop_plots import pose_correction_figure, save_figure
    from defgraspnets.tactile.membrane import build_membrane

    if cfg.estimator == "cnn":
        cfg.ckpt_path = hydra.utils.to_absolute_path(cfg.ckpt_path)  # relative to the launch directory
    check_estimator(cfg.estimator, cfg.ckpt_path, cfg.cnn_reference)  # fail before the FEM set-up
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sensor = build_membrane(cap_divisions=cfg.sensor.cap_divisions, layers=cfg.sensor.layers)
    intrinsics = PICO_FLEXX.scaled(cfg.sensor.camera_scale) if cfg.sensor.camera_scale != 1.0 else PICO_FLEXX
    common = dict(
        gauge_pressure=cfg.sensor.gauge_pressure,
        closed=cfg.sensor.closed,
        friction=cfg.sensor.friction,
        contact_subdivisions=cfg.sensor.contact_subdivisions,
        intrinsics=intrinsics,
    )
    sim = make_simulator(sensor, SphereIndenter(radius=cfg.fingertip_radius), **common)
    estimator = make_estimator(cfg.estimator, sim, cfg.ckpt_path, cfg.cnn_reference)
    gains = CorrectionGains(**dict(cfg.gains))
    runs, entries = pose_correction_runs(
        sim, cfg.pokes, estimator, steps=cfg.steps, gains=gains, log=log.info
    )
    if cfg.forearm.enabled:
        arm = make_simulator(
            sensor, CapsuleIndenter(radius=cfg.forearm.radius, length=cfg.forearm.length), **common
        )
        arm_runs, arm_entries = forearm_support_runs(
            arm,
            cfg.forearm.steps,
            cfg.forearm.shear_per_step,
            cfg.forearm.twist_per_step,
            depth=cfg.forearm.depth,
            estimator=make_estimator(cfg.estimator, arm, cfg.ckpt_path, cfg.cnn_reference),
            gains=gains,
            log=log.info,
        )
        runs.update(arm_runs)
        entries.update(arm_entries)
    report = {"estimator": cfg.estimator, "gains": dict(cfg.gains), "runs": entries}
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "pose_correction.json").write_text(json.dumps(report, indent=2))
    save_figure(pose_correction_figure(runs), out / "pose_correction.png")
    log.info("wrote %s (%.1f s)", out, report["wall_time_s"])
    return report


if __name__ == "__main__":
    main()
