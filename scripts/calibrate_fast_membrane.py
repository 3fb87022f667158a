"""Calibrate the fast membrane model against the FEM sensor and report its error.

    python scripts/calibrate_fast_membrane.py
    python scripts/calibrate_fast_membrane.py fem_cap_divisions=10 camera_scale=1.0

Config: configs/calibrate_fast_membrane.yaml. Logic:
:func:`defgraspnets.tactile.fast_membrane.run_fem_calibration`. Writes fast_membrane_calibration.json to the
run directory; paste its ``calibration`` constants into ``DEFAULT_CALIBRATION`` of
:mod:`defgraspnets.tactile.fast_membrane`.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("calibrate_fast_membrane")


@hydra.main(version_base="1.3", config_path="../configs", config_name="calibrate_fast_membrane")
def main(cfg: DictConfig) -> dict:
    import platform

    from defgraspnets.tactile.fast_membrane import run_fem_calibration

    report = run_fem_calibration(
        fem_cap_divisions=cfg.fem_cap_divisions,
        fast_cap_divisions=cfg.fast_cap_divisions,
        camera_scale=cfg.camera_scale,
        gauge_pressure=cfg.gauge_pressure,
        max_depth=cfg.max_depth,
        levels=tuple(cfg.levels),
        sphere_radius=cfg.sphere_radius,
        pipe_radius=cfg.pipe_radius,
        pipe_length=cfg.pipe_length,
        sphere_tilt_deg=cfg.sphere_tilt_deg,
        pipe_turn_deg=cfg.pipe_turn_deg,
        pipe_offset=cfg.pipe_offset,
        contact_samples_per_face=cfg.contact_samples_per_face,
        contact_edge_radius=cfg.contact_edge_radius,
    )
    report["machine"] = platform.processor() or platform.machine()
    out = Path(cfg.paths.output_dir) / "fast_membrane_calibration.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    for r in report["samples"]:
        log.info(
            "%-28s F_fem=%.3f N  F_model=%.3f N  depth RMS=%.2f mm  F~ fem/model=%.3f/%.3f "
            "(plain FEM F~ %.3f)",
            r["name"], r["fem_force"], r["model_force"], r["depth_rms_error"] * 1e3,
            r["fem_contact_depth_proxy"], r["model_contact_depth_proxy"], r["fem_depth_proxy"],
        )  # fmt: skip
    keys = ("calibration", "fit_all", "fit_default_constants", "cross_shape_fit_spheres_test_pipes")
    keys += ("fast_model",)
    log.info("%s", json.dumps({k: report[k] for k in keys}, indent=2))
    log.info("wrote %s", out)
    return report


if __name__ == "__main__":
    main()
