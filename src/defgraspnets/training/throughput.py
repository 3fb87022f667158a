"""Training throughput in graphs per second, summed over all DDP ranks (``callbacks=[default,throughput]``).

Per training epoch, on every rank: the graphs of the batches after the first ``warmup_steps`` batches and the
wall time from the end of batch ``warmup_steps`` to the end of the last batch (validation excluded; the data
loading, forward, backward, gradient all-reduce and optimizer step included). At the end of the epoch the
counts and times of all ranks are gathered and

    train/graphs_per_sec            = sum_r graphs_r / max_r time_r        (the whole job)
    train/graphs_per_sec_per_device = train/graphs_per_sec / world_size
    train/throughput_graphs         = sum_r graphs_r                       (graphs measured)

are logged (epoch level) to every logger. On CUDA the device is synchronized at the two ends of the timed
window only, so the timing covers the queued GPU work without a sync per step.

Lightning's ``ThroughputMonitor`` does not fit: it multiplies rank 0's rate by the world size instead of
summing the ranks, needs a rolling window of ``window_size`` (default 100) steps, and logs per step.
"""

from __future__ import annotations

import logging
import time

import torch
from lightning import Callback, LightningModule, Trainer

__all__ = ["GraphThroughput", "graph_count"]

log = logging.getLogger(__name__)


def graph_count(batch) -> int:
    """Graphs in a batch: ``graph_count`` (GraspGraph), ``num_graphs`` (PyG Batch), else its length."""
    for name in ("graph_count", "num_graphs"):
        n = getattr(batch, name, None)
        if n is not None:
            return int(n)
    if isinstance(batch, (list, tuple)):
        batch = batch[0]
    return int(len(batch))


class GraphThroughput(Callback):
    """Log training graphs/s summed over ranks, once per training epoch.

    Args:
        warmup_steps: batches of each epoch left out of the measurement (data-loader start, allocator,
            ``torch.compile``, cuDNN autotuning). An epoch of at most ``warmup_steps`` batches logs nothing.
        prefix: metric name prefix.
    """

    def __init__(self, warmup_steps: int = 5, prefix: str = "train/"):
        super().__init__()
        if warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
        self.warmup_steps = int(warmup_steps)
        self.prefix = prefix
        self._reset()

    def _reset(self) -> None:
        self._batches = 0
        self._graphs = 0
        self._t0: float | None = None
        self._t1: float | None = None

    @staticmethod
    def _sync(pl_module: LightningModule) -> None:
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)

    def on_train_epoch_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._reset()
        if self.warmup_steps == 0:
            self._sync(pl_module)
            self._t0 = time.perf_counter()

    def on_train_batch_end(
        self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int
    ) -> None:
        self._batches += 1
        if self._batches == self.warmup_steps:
            self._sync(pl_module)
            self._t0 = time.perf_counter()
            return
        if self._batches < self.warmup_steps:
            return
        self._graphs += graph_count(batch)
        last = batch_idx + 1 >= trainer.num_training_batches
        if last:
            self._sync(pl_module)
        self._t1 = time.perf_counter()

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        measured = self._t0 is not None and self._t1 is not None and self._graphs > 0
        elapsed = (self._t1 - self._t0) if measured else 0.0
        local = torch.tensor([float(self._graphs), elapsed, float(measured)], dtype=torch.float64)
        everyone = trainer.strategy.all_gather(local.to(pl_module.device)).reshape(-1, 3).cpu()
        if not bool(everyone[:, 2].all()):
            if trainer.is_global_zero:
                log.warning(
                    "throughput not measured in epoch %d: it has no batch after the %d warm-up batches",
                    trainer.current_epoch,
                    self.warmup_steps,
                )
            return
        graphs = float(everyone[:, 0].sum())
        rate = graphs / float(everyone[:, 1].max())
        world = everyone.shape[0]
        # the same values on every rank; sync_dist only averages equal numbers
        pl_module.log_dict(
            {
                f"{self.prefix}graphs_per_sec": rate,
                f"{self.prefix}graphs_per_sec_per_device": rate / world,
                f"{self.prefix}throughput_graphs": graphs,
            },
            on_step=False,
            on_epoch=True,
            sync_dist=True,
        )
