"""Render a grasp sample of a shard as a PNG (stress, deformation, finger pads) and export it as VTU.

    python scripts/show_grasp.py shard=data/grasps/box_30x30x30__shard0of1.h5            # last step, grasp 0
    python scripts/show_grasp.py shard=... modulus=1 grasp=3 step=24 out_dir=figures

Config: configs/show_grasp.yaml. Logic: :mod:`defgraspnets.grasp.visualize`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

log = logging.getLogger("show_grasp")


@hydra.main(version_base="1.3", config_path="../configs", config_name="show_grasp")
def main(cfg: DictConfig) -> None:
    from defgraspnets.grasp.visualize import export_sample_vtu, load_sample, render_sample

    if cfg.shard is None:
        raise ValueError("give the shard to show: python scripts/show_grasp.py shard=<path/to/file.h5>")
    sample = load_sample(cfg.shard, cfg.modulus, cfg.grasp, cfg.step)
    stem = Path(cfg.out_dir) / f"{sample.name}_E{sample.k}_g{sample.g}_s{sample.s}"
    png = render_sample(sample, stem.with_suffix(".png"), exaggeration=cfg.exaggeration)
    vtu, fingers = export_sample_vtu(sample, stem.with_suffix(".vtu"))
    log.info("%s: wrote %s, %s, %s", sample.title, png, vtu, fingers)


if __name__ == "__main__":
    main()
