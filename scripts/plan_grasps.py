"""Plan grasps of an object with a trained DefGraspNets checkpoint: sample, score, refine, (verify).

    python scripts/plan_grasps.py ckpt_path=checkpoints/defgraspnets_small.ckpt object=box
    python scripts/plan_grasps.py ckpt_path=... object=ellipsoid_20x20x20 objective=max_mean_deformation
    python scripts/plan_grasps.py ckpt_path=... object=mesh.obj n_samples=100 refine_steps=12 device=cuda

Config: configs/plan.yaml (objectives: configs/objective/). Logic: :mod:`defgraspnets.planning`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("plan_grasps")


@hydra.main(version_base="1.3", config_path="../configs", config_name="plan")
def main(cfg: DictConfig) -> dict:
    import torch
    from hydra.utils import instantiate

    from defgraspnets.grasp.datagen import resolve_object_mesh
    from defgraspnets.models.predictor import DefGraspNetsPredictor
    from defgraspnets.planning import GraspPlanner
    from defgraspnets.planning.pipeline import plan_grasps

    device = cfg.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    predictor = DefGraspNetsPredictor.from_checkpoint(
        cfg.ckpt_path,
        device=device,
        precision=cfg.precision,
        compile=cfg.compile,
        fused_message_passing=cfg.fused_message_passing,
    )
    mesh = resolve_object_mesh(cfg.object, cfg.box.size, cfg.box.divisions, cfg.target_nodes, cfg.mesher)
    objective = instantiate(cfg.objective, _convert_="all")
    planner = GraspPlanner(
        predictor,
        mesh,
        cfg.youngs_modulus,
        objective,
        force=cfg.force,
        closing_temperature=cfg.closing_temperature,
        batch_size=cfg.batch_size,
        check_collisions=cfg.check_collisions,
        compile_geometry=cfg.compile_geometry,
    )
    report = plan_grasps(
        planner,
        cfg.out_dir,
        n_samples=cfg.n_samples,
        seed=cfg.seed,
        friction=cfg.friction,
        n_select=cfg.n_select,
        refine_steps=cfg.refine_steps,
        refine_options=dict(cfg.refine),
        verify=cfg.verify,
        verify_steps=cfg.verify_steps,
        fem_device=cfg.fem_device,
        poisson_ratio=cfg.poisson_ratio,
        density=cfg.density,
        material_model=cfg.material_model,
        progress=cfg.progress,
    )
    best = report["best"]
    log.info(
        "%s: best grasp (sample %d) %s = %.4g %s; wrote %s/plan.json",
        mesh.name, best["sample"], objective.name, best["q"], objective.units, cfg.out_dir,
    )  # fmt: skip
    return report


if __name__ == "__main__":
    main()
