"""Generate the tactile datasets of thesis §3.3 on the FEM membrane sensor (depth image -> wrench).

    python datagen/tactile.py                                  # small poking set (CPU, minutes)
    python datagen/tactile.py dataset=forearm                  # small forearm shear / twist set
    python datagen/tactile.py stride=1 limit=null membrane.cap_divisions=16 \
        indenter.radius=0.005 batch_size=16 device=cuda        # the thesis poking grid
    python datagen/tactile.py dataset=forearm repeats=5 stride=1 limit=null \
        membrane.cap_divisions=16                              # the thesis forearm grid + 4 repeats

Config: configs/datagen/tactile.yaml. All logic lives in :mod:`defgraspnets.tactile.datasets`; a
re-run resumes an unfinished shard and leaves a finished one alone.
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

    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.datasets import generate_tactile_dataset
    from defgraspnets.tactile.indenters import CapsuleIndenter, SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane
    from defgraspnets.tactile.sensor import membrane_solver_options

    if cfg.device is not None:
        wp.set_device(cfg.device)
    solver_options = membrane_solver_options(cfg.device, **OmegaConf.to_container(cfg.solver, resolve=True))
    sensor = build_membrane(cap_divisions=cfg.membrane.cap_divisions, layers=cfg.membrane.layers)
    if cfg.dataset == "poke":
        indenter = SphereIndenter(radius=cfg.indenter.radius)
    else:
        indenter = CapsuleIndenter(radius=cfg.forearm.radius, length=cfg.forearm.length)
    counts = generate_tactile_dataset(
        cfg.dataset,
        Path(cfg.out_dir) / cfg.dataset / f"{cfg.shard_name}.h5",
        sensor,
        indenter,
        gauge_pressure=cfg.gas.gauge_pressure,
        closed=cfg.gas.closed,
        friction=cfg.friction,
        batch_size=cfg.batch_size,
        stride=cfg.stride,
        limit=cfg.limit,
        shard_index=cfg.shard_index,
        shard_count=cfg.shard_count,
        max_step=cfg.max_step,
        intrinsics=PICO_FLEXX.scaled(cfg.camera_scale),
        store_points=cfg.store_points,
        config_text=OmegaConf.to_yaml(cfg, resolve=True),
        progress=cfg.progress,
        repeats=cfg.repeats,
        perturbation=OmegaConf.to_container(cfg.perturbation, resolve=True),
        solver_options=solver_options,
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
