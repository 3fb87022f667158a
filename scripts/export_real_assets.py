"""Copy the real-world objects' mesh files out of their pip packages, for a machine without them.

    python scripts/export_real_assets.py out=assets            # where pybullet / robosuite are installed
    export DEFGRASPNETS_ASSETS=$PWD/assets                      # then, on the other machine

See defgraspnets.objects.real. Config: configs/export_real_assets.yaml.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="../configs", config_name="export_real_assets")
def main(cfg: DictConfig) -> None:
    from defgraspnets.objects import ASSETS_ENV, export_real_assets

    names = None if cfg.names is None else list(cfg.names)
    paths = export_real_assets(cfg.out, names)
    for path in paths:
        print(path)
    print(f"{len(paths)} mesh files -> {cfg.out}; elsewhere: export {ASSETS_ENV}=<a copy of {cfg.out}>")


if __name__ == "__main__":
    main()
