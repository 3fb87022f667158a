"""Summarize a folder of grasp shards: what was solved, what failed and why, and how consistently the
ground truth ranks the grasps across moduli (a reference for DefGraspNets' Kendall tau).

    python scripts/grasp_data_report.py data_dir=data/grasps

Writes ``<out_dir>/grasp_data_report.md`` and ``.json``. Config: configs/grasp_data_report.yaml. Logic:
:mod:`defgraspnets.data.shard_report`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("grasp_data_report")


@hydra.main(version_base="1.3", config_path="../configs", config_name="grasp_data_report")
def main(cfg: DictConfig) -> None:
    from defgraspnets.data.dataset import discover_shards
    from defgraspnets.data.grasp_schema import GraspShard
    from defgraspnets.data.shard_report import report_markdown, shard_summary
    from defgraspnets.eval.report import write_json

    rows = [shard_summary(GraspShard(p), progress=True) for p in discover_shards(cfg.data_dir)]
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = report_markdown(rows)
    (out / f"{cfg.name}.md").write_text(text)
    write_json(out / f"{cfg.name}.json", {"data_dir": str(cfg.data_dir), "shards": rows})
    print(text)
    log.info("wrote %s", out / f"{cfg.name}.md")


if __name__ == "__main__":
    main()
