"""Closed-loop end-effector pose correction (thesis §3.5, Fig. 3.9) and forearm support (Fig. 3.10) on the
FEM sensor.

    python scripts/pose_correction.py
    python scripts/pose_correction.py estimator=cnn ckpt_path=checkpoints/wrench_poke.ckpt
    python scripts/pose_correction.py forearm.enabled=true

Config: configs/pose_correction.yaml. Logic: :mod:`defgraspnets.tactile.closed_loops`. Outputs in the
run directory: pose_correction.json (per run and step: sensor pose, true and estimated wrench, contact,
displacement along the push, rotation) and pose_correction.png (force and displacement vs step).
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


def make_estimator(cfg: DictConfig, sim):
    """The configured wrench estimator (a missing checkpoint raises FileNotFoundError naming it)."""
    from defgraspnets.tactile.closed_loops import CNNWrenchEstimator, oracle_estimator

    if cfg.estimator == "oracle":
        return oracle_estimator
    if cfg.estimator == "cnn":
        if cfg.cnn_reference not in ("checkpoint", "simulator"):
            raise ValueError(f"cnn_reference must be 'checkpoint' or 'simulator', got {cfg.cnn_reference!r}")
        reference = sim.reference_depth().depth if cfg.cnn_reference == "simulator" else None
        return CNNWrenchEstimator.from_checkpoint(cfg.ckpt_path, reference=reference)
    raise ValueError(f"estimator must be 'oracle' or 'cnn', got {cfg.estimator!r}")


@hydra.main(version_base="1.3", config_path="../configs", config_name="pose_correction")
def main(cfg: DictConfig) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.closed_loops import (
        CorrectionGains,
        place_fingertip,
        run_forearm_support,
        run_pose_correction,
        shear_twist_schedule,
    )
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import CapsuleIndenter, PokeCommand, SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane

    if cfg.estimator not in ("oracle", "cnn"):
        raise ValueError(f"estimator must be 'oracle' or 'cnn', got {cfg.estimator!r}")
    if cfg.estimator == "cnn":
        cfg.ckpt_path = hydra.utils.to_absolute_path(cfg.ckpt_path)  # relative to the launch directory
        if not Path(cfg.ckpt_path).is_file():
            raise FileNotFoundError(
                f"wrench CNN checkpoint not found: {cfg.ckpt_path} (train it first, or run estimator=oracle)"
            )
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sensor = build_membrane(cap_divisions=cfg.sensor.cap_divisions, layers=cfg.sensor.layers)
    intrinsics = PICO_FLEXX.scaled(cfg.sensor.camera_scale) if cfg.sensor.camera_scale != 1.0 else PICO_FLEXX
    common = dict(
        gauge_pressure=cfg.sensor.gauge_pressure,
        closed=cfg.sensor.closed,
        friction=cfg.sensor.friction,
        intrinsics=intrinsics,
    )
    sim = make_simulator(sensor, SphereIndenter(radius=cfg.fingertip_radius), **common)
    estimator = make_estimator(cfg, sim)
    gains = CorrectionGains(**dict(cfg.gains))
    report = {"estimator": cfg.estimator, "gains": dict(cfg.gains), "runs": {}}
    runs = {}
    for name, poke in cfg.pokes.items():
        t = time.perf_counter()
        tip = place_fingertip(sim, PokeCommand(**dict(poke)))
        runs[name] = run = run_pose_correction(sim, tip, estimator, steps=cfg.steps, gains=gains)
        report["runs"][name] = {"poke": dict(poke), **run.to_dict(), "wall_time_s": time.perf_counter() - t}
        log.info(
            "%s: |F| %s N, displacement along push %s m, rotation %s rad",
            name,
            np.round(run.force_magnitude, 3).tolist(),
            np.round(run.displacement @ run.push_direction, 5).tolist(),
            np.round(run.rotation[-1], 4).tolist(),
        )
    if cfg.forearm.enabled:
        arm = make_simulator(
            sensor, CapsuleIndenter(radius=cfg.forearm.radius, length=cfg.forearm.length), **common
        )
        arm_estimator = make_estimator(cfg, arm)
        for name, shear, twist in [
            ("forearm_shear", cfg.forearm.shear_per_step, 0.0),
            ("forearm_twist", [0.0, 0.0, 0.0], cfg.forearm.twist_per_step),
        ]:
            t = time.perf_counter()
            runs[name] = run = run_forearm_support(
                arm,
                shear_twist_schedule(cfg.forearm.steps, list(shear), float(twist)),
                depth=cfg.forearm.depth,
                estimator=arm_estimator,
                gains=gains,
            )
            report["runs"][name] = {**run.to_dict(), "wall_time_s": time.perf_counter() - t}
            log.info(
                "%s: sensor displacement %s m, rotation %s rad",
                name,
                np.round(run.displacement[-1], 5).tolist(),
                np.round(run.rotation[-1], 4).tolist(),
            )
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "pose_correction.json").write_text(json.dumps(report, indent=2))

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
    fig.savefig(out / "pose_correction.png", dpi=110)
    plt.close(fig)
    log.info("wrote %s (%.1f s)", out, report["wall_time_s"])
    return report


if __name__ == "__main__":
    main()
