"""Closed-loop tactile contour following on four scenes (thesis ch. 4) with the fast membrane model.

    python scripts/contour_following.py
    python scripts/contour_following.py scenes=[shelf_corner] controller.alignment_gain=0.5

Config: configs/contour_following.yaml. Logic: :mod:`defgraspnets.tactile.contour_sim`, figures:
:mod:`defgraspnets.tactile.loop_plots`. Outputs in the run directory: contour_following.json (metrics per
scene, F~ vs force correlation), trajectories.png, force_proxy.png (the Fig. 4.4 analogue: F~ against the
model's contact force over all in-contact steps).
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
    from defgraspnets.tactile.contour import ContourParameters
    from defgraspnets.tactile.contour_sim import build_fast_simulation, contour_following_study
    from defgraspnets.tactile.loop_plots import (
        contour_trajectories_figure,
        force_proxy_figure,
        save_figure,
    )

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = build_fast_simulation(**cfg.sensor)
    params = ContourParameters(**dict(cfg.controller))
    study = contour_following_study(
        sim, list(cfg.scenes), params, max_displacement=cfg.max_displacement, log=log.info
    )
    report = study.report
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "contour_following.json").write_text(json.dumps(report, indent=2))
    save_figure(contour_trajectories_figure(study.runs, study.scenes, study.height), out / "trajectories.png")
    save_figure(force_proxy_figure(study.runs, report["force_proxy_correlation"]), out / "force_proxy.png")
    log.info("wrote %s (%.1f s)", out, report["wall_time_s"])
    return report


if __name__ == "__main__":
    main()
