"""Evaluate DefGraspNets checkpoints: §7.6 table per generalization level, Table 7.1 per test object, plots.

    python scripts/evaluate.py ckpt_path=logs/defgraspnets/runs/<time>/checkpoints/last.ckpt
    python scripts/evaluate.py 'ckpt_paths=[a.ckpt,b.ckpt]' data.data_dir=/data/grasps device=cuda
    python scripts/evaluate.py ckpt_path=a.ckpt data.data_dir=/data/fresh_grasps part=all  # every squeeze
    python scripts/evaluate.py 'ckpt_paths=[base.ckpt,v1.ckpt,v2.ckpt,v3.ckpt,v4.ckpt]' ablations=true

For each checkpoint the test split it was trained with is rebuilt from the datamodule hyperparameters stored
in the checkpoint. Outputs in Hydra's run directory: ``results.md`` and ``results.json`` (rows: tau_s, tau_d,
stress MAE [kPa], deformation MAE [mm] per level; per test object with its Chamfer distance d_C [mm] to the
nearest training object; with ``ablations=true`` the Table 7.2 analogue of checkpoints that differ in one
design condition, :mod:`defgraspnets.eval.ablation`) and ``fields_<level>_<i>_{stress,deformation}.png``
(predicted vs FEM fields; ``fields_<model>_<level>_...`` for several checkpoints, model = run directory).
``part=all`` evaluates every solved squeeze of ``data.data_dir`` whatever the split (data the checkpoint never
saw, e.g. new grasps drawn with another datagen seed); its object rows name no nearest training object.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("evaluate")

PARTS = ("test", "val", "train", "all")


def load(ckpt_path: str, cfg: DictConfig, device):
    """(predictor module, datamodule, level name) of a checkpoint, the datamodule with ``cfg.data``
    overrides; for ``cfg.part == "train"`` its training part holds the evaluation steps (not the training
    steps). The level name is the split the checkpoint was trained with (the rows' label)."""

    from defgraspnets.data.datamodule import GraspDataModule
    from defgraspnets.models.checkpoints import read_checkpoint
    from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

    path = Path(ckpt_path)
    ckpt = read_checkpoint(path, "DefGraspNetsModule")  # names a missing, unreadable or wrong-model file
    dm_hparams = dict(ckpt.get("datamodule_hyper_parameters") or {})
    if not dm_hparams:
        raise KeyError(f"{path}: no datamodule hyperparameters stored (was it trained with GraspDataModule?)")
    level_name = dm_hparams.get("split", "unseen_grasps")
    for key, value in OmegaConf.to_container(cfg.data, resolve=True).items():
        if value is not None:
            dm_hparams[key] = value
    if cfg.part == "train":
        dm_hparams["train_steps"] = dm_hparams.get("eval_steps")
    if cfg.part == "all":
        # every solved squeeze, whatever the split: the checkpoint's level need not fit the data (an
        # unseen_real model on data without real objects), so the data is split by grasps only to load it;
        # rows keep the checkpoint's level name
        dm_hparams.update(split="unseen_grasps", test_objects=None, train_objects=None)
    module = DefGraspNetsModule.load_from_checkpoint(path, map_location="cpu").to(device).eval()
    module.use_displacement_target(dm_hparams.get("displacement", "total"))
    return module, GraspDataModule(**dm_hparams), level_name


def model_label(ckpt_path: str) -> str:
    """A short name of a checkpoint for the tables: its run directory (``<run>/checkpoints/last.ckpt``) or
    else its file name without the suffix."""
    path = Path(ckpt_path)
    return path.parent.parent.name if path.parent.name == "checkpoints" else path.stem


def evaluate_checkpoint(
    ckpt_path: str, cfg: DictConfig, out_dir: Path, plots_by_model: bool = False
) -> tuple[dict, list[dict]]:
    """Run the test split; return the level row and the per-object rows. ``plots_by_model``: the plots'
    file names start with the model's label (several checkpoints of one split would overwrite each
    other's)."""
    import numpy as np
    import torch
    from torch.utils.data import Subset
    from torch_geometric.loader import DataLoader
    from tqdm.auto import tqdm

    from defgraspnets.eval.ablation import model_conditions
    from defgraspnets.eval.chamfer import chamfer_distance, surface_samples
    from defgraspnets.eval.metrics import FieldMetrics
    from defgraspnets.eval.report import plot_fields

    device = torch.device(cfg.device)
    module, dm, level_name = load(ckpt_path, cfg, device)
    dm.setup("test")
    test = dm.datasets[cfg.part]
    idx = np.arange(len(test))
    if cfg.max_samples and len(test) > cfg.max_samples:
        idx = np.unique(np.linspace(0, len(test) - 1, int(cfg.max_samples)).round().astype(int))
    loader = DataLoader(
        Subset(test, idx.tolist()),
        batch_size=dm.hparams.eval_batch_size or 1,
        num_workers=dm.hparams.num_workers,
    )
    metrics = FieldMetrics(min_relative_spread=cfg.min_relative_spread)
    net = module.net
    with torch.no_grad():
        for batch in tqdm(loader, desc=f"{cfg.part} {level_name}", leave=False):
            batch = batch.to(device)
            stress, disp = net.fields(batch)
            metrics.update(stress, disp, batch)
    # a part other than the test part is named in every row and file ("unseen_grasps/train")
    split = level_name if cfg.part == "test" else f"{level_name}/{cfg.part}"
    model = model_label(ckpt_path)
    stem = f"{model}_{split}" if plots_by_model else split
    stem = stem.replace("/", "_")
    # which field "deformation" is: the total displacement or the one without the object's rigid motion
    level = {
        "model": model,
        "split": split,
        "displacement_target": module.displacement_target,
        "checkpoint": str(ckpt_path),
        "min_relative_spread": cfg.min_relative_spread,
        "conditions": model_conditions(module.hparams),  # the design variables of Table 7.2
        **metrics.compute(),
    }

    # Table 7.1: per test object, with its Chamfer distance to the nearest training object. part=all: the
    # split rebuilt on foreign data says nothing of the checkpoint's real training objects: no nearest one
    train_objects = [] if cfg.part == "all" else dm.split.train_objects
    sampled = sorted(set(train_objects) | set(dm.split.test_objects)) if train_objects else []
    samples = {name: surface_samples(*dm.object_surface(name), count=cfg.chamfer_samples) for name in sampled}
    rows = []
    for oid, values in metrics.compute_per_object().items():
        name = dm.object_names[oid]
        dist = {t: chamfer_distance(samples[name], samples[t]) for t in train_objects}
        nearest = min(dist, key=dist.get) if dist else None
        rows.append(
            {
                "model": model,
                "split": split,
                "object": name,
                "nearest_train_object": nearest,
                "chamfer_mm": dist[nearest] * 1e3 if nearest else float("nan"),
                **values,
            }
        )

    # Fig. 7.3 analogue: predicted vs ground-truth fields on a few test samples
    for j, i in enumerate(np.linspace(0, len(idx) - 1, min(cfg.plots, len(idx))).round().astype(int)):
        g = test[int(idx[i])].to(device)
        with torch.no_grad():
            s, d = net.fields(g)
        obj = g.object_mask.cpu()
        shard, k, gi, step = g.sample[0].tolist()
        pts = g.pos[obj].cpu().numpy()
        title = (
            f"{dm.object_names[int(g.object_id)]}  ({cfg.part})  grasp {gi}  "
            f"E = {float(g.youngs_modulus):.3g} Pa  F = {float(g.force):.3g} N"
        )
        plot_fields(
            pts,
            s[obj].cpu().numpy() / 1e3,
            g.stress[obj].cpu().numpy() / 1e3,
            out_dir / f"fields_{stem}_{j}_stress.png",
            title,
            "von Mises stress [kPa]",
        )
        plot_fields(
            pts,
            d[obj].norm(dim=1).cpu().numpy() * 1e3,
            g.displacement[obj].norm(dim=1).cpu().numpy() * 1e3,
            out_dir / f"fields_{stem}_{j}_deformation.png",
            title,
            "deformation |d| [mm]",
        )
    return level, rows


@hydra.main(version_base="1.3", config_path="../configs", config_name="evaluate.yaml")
def main(cfg: DictConfig) -> None:
    from defgraspnets.eval.ablation import ABLATION_COLUMNS, ablation_rows
    from defgraspnets.eval.report import LEVEL_COLUMNS, OBJECT_COLUMNS, markdown_table, write_json

    ckpts = list(cfg.ckpt_paths or []) + ([cfg.ckpt_path] if cfg.ckpt_path else [])
    if not ckpts:
        raise ValueError("give ckpt_path=<file> or ckpt_paths=[...]")
    if cfg.part not in PARTS:
        raise ValueError(f"part={cfg.part!r}: choose one of {', '.join(PARTS)}")
    out_dir = Path(cfg.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not isinstance(cfg.ablations, bool):
        raise ValueError(f"ablations={cfg.ablations!r}: true or false")
    if cfg.ablations and len(ckpts) < 2:
        raise ValueError("ablations=true compares several checkpoints: give ckpt_paths=[baseline,V1,...]")
    levels, objects = [], []
    for ckpt in ckpts:
        level, rows = evaluate_checkpoint(ckpt, cfg, out_dir, plots_by_model=len(ckpts) > 1)
        levels.append(level)
        objects += rows
    # several checkpoints: each row names its model (run directory or file name)
    named = (("model", "Model", "{}"),) if len(ckpts) > 1 else ()
    sections = [
        "## DefGraspNets generalization (thesis §7.6)",
        markdown_table(levels, (*named, *LEVEL_COLUMNS)),
        "## Per test object (thesis Table 7.1): d_C = Chamfer distance to the nearest train object",
        markdown_table(objects, (*named, ("split", "Level", "{}"), *OBJECT_COLUMNS)),
    ]
    results = {"levels": levels, "objects": objects}
    if cfg.ablations:
        results["ablations"] = ablation_rows(levels)
        sections += [
            "## Ablations (thesis §7.8, Table 7.2): each variant differs from the baseline in the named "
            "condition; thesis values from its own data and test set",
            markdown_table(results["ablations"], ABLATION_COLUMNS),
        ]
    text = "\n\n".join(sections) + "\n"
    (out_dir / "results.md").write_text(text)
    write_json(out_dir / "results.json", results)
    print(text)
    log.info("results written to %s", out_dir)


if __name__ == "__main__":
    main()
