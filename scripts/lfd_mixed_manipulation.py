"""Mixed-manipulation learning from demonstration in simulation (thesis §5.5).

    python scripts/lfd_mixed_manipulation.py
    python scripts/lfd_mixed_manipulation.py seed=1 n_rollouts=20 teacher.push_speed=0.03

Config: configs/lfd_mixed_manipulation.yaml. Logic: :mod:`defgraspnets.tactile.lfd.manipulation`, figure:
:mod:`defgraspnets.tactile.loop_plots`. Outputs in the run directory: lfd_mixed_manipulation.json (teacher and
policy successes per task, per-start outcomes) and lfd_mixed_manipulation.png (object and palm paths of the
demonstrations and rollouts, prism yaw over time).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("lfd_mixed_manipulation")


@hydra.main(version_base="1.3", config_path="../configs", config_name="lfd_mixed_manipulation")
def main(cfg: DictConfig) -> dict:
    import numpy as np

    from defgraspnets.tactile.contour_sim import build_fast_simulation
    from defgraspnets.tactile.lfd.manipulation import (
        ManipulationWorld,
        TeacherParameters,
        mixed_manipulation_experiment,
    )
    from defgraspnets.tactile.loop_plots import mixed_manipulation_figure, save_figure

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = build_fast_simulation(**cfg.sensor)
    world = ManipulationWorld(**dict(cfg.world))
    teacher = TeacherParameters(**dict(cfg.teacher))
    result = mixed_manipulation_experiment(
        sim, world, teacher, n_demonstrations=cfg.n_demonstrations, n_rollouts=cfg.n_rollouts,
        n_states=cfg.n_states, rollout_steps=cfg.rollout_steps, seed=cfg.seed,
        regularization=cfg.hmm_regularization, yaw_tolerance=np.deg2rad(cfg.yaw_tolerance_deg),
        n_restarts=cfg.hmm_restarts, mirror_demonstrations=tuple(cfg.mirror_demonstrations),
    )  # fmt: skip
    report = result["report"]
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "lfd_mixed_manipulation.json").write_text(json.dumps(report, indent=2))
    log.info(
        "teacher %d/%d, policy %d/%d %s (%.1f s)", report["teacher_successes"], report["n_demonstrations"],
        report["successes"], report["trials"], report["successes_by_task"], report["wall_time_s"],
    )  # fmt: skip
    save_figure(mixed_manipulation_figure(result), out / "lfd_mixed_manipulation.png")
    log.info("wrote %s", out)
    return report


if __name__ == "__main__":
    main()
