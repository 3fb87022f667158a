"""Evaluate trained wrench CNNs (thesis §3.4) on their validation splits; write errors and figures.

    python scripts/evaluate_wrench.py ckpts.poke=checkpoints/wrench_poke.ckpt \
        ckpts.forearm=checkpoints/wrench_forearm.ckpt ckpts.combined=checkpoints/wrench_combined.ckpt

Each model is scored on the validation split of every dataset it was trained on (the datamodule's
seeded 80:20 split by grid state, so the samples of states it never trained on): poke -> poking,
forearm -> forearm, combined -> both and their union. Writes ``wrench_eval.json`` (MSE in SI units next to the
thesis's 0.03 / 0.057 / 0.1, per-component RMSE and R²) and the Fig. 3.4 / 3.7 / 3.8 analogues as PNGs
in the run directory. Config: configs/evaluate_wrench.yaml. Logic: :mod:`defgraspnets.eval.wrench`.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("evaluate_wrench")

THESIS_VAL_MSE = {"poke": 0.03, "forearm": 0.057, "combined": 0.1}
TRAINED_ON = {"poke": ("poke",), "forearm": ("forearm",), "combined": ("poke", "forearm")}


@hydra.main(version_base="1.3", config_path="../configs", config_name="evaluate_wrench")
def main(cfg: DictConfig) -> dict:
    import numpy as np

    from defgraspnets.data.tactile_datamodule import TactileWrenchDataModule
    from defgraspnets.eval import wrench as ev
    from defgraspnets.models.wrench_module import WrenchRegressionModule

    models = {k: WrenchRegressionModule.from_checkpoint(v) for k, v in cfg.ckpts.items() if v}
    if not models:
        raise ValueError("no checkpoint given: set ckpts.poke, ckpts.forearm and/or ckpts.combined")
    out_dir = Path(cfg.output_dir)
    needed = sorted({d for name in models for d in TRAINED_ON[name]})
    data = {}
    for d in needed:
        dm = TactileWrenchDataModule(
            list(cfg.shards[d]), val_fraction=cfg.val_fraction, seed=cfg.seed, depth_scale=cfg.depth_scale
        )
        dm.setup("fit")
        data[d] = dm
    results: dict = {"thesis_val_mse": THESIS_VAL_MSE, "models": {}}
    val = {}  # (model, dataset) -> (true, predicted) on the validation split
    full = {}  # (model, dataset) -> (params, true, predicted) on all samples, for the figures
    for name, module in models.items():
        entry = {"checkpoint": str(cfg.ckpts[name]), "val": {}}
        for d in TRAINED_ON[name]:
            val[name, d] = ev.predict_dataset(module, data[d].data_val, device=cfg.device)
            entry["val"][d] = ev.wrench_errors(*val[name, d]).to_dict()
            both = [data[d].data_train, data[d].data_val]
            params = np.concatenate([ev.dataset_params(x) for x in both])
            preds = [ev.predict_dataset(module, x, device=cfg.device) for x in both]
            full[name, d] = (
                params,
                np.concatenate([p[0] for p in preds]),
                np.concatenate([p[1] for p in preds]),
            )
        if len(TRAINED_ON[name]) > 1:
            t = np.concatenate([val[name, d][0] for d in TRAINED_ON[name]])
            p = np.concatenate([val[name, d][1] for d in TRAINED_ON[name]])
            entry["val"]["all"] = ev.wrench_errors(t, p).to_dict()
        results["models"][name] = entry
        log.info("%s: validation MSE %s", name, {k: round(v["mse"], 5) for k, v in entry["val"].items()})

    figures = {}
    for d, plot, name in (
        ("poke", ev.plot_poke_torque_polar, "fig3_4_poke_torque_x.png"),
        ("forearm", ev.plot_forearm_shear, "fig3_7_forearm_shear.png"),
        ("forearm", ev.plot_forearm_twist, "fig3_8_forearm_twist.png"),
    ):
        owners = [m for m in models if d in TRAINED_ON[m]]
        if not owners:
            continue
        params, true, _ = full[owners[0], d]
        try:
            figures[name] = plot(params, true, {f"{m} model": full[m, d][2] for m in owners}, out_dir / name)
        except ValueError as error:  # the dataset lacks the samples this figure shows
            log.warning("skipped %s: %s", name, error)
    results["figures"] = figures
    (out_dir / "wrench_eval.json").write_text(json.dumps(results, indent=2))
    log.info("wrote %s", out_dir / "wrench_eval.json")
    return results


if __name__ == "__main__":
    main()
