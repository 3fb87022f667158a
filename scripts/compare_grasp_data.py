"""Compare two data sets of the same grasps (solver settings, devices, code versions): what each solved, how
far the solved states differ, and whether the grasp rankings by mean stress agree.

    python scripts/compare_grasp_data.py a=data/plain b=data/stabilized out_dir=reports

Writes ``<out_dir>/grasp_data_comparison.md`` and ``.json`` (per object, per ramp and pooled). Config:
configs/compare_grasp_data.yaml. Logic: :mod:`defgraspnets.data.shard_compare`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("compare_grasp_data")


@hydra.main(version_base="1.3", config_path="../configs", config_name="compare_grasp_data")
def main(cfg: DictConfig) -> None:
    from defgraspnets.data.shard_compare import compare_grasp_data, comparison_markdown, pooled_summary
    from defgraspnets.eval.report import write_json

    tolerances = {
        "stress_tolerance": cfg.stress_tolerance,
        "rotation_tolerance_deg": cfg.rotation_tolerance_deg,
    }
    rows = compare_grasp_data(cfg.a, cfg.b, step=cfg.step, progress=True)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = pooled_summary(rows, **tolerances)
    text = comparison_markdown(rows, str(cfg.a), str(cfg.b), summary=summary)
    (out / f"{cfg.name}.md").write_text(text)
    write_json(
        out / f"{cfg.name}.json",
        {"a": str(cfg.a), "b": str(cfg.b), "step": cfg.step, "all": summary, "shards": rows},
    )
    print(text)
    log.info("wrote %s", out / f"{cfg.name}.md")


if __name__ == "__main__":
    main()
