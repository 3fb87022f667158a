"""Generate the tactile datasets of thesis §3.3 on the FEM membrane sensor (depth image -> wrench).

    python datagen/tactile.py                                  # small poking set (CPU, minutes)
    python datagen/tactile.py dataset=forearm                  # small forearm shear / twist set
    python datagen/tactile.py stride=1 limit=null membrane.cap_divisions=16 \
        indenter.radius=0.005 batch_size=16 device=cuda        # the thesis poking grid
    python datagen/tactile.py dataset=forearm repeats=5 stride=1 limit=null \
        membrane.cap_divisions=16                              # the thesis forearm grid + 4 repeats

Config: configs/datagen/tactile.yaml. All logic lives in :mod:`defgraspnets.tactile.datasets`
(``generate_tactile_from_config``); a re-run resumes an unfinished shard and leaves a finished one alone.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("datagen.tactile")


@hydra.main(version_base="1.3", config_path="../configs", config_name="datagen/tactile")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets.tactile.datasets import generate_tactile_from_config

    if cfg.device is not None:
        wp.set_device(cfg.device)
    counts = generate_tactile_from_config(
        OmegaConf.to_container(cfg, resolve=True), config_text=OmegaConf.to_yaml(cfg, resolve=True)
    )
    if counts["skipped"] < 0:
        log.info("%s is already finished (delete it to regenerate)", counts["path"])
    else:
        log.info(
            "%s: %d samples, %d failed readings, %.1f s",
            counts["path"],
            counts["samples"],
            counts["failed"],
            counts["seconds"],
        )


if __name__ == "__main__":
    main()
