"""Train and test a model with Lightning, configured by Hydra (``configs/train.yaml``).

    python train.py experiment=defgraspnets                          # fit, test the best checkpoint
    python train.py experiment=defgraspnets data.split=unseen_E model.latent=64 trainer.max_epochs=3
    python train.py experiment=defgraspnets trainer=gpu              # or trainer=ddp [trainer.num_nodes=N]
    python train.py experiment=defgraspnets ckpt_path=logs/.../checkpoints/last.ckpt   # resume
    python train.py experiment=defgraspnets train=false ckpt_path=...                 # test only
    python train.py -m experiment=defgraspnets hparams_search=defgraspnets_grid       # sweep

The script is generic: it instantiates ``cfg.data`` (a LightningDataModule), ``cfg.model`` (a
LightningModule), ``cfg.callbacks``, ``cfg.logger`` and ``cfg.trainer`` from their ``_target_``, so a new
model only needs ``configs/model/<name>.yaml``, ``configs/data/<name>.yaml`` and
``configs/experiment/<name>.yaml``.
Outputs (config, checkpoints, CSV and W&B logs) go to Hydra's run directory, ``logs/<task_name>/runs/<time>``.
W&B runs offline unless ``WANDB_MODE`` is set otherwise. Unknown config keys are rejected (struct mode).
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parent))
os.environ.setdefault("WANDB_MODE", "offline")

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("train")


def instantiate_group(cfg: DictConfig | None, what: str) -> list:
    """Instantiate every entry of a config group of named objects (callbacks, loggers)."""
    out = []
    if not cfg:
        return out
    if not isinstance(cfg, DictConfig):
        raise TypeError(f"the {what} config must be a mapping of named {what}s, got {type(cfg).__name__}")
    for name, conf in cfg.items():
        if not isinstance(conf, DictConfig) or "_target_" not in conf:
            raise ValueError(f"{what} {name!r} has no _target_ (got {conf!r})")
        log.info("instantiating %s %s <%s>", what, name, conf._target_)
        out.append(hydra.utils.instantiate(conf))
    return out


def apply_extras(cfg: DictConfig) -> None:
    extras = cfg.get("extras") or {}
    if extras.get("ignore_warnings"):
        warnings.filterwarnings("ignore")
    if extras.get("print_config"):
        log.info("resolved config:\n%s", OmegaConf.to_yaml(cfg, resolve=True))


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit and/or test; returns the collected metrics (``val/*`` of the last epoch, ``test/*``)."""
    import lightning as L

    L.seed_everything(cfg.seed, workers=True)
    if cfg.get("ckpt_path") and not Path(cfg.ckpt_path).exists():
        raise FileNotFoundError(f"ckpt_path not found: {cfg.ckpt_path}")
    log.info("instantiating datamodule <%s>", cfg.data._target_)
    datamodule = hydra.utils.instantiate(cfg.data)
    log.info("instantiating model <%s>", cfg.model._target_)
    model = hydra.utils.instantiate(cfg.model)
    callbacks = instantiate_group(cfg.get("callbacks"), "callback")
    loggers = instantiate_group(cfg.get("logger"), "logger")
    log.info("instantiating trainer <%s>", cfg.trainer._target_)
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    for lg in loggers:
        lg.log_hyperparams({"config": OmegaConf.to_container(cfg, resolve=True)})

    metrics: dict[str, float] = {}
    if cfg.get("train"):
        log.info("fitting")
        trainer.fit(model=model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items()})
    if cfg.get("test"):
        if cfg.get("train"):
            ckpt = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
            if not ckpt:
                log.warning("no best checkpoint found: testing the current weights")
        else:
            ckpt = cfg.get("ckpt_path") or ""
            if not ckpt:
                log.warning("test without training and without ckpt_path: testing untrained weights")
        log.info("testing %s", ckpt or "current weights")
        trainer.test(model=model, datamodule=datamodule, ckpt_path=ckpt or None)
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
    if trainer.checkpoint_callback is not None and trainer.checkpoint_callback.best_model_path:
        log.info("best checkpoint: %s", trainer.checkpoint_callback.best_model_path)
    return metrics


def close_loggers() -> None:
    """Finish the W&B run (needed between multirun jobs)."""
    try:
        import wandb
    except ImportError:
        return
    if wandb.run is not None:
        wandb.finish()


@hydra.main(version_base="1.3", config_path="configs", config_name="train.yaml")
def main(cfg: DictConfig) -> float | None:
    apply_extras(cfg)
    try:
        metrics = train(cfg)
    finally:
        close_loggers()
    name = cfg.get("optimized_metric")
    if not name:
        return None
    if name not in metrics:
        raise KeyError(f"optimized_metric {name!r} was not logged; logged metrics: {sorted(metrics)}")
    return metrics[name]


if __name__ == "__main__":
    main()
