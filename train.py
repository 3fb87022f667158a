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

Several processes (``trainer=ddp``):
- one node, ``python train.py ... trainer=ddp``: Lightning starts ranks 1..N-1 by re-running this command
  with ``hydra.run.dir=<rank 0's run dir> hydra.output_subdir=null``, so all ranks share one run directory
  (and its log file) and only rank 0 writes the config, checkpoints and logs.
- ``srun`` (SLURM) or ``torchrun`` start every rank themselves; each would resolve ``${now:...}`` of the run
  directory on its own. Unless ``hydra.run.dir`` is given, it is pinned to
  ``logs/<task_name>/runs/slurm_<job>_<step>`` (``torchrun_<run id>``) so that every rank agrees.
- a Hydra multirun (``-m``) cannot use Lightning's re-launching (each rank would re-run the whole sweep):
  ``-m`` with a DDP trainer that launches its own processes is refused; sweep DDP jobs through
  hydra-submitit-launcher (each job is a SLURM job whose tasks are the ranks) or run them one by one.
- testing runs on all ranks too: the metrics gather every rank's per-sample summaries and drop the samples
  that the DistributedSampler repeats, so ``test/*`` are those of the whole test split.
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


def pin_run_dir_for_external_launch(argv: list[str]) -> None:
    """Give the ranks that srun / torchrun start one Hydra run directory (appends ``hydra.run.dir``)."""
    if any(a in ("-m", "--multirun") or a.lstrip("+").startswith("hydra.run.dir=") for a in argv[1:]):
        return
    env = os.environ
    run = None
    if int(env.get("SLURM_NTASKS", "1") or 1) > 1 and env.get("SLURM_JOB_ID"):
        run = f"slurm_{env['SLURM_JOB_ID']}_{env.get('SLURM_STEP_ID', '0')}"
    elif env.get("TORCHELASTIC_RUN_ID", "none") != "none":
        run = f"torchrun_{env['TORCHELASTIC_RUN_ID']}"
    if run:
        argv.append(f"hydra.run.dir=${{paths.log_dir}}/${{task_name}}/runs/{run}")


def check_launch(trainer) -> None:
    """Refuse a Hydra multirun whose trainer would re-launch this script for its other ranks."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if trainer.world_size <= 1 or not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return
    if not trainer.strategy.cluster_environment.creates_processes_externally:
        raise ValueError(
            "a Hydra multirun (-m) cannot use a multi-process trainer that launches its own processes "
            f"(strategy {type(trainer.strategy).__name__}, {trainer.world_size} processes): Lightning would "
            "re-run the whole sweep in every rank. Run the DDP jobs one at a time, or sweep with "
            "hydra-submitit-launcher (hydra/launcher=submitit_slurm, one SLURM task per GPU)."
        )


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
    if cfg.get("ckpt_path"):  # missing, truncated or the other model's checkpoint: named before any work
        from defgraspnets.models.checkpoints import check_checkpoint_for

        if not Path(cfg.ckpt_path).exists():
            raise FileNotFoundError(f"ckpt_path not found: {cfg.ckpt_path}")
        check_checkpoint_for(cfg.ckpt_path, cfg.model._target_)
    log.info("instantiating datamodule <%s>", cfg.data._target_)
    datamodule = hydra.utils.instantiate(cfg.data)
    log.info("instantiating model <%s>", cfg.model._target_)
    model = hydra.utils.instantiate(cfg.model)
    callbacks = instantiate_group(cfg.get("callbacks"), "callback")
    loggers = instantiate_group(cfg.get("logger"), "logger")
    log.info("instantiating trainer <%s>", cfg.trainer._target_)
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    check_launch(trainer)
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
    import sys

    pin_run_dir_for_external_launch(sys.argv)
    main()
