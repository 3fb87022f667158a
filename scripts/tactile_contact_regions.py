"""Contact regions of the simulated tactile sensor (thesis §2.3, Algorithm 1, Figs 2.5, 2.7, 2.8).

    python scripts/tactile_contact_regions.py
    python scripts/tactile_contact_regions.py obstacle_cap_divisions=16 sweep.cap_divisions=[16,16,8]

Config: configs/tactile_contact_regions.yaml. Logic: :mod:`defgraspnets.tactile.indentation_studies`.
Writes contact_regions.png, contact_area.png, deformed_area.png and contact_regions.json to the run dir.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("tactile_contact_regions")


@hydra.main(version_base="1.3", config_path="../configs", config_name="tactile_contact_regions")
def main(cfg: DictConfig) -> dict:
    import warp as wp

    from defgraspnets.tactile.indentation_studies import ClassificationConfig, run_contact_region_study

    wp.config.quiet = True
    c = OmegaConf.to_container(cfg, resolve=True)
    report = run_contact_region_study(
        c["out_dir"],
        obstacles=c["obstacles"],
        obstacle_depth=c["obstacle_depth"],
        obstacle_state=c["obstacle_state"],
        obstacle_cap_divisions=c["obstacle_cap_divisions"],
        sphere_diameters=c["sweep"]["sphere_diameters"],
        sweep_cap_divisions=c["sweep"]["cap_divisions"],
        sweep_states=c["sweep"]["states"],
        sweep_depths=c["sweep"]["depths"],
        layers=c["layers"],
        classification=ClassificationConfig(**c["classification"]),
        contact_tolerance=c["contact_tolerance"],
        friction=c["friction"],
        max_step=c["max_step"],
        device=c["device"],
        contact_subdivisions=c["contact_subdivisions"],
        log=log.info,
    )
    log.info("wrote %s/contact_regions.json (%.0f s)", c["out_dir"], report["seconds"])
    return report


if __name__ == "__main__":
    main()
