"""Edge-following learning from demonstration in simulation (thesis §5.4).

    python scripts/lfd_edge_following.py
    python scripts/lfd_edge_following.py rollout_steps=90 seed=1

Config: configs/lfd_edge_following.yaml. Logic: :func:`defgraspnets.tactile.lfd.experiments.
edge_following_experiment`, figure: :func:`defgraspnets.tactile.loop_plots.edge_following_figure`. Outputs in
the run directory: lfd_edge_following.json (demonstrations, HMM, rollout contact, housing contact and
progress along the unseen pipe) and lfd_edge_following.png.
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

log = logging.getLogger("lfd_edge_following")


@hydra.main(version_base="1.3", config_path="../configs", config_name="lfd_edge_following")
def main(cfg: DictConfig) -> dict:
    from defgraspnets.tactile.contour import ContourParameters
    from defgraspnets.tactile.contour_sim import build_fast_simulation
    from defgraspnets.tactile.lfd.experiments import edge_following_experiment
    from defgraspnets.tactile.loop_plots import edge_following_figure, save_figure

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = build_fast_simulation(**cfg.sensor)
    result = edge_following_experiment(
        sim,
        ContourParameters(**dict(cfg.teacher)),
        steps=cfg.demonstration_steps,
        rollout_steps=cfg.rollout_steps,
        seed=cfg.seed,
    )
    report = result["report"]
    report["wall_time_s"] = time.perf_counter() - t0
    (out / "lfd_edge_following.json").write_text(json.dumps(report, indent=2))
    log.info(
        "%d demonstrations, %d-state HMM; rollout on the curved pipe: contact %.2f, housing %d steps, "
        "%.3f m along the pipe in %d steps (%.1f s)", report["n_demonstrations"], report["hmm_states"],
        report["rollout_contact_fraction"], report["rollout_housing_contact_steps"],
        report["rollout_distance_along_pipe_m"], report["rollout_steps"], report["wall_time_s"],
    )  # fmt: skip
    save_figure(edge_following_figure(result), out / "lfd_edge_following.png")
    log.info("wrote %s", out)
    return report


if __name__ == "__main__":
    main()
