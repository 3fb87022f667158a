"""Force-deformation models of the simulated tactile sensor (thesis §2.4, Figs 2.9-2.11, Table 2.1).

    python scripts/tactile_force_models.py
    python scripts/tactile_force_models.py cap_divisions=[16,16,16]
    python scripts/tactile_force_models.py force_matching.trials=3 force_matching.depth_noise=0.0005

Config: configs/tactile_force_models.yaml. Logic: :mod:`defgraspnets.tactile.indentation_studies`.
Writes force_indentation.png, slope_vs_pv.png, force_matching.png and force_models.json to the run dir.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("tactile_force_models")


@hydra.main(version_base="1.3", config_path="../configs", config_name="tactile_force_models")
def main(cfg: DictConfig) -> dict:
    import warp as wp

    from defgraspnets.tactile.indentation_studies import run_force_model_study

    wp.config.quiet = True
    c = OmegaConf.to_container(cfg, resolve=True)
    fm = c["force_matching"]
    report = run_force_model_study(
        c["out_dir"],
        sphere_diameters=c["sphere_diameters"],
        cap_divisions=c["cap_divisions"],
        states=c["states"],
        depths=c["depths"],
        polynomial_order=c["polynomial_order"],
        matching_diameter=fm["sphere_diameter"],
        matching_states=fm["states"],
        desired_force_fractions=fm["desired_force_fractions"],
        trials=fm["trials"],
        gain=fm["gain"],
        controller_max_step=fm["max_step"],
        indentation_tolerance=fm["indentation_tolerance"],
        max_steps=fm["max_steps"],
        depth_noise=fm["depth_noise"],
        indentation_percentile=fm["indentation_percentile"],
        seed=fm["seed"],
        layers=c["layers"],
        friction=c["friction"],
        max_step=c["max_step"],
        device=c["device"],
        contact_subdivisions=c["contact_subdivisions"],
        log=log.info,
    )
    for pv, row in report["table_2_1"].items():
        log.info(
            "Table 2.1: PV %s N m: F_actual - F_desired = %+.4f +- %.4f N",
            pv,
            row["mean_error"],
            row["standard_error"],
        )
    log.info("wrote %s/force_models.json (%.0f s)", c["out_dir"], report["seconds"])
    return report


if __name__ == "__main__":
    main()
