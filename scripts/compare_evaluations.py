"""Is model B better than model A? A paired comparison of two evaluations on the same test data.

    python scripts/compare_evaluations.py a=runs/a/results.json b=runs/b/results.json out_dir=runs

Reads two ``results.json`` of ``scripts/evaluate.py`` and writes ``<out_dir>/<name>.md`` and ``.json``: per
level and metric, A, B, B - A and its 95 % interval from a bootstrap that resamples the test objects once
for both models. Config: configs/compare_evaluations.yaml. Logic: :mod:`defgraspnets.eval.compare`.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("compare_evaluations")


def read_results(path: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"evaluation results not found: {p}")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{p} is not valid JSON: {err}") from err


@hydra.main(version_base="1.3", config_path="../configs", config_name="compare_evaluations")
def main(cfg: DictConfig) -> None:
    from defgraspnets.eval.compare import COMPARISON_COLUMNS, compare_evaluations
    from defgraspnets.eval.report import markdown_table, write_json

    rows = compare_evaluations(
        read_results(cfg.a),
        read_results(cfg.b),
        metrics=list(cfg.metrics),
        level=cfg.level,
        resamples=cfg.resamples,
        seed=cfg.seed,
    )
    text = f"## B - A (A: `{cfg.a}`, B: `{cfg.b}`)\n\n" + markdown_table(rows, COMPARISON_COLUMNS) + "\n"
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{cfg.name}.md").write_text(text)
    write_json(out / f"{cfg.name}.json", {"a": str(cfg.a), "b": str(cfg.b), "level": cfg.level, "rows": rows})
    print(text)
    log.info("wrote %s", out / f"{cfg.name}.md")


if __name__ == "__main__":
    main()
