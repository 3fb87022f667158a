"""Generate grasp shards: squeeze ramps of sampled Franka grasps on the FEM engine (thesis §7.4).

    python datagen/grasps.py                                   # small default data set -> data/grasps
    python datagen/grasps.py object=ellipsoid_20x20x20 num_grasps=20 device=cuda
    python datagen/grasps.py -m object=cuboid_30x30x30,ellipsoid_20x20x20,cylinder_r20_h40
    python datagen/grasps.py -m object=cuboid_50x50x50 shard_count=4 shard_index=0,1,2,3
    python datagen/grasps.py experiments=[pickup,reorientation,linear,angular]   # + DefGraspSim metrics
    python datagen/grasps.py object=cuboid_50x50x50 num_grasps=100 device=cuda stream_slots=128
    python datagen/grasps.py object=/data/meshes/mug.vtu file_labels.category=cup   # any tet or surface mesh

Config: configs/datagen/grasps.yaml (thesis-scale values in its comments). All logic lives in
:func:`defgraspnets.grasp.datagen.generate_object_shards`; re-running resumes unfinished shards.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("datagen.grasps")


@hydra.main(version_base="1.3", config_path="../configs", config_name="datagen/grasps")
def main(cfg: DictConfig) -> None:
    from defgraspnets.grasp.datagen import (
        claim_object,
        generate_object_shards,
        resolve_object_mesh,
        structured_box,
    )
    from defgraspnets.grasp.experiments import experiment_solver_options
    from defgraspnets.grasp.squeeze import squeeze_solver_options

    if cfg.claim_dir:
        if not claim_object(cfg.claim_dir, cfg.object):
            log.info("%s: claimed by another worker, skipped", cfg.object)
            return
        log.info("claimed object %s for this worker", cfg.object)
    obj, labels = cfg.object, {}
    if obj == "box":
        obj = structured_box(cfg.box.size, cfg.box.divisions)
    elif Path(obj).suffix:  # a mesh file: tet mesh (.vtu, .msh, ...) or closed surface (.obj, .stl, ...)
        obj = resolve_object_mesh(obj, target_nodes=cfg.target_nodes, mesher=cfg.mesher)
        labels = {"category": cfg.file_labels.category, "source": cfg.file_labels.source}
    results = generate_object_shards(
        obj,
        **labels,
        out_dir=cfg.out_dir,
        youngs_modulus=OmegaConf.to_object(cfg.youngs_modulus)
        if OmegaConf.is_list(cfg.youngs_modulus)
        else cfg.youngs_modulus,
        moduli_per_object=cfg.moduli_per_object,
        all_moduli_objects=list(cfg.all_moduli_objects),
        num_grasps=cfg.num_grasps,
        rotations_per_axis=cfg.rotations_per_axis,
        steps=cfg.steps,
        max_force=cfg.max_force,
        friction=cfg.friction,
        poisson_ratio=cfg.poisson_ratio,
        density=cfg.density,
        material_model=cfg.material_model,
        shard_count=cfg.shard_count,
        shard_index=cfg.shard_index,
        seed=cfg.seed,
        device=cfg.device,
        target_nodes=cfg.target_nodes,
        mesher=cfg.mesher,
        solver_options=squeeze_solver_options(
            linear_solver=cfg.linear_solver,
            max_newton_per_solve=cfg.max_newton_per_step,
            max_newton_first_step=cfg.max_newton_first_step,
            max_step_fraction=cfg.max_step_fraction,
            friction_stick_slip=cfg.friction_stick_slip,
            stabilization=cfg.stabilization,
            stabilization_release=cfg.stabilization_release,
            force_maximum_runaway=cfg.force_maximum_runaway,
            force_maximum_snap=cfg.force_maximum_snap,
            stabilization_relax=cfg.stabilization_relax,
            stabilization_relax_decay=cfg.stabilization_relax_decay,
            self_contact=cfg.self_contact,
            self_contact_model=cfg.self_contact_model,
            self_contact_friction=cfg.self_contact_friction,
        ),
        reject_inverted=cfg.reject_inverted,
        overwrite=cfg.overwrite,
        config_text=OmegaConf.to_yaml(cfg, resolve=True),
        progress=cfg.progress,
        experiments=cfg.experiments,  # a list, or one name
        experiment_settings=OmegaConf.to_container(cfg.experiment_settings, resolve=True),
        experiment_options=experiment_solver_options(linear_solver=cfg.experiment_linear_solver),
        directions_per_solver=cfg.experiment_directions_per_solver,
        moduli_per_solver=cfg.moduli_per_solver,
        stream_slots=cfg.stream_slots,
    )
    for r in results:
        if r.skipped:
            log.info("%s: already finished (overwrite=true regenerates it)", r.path)
        else:
            log.info("%s: %d/%d squeeze ramps solved, %.1f s", r.path, r.solved, r.total, r.seconds)
            if r.experiments:
                log.info("%s: experiment entries: %s", r.path.name, r.experiment_summary())


if __name__ == "__main__":
    main()
