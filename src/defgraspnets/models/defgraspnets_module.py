r"""LightningModule training DefGraspNets (thesis §7.4) on grasp-field batches.

Loss over object nodes (standardized targets, see :mod:`defgraspnets.data.normalization`):

    L = w_sigma mean_i (y^sigma_i - yhat^sigma_i)^2 + w_d mean_i 1/3 |y^d_i - yhat^d_i|^2

Optimizer Adam (or AdamW) with the learning rate decaying exponentially per epoch from ``lr`` = 5e-5 to
``lr_final`` = 1e-6 over ``lr_decay_epochs`` = 25 epochs, then constant:
``lr_e = lr (lr_final / lr)^(min(e, epochs) / epochs)``.

Logged: ``train/loss``, ``val/loss``, and on validation/test the metrics of
:class:`~defgraspnets.eval.metrics.FieldMetrics` in physical units: ``mae_stress_pa``, ``mae_stress_kpa``,
``mae_deformation_mm``, ``mae_displacement_mm``, ``tau_s``, ``tau_d`` (grasp rankings by mean stress and
mean deformation within (object, modulus, force step) groups).

``val/loss`` and ``test/loss`` (and their stress / displacement parts) are the loss over the whole split:
squared errors summed over all loss nodes of all samples, divided by the node counts, i.e. independent of
the batch size and of the number of devices (not the mean of per-batch means).

On ``fit``, if its normalizers are not fitted yet (fresh run), the module measures them on
``trainer.datamodule.statistics_dataloader()`` and records the datamodule's contact radius; both are stored in
the checkpoint (buffers), so a checkpoint alone suffices for :mod:`defgraspnets.models.predictor`.

Distributed data parallel (``trainer=ddp``): every rank sees a shard of the validation/test split (Lightning's
DistributedSampler, which pads the last shard with repeated samples). The per-sample summaries of the
metrics and of the loss are gathered from all ranks at the end of the epoch and de-duplicated by sample id,
so ``val/*`` and ``test/*`` are those of the whole split, equal to a single-device evaluation (up to
float32 rounding of the predictions). The normalization statistics are measured on every rank on the same
seeded subset and then broadcast from rank 0 (bit-identical on every rank). Epoch-level training losses are
averaged over ranks; step-level ones are rank 0's (no collective per step).
"""

from __future__ import annotations

import math

import torch
from lightning import LightningModule

from defgraspnets.eval.metrics import FieldMetrics, PerSampleSums
from defgraspnets.models.graph import DEFAULT_CONTACT_RADIUS, GraspGraph
from defgraspnets.models.meshgraphnet import DefGraspNet, graph_mean

__all__ = ["DefGraspNetsModule", "LossSums"]


class LossSums(PerSampleSums):
    """Per-sample sums of the squared standardized errors of an evaluation split, mergeable over DDP ranks.

    Per sample: its id (shard, k, g, s), the squared stress errors summed over the stress-loss nodes, their
    count, the squared displacement errors summed over the displacement-loss nodes and components, their
    count. :meth:`compute` gives the loss of the whole split (sums over samples / counts).
    """

    _KEYS = ("sample", "stress_sq", "stress_n", "disp_sq", "disp_n")

    @torch.no_grad()
    def update(self, module: DefGraspNetsModule, batch: GraspGraph, pred: torch.Tensor) -> None:
        """Add a batch: standardized predictions ``pred`` (n, 4) of ``module.net``."""
        net = module.net
        target = net.normalized_targets(batch)
        mask_s, mask_d = net.loss_mask(batch)
        graph = batch.node_graph()
        b = batch.graph_count

        def per_graph(mask: torch.Tensor, sq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            idx = graph[mask]
            total = torch.zeros(b, dtype=torch.float64, device=sq.device).index_add_(0, idx, sq.double())
            count = torch.zeros(b, dtype=torch.float64, device=sq.device).index_add_(
                0, idx, torch.ones_like(idx, dtype=torch.float64)
            )
            return total, count

        s_sq, s_n = per_graph(mask_s, (pred[mask_s, 0] - target[mask_s, 0]).square())
        d_err = (pred[mask_d, 1:] - target[mask_d, 1:]).square()
        d_sq, d_n = per_graph(mask_d, d_err.sum(1))
        self._append(
            {
                "sample": batch.sample.reshape(b, -1),
                "stress_sq": s_sq,
                "stress_n": s_n,
                "disp_sq": d_sq,
                "disp_n": d_n * d_err.shape[1],
            }
        )

    def compute(self, stress_weight: float = 1.0, displacement_weight: float = 1.0) -> tuple[float, ...]:
        """(total, stress, displacement) loss of everything accumulated."""
        a = self.arrays()
        stress = float(a["stress_sq"].sum() / a["stress_n"].sum())
        disp = float(a["disp_sq"].sum() / a["disp_n"].sum())
        return stress_weight * stress + displacement_weight * disp, stress, disp


class DefGraspNetsModule(LightningModule):
    """Training wrapper of :class:`~defgraspnets.models.meshgraphnet.DefGraspNet`.

    Args:
        latent, num_blocks, hidden_layers, outputs, prediction, num_steps, force_feature, force_on,
            stress_reference, modulus_reference, modulus_saturation: see :class:`DefGraspNet` (checkpoints
            saved without ``modulus_saturation`` load with ``None``, the scaling they were trained with).
        global_context: a graph-level context after every message-passing block
            (:class:`~defgraspnets.models.meshgraphnet.GlobalContext`); off by default (the thesis's network).
        stress_weight, displacement_weight: loss weights.
        graph_mean_weight: weight of a third loss term, the MSE over graphs of each graph's mean
            standardized stress and mean standardized displacement magnitude (its loss nodes). The node
            MSE lets errors of either sign cancel in a graph's mean, and the mean fields are what grasps
            are ranked by (Kendall tau) and planned with; 0 (default) is the thesis's loss. Validation and
            test losses stay the node MSE, so checkpoints are selected alike. Measured at weight 1 on 18
            objects it hurt (test tau_s 0.62 -> 0.55, stress MAE 1.10 -> 1.68 kPa;
            ``benchmarks/defgraspnets_fit_h100.md``); an ablation, not a recommendation.
        optimizer: ``"adam"`` or ``"adamw"``. lr, lr_final, lr_decay_epochs: exponential decay.
        weight_decay: optimizer weight decay.
        compile: wrap the network in ``torch.compile`` for training.
    """

    def __init__(
        self,
        latent: int = 128,
        num_blocks: int = 15,
        hidden_layers: int = 2,
        outputs: str = "joint",
        prediction: str = "one_step",
        num_steps: int = 5,
        force_feature: str = "distributed",
        force_on: str = "contact_edges",
        stress_reference: float = 1e3,
        modulus_reference: float = 1e6,
        modulus_saturation: float | None = None,
        global_context: bool = False,
        stress_weight: float = 1.0,
        displacement_weight: float = 1.0,
        graph_mean_weight: float = 0.0,
        optimizer: str = "adam",
        lr: float = 5e-5,
        lr_final: float = 1e-6,
        lr_decay_epochs: int = 25,
        weight_decay: float = 0.0,
        compile: bool = False,
    ):
        super().__init__()
        if optimizer not in ("adam", "adamw"):
            raise ValueError(f"model.optimizer must be 'adam' or 'adamw', got {optimizer!r}")
        if not graph_mean_weight >= 0:
            raise ValueError(f"model.graph_mean_weight must be >= 0, got {graph_mean_weight!r}")
        if not (lr > 0 and lr_final > 0 and lr_decay_epochs >= 1):
            raise ValueError("model.lr and model.lr_final must be positive and model.lr_decay_epochs >= 1")
        self.save_hyperparameters(logger=True)
        self.net = DefGraspNet(
            latent,
            num_blocks,
            hidden_layers,
            outputs,
            prediction,
            num_steps,
            force_feature,
            force_on,
            stress_reference,
            modulus_reference,
            modulus_saturation,
            global_context,
        )
        self.register_buffer("contact_radius", torch.tensor(float("nan"), dtype=torch.float64))
        # displacement target of the training data (data.displacement), saved in the checkpoint; None: not set
        self._displacement_target: str | None = None
        self.metrics = {"val": FieldMetrics(), "test": FieldMetrics()}
        self.loss_sums = {"val": LossSums(), "test": LossSums()}
        object.__setattr__(
            self, "_compiled", None
        )  # not a registered submodule: no duplicate state_dict keys

    # -------------------------------------------------------------- setup
    def setup(self, stage: str) -> None:
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if dm is not None:
            radius = getattr(dm, "contact_radius", None)
            if radius is not None:
                if math.isnan(float(self.contact_radius)):
                    self.contact_radius.fill_(float(radius))
                elif abs(float(self.contact_radius) - radius) > 1e-12:
                    raise ValueError(
                        f"data.contact_radius={radius} differs from the model's {float(self.contact_radius)}"
                    )
            target = getattr(dm, "displacement", None)
            if target is not None:
                self.use_displacement_target(str(target))
            if self.hparams.prediction == "multi_step" and getattr(dm, "ramp_stride", None) is None:
                raise ValueError(
                    "model.prediction=multi_step needs data.ramp_stride (steps between the previous "
                    "and the predicted ramp state), e.g. data.ramp_stride=10"
                )
        if stage == "fit" and not self.net.normalized:
            if dm is None or not hasattr(dm, "statistics_dataloader"):
                raise RuntimeError(
                    "normalization statistics are missing: fit with a datamodule that provides "
                    "statistics_dataloader() or call net.fit_normalizers() first"
                )
            dm.setup("fit")
            self.net.fit_normalizers(dm.statistics_dataloader(), progress=self.trainer.is_global_zero)
            self._broadcast_normalizers()
        if self.hparams.compile and stage == "fit" and self._compiled is None:
            object.__setattr__(self, "_compiled", torch.compile(self.net))

    def _broadcast_normalizers(self) -> None:
        """DDP: make every rank use rank 0's normalization statistics (bit-identical buffers)."""
        if self._trainer is None or self.trainer.world_size <= 1:
            return
        names = [n for n, _ in self.net.named_buffers() if "norm." in n]
        state = {n: b.detach().cpu() for n, b in self.net.named_buffers() if n in names}
        state = self.trainer.strategy.broadcast(state, src=0)
        for n, b in self.net.named_buffers():
            if n in state:
                b.copy_(state[n].to(b))

    @property
    def network(self) -> DefGraspNet | torch.nn.Module:
        """The network the training step runs: ``net``, or its ``torch.compile`` wrapper after
        ``setup("fit")`` with ``compile=True`` (tested with ``is None``, not truthiness: a compiled module
        proxies ``len()``, which raises TypeError for a DefGraspNet)."""
        return self.net if self._compiled is None else self._compiled

    # -------------------------------------------------------------- steps
    def loss(self, batch: GraspGraph, pred: torch.Tensor | None = None):
        """(total, stress, displacement) MSE of standardized targets over the loss nodes; the total adds
        ``graph_mean_weight`` times :meth:`graph_mean_loss`.

        ``pred``: standardized network outputs (n, 4) if already computed.
        """
        if pred is None:
            pred = self.network(batch)
        target = self.net.normalized_targets(batch)
        mask_s, mask_d = self.net.loss_mask(batch)
        stress = (pred[mask_s, 0] - target[mask_s, 0]).square().mean()
        disp = (pred[mask_d, 1:] - target[mask_d, 1:]).square().mean()
        hp = self.hparams
        total = hp.stress_weight * stress + hp.displacement_weight * disp
        if hp.graph_mean_weight > 0:
            masks = (mask_s, mask_d)
            total = total + hp.graph_mean_weight * self.graph_mean_loss(batch, pred, target, masks)
        return total, stress, disp

    def graph_mean_loss(
        self,
        batch: GraspGraph,
        pred: torch.Tensor,
        target: torch.Tensor,
        masks: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """MSE over graphs of the mean standardized stress plus that of the mean standardized displacement
        magnitude, each mean over the graph's loss nodes (``pred``, ``target`` (n, 4) standardized;
        ``masks``: the stress and displacement loss masks if already computed)."""
        mask_s, mask_d = masks if masks is not None else self.net.loss_mask(batch)
        graph, b = batch.node_graph(), batch.graph_count

        def means(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            # per-graph means over the masked nodes, for the graphs that have any
            mean, count = graph_mean(values, graph[mask], b)
            return mean[count > 0]

        stress = means(pred[mask_s, 0], mask_s) - means(target[mask_s, 0], mask_s)
        disp = means(pred[mask_d, 1:].norm(dim=1), mask_d) - means(target[mask_d, 1:].norm(dim=1), mask_d)
        return stress.square().mean() + disp.square().mean()

    def training_step(self, batch: GraspGraph, batch_idx: int) -> torch.Tensor:
        total, stress, disp = self.loss(batch)
        b = batch.graph_count
        values = {"train/loss": total, "train/loss_stress": stress, "train/loss_displacement": disp}
        # step values: this rank's (no collective per step); epoch values: averaged over ranks
        for name, value in values.items():
            bar = name == "train/loss"
            self.log(f"{name}_step", value, on_step=True, on_epoch=False, prog_bar=bar, batch_size=b)
            self.log(f"{name}_epoch", value, on_step=False, on_epoch=True, batch_size=b, sync_dist=True)
        return total

    def _eval_step(self, batch: GraspGraph, stage: str) -> None:
        pred = self.net(batch)
        self.loss_sums[stage].update(self, batch, pred)
        # fields in Pa and m: one-step reuses the pass above, multi-step rolls out from the rest state
        s, d = (
            self.net.to_physical(pred, batch) if self.net.prediction == "one_step" else self.net.fields(batch)
        )
        self.metrics[stage].update(s, d, batch)

    def _eval_epoch_end(self, stage: str) -> None:
        m, sums = self.metrics[stage], self.loss_sums[stage]
        m.gather()
        sums.gather()
        values = {}
        if len(sums):
            total, stress, disp = sums.compute(self.hparams.stress_weight, self.hparams.displacement_weight)
            values.update({"loss": total, "loss_stress": stress, "loss_displacement": disp})
        if len(m):
            metrics = m.compute()
            metrics.pop("samples", None)
            values.update(metrics)
        if values:
            # identical on every rank after gather(); sync_dist only averages equal values
            loss = values.pop("loss", None)
            if loss is not None:
                self.log(f"{stage}/loss", float(loss), prog_bar=True, sync_dist=True)
            self.log_dict({f"{stage}/{k}": float(v) for k, v in values.items()}, sync_dist=True)
        m.reset()
        sums.reset()

    def validation_step(self, batch: GraspGraph, batch_idx: int) -> None:
        self._eval_step(batch, "val")

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val")

    def test_step(self, batch: GraspGraph, batch_idx: int) -> None:
        self._eval_step(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test")

    def forward(self, batch: GraspGraph) -> tuple[torch.Tensor, torch.Tensor]:
        """Von Mises stress (n,) [Pa] and displacement (n, 3) [m] of every node of ``batch``."""
        return self.net.fields(batch)

    # -------------------------------------------------------------- optimization
    def configure_optimizers(self):
        hp = self.hparams
        cls = torch.optim.AdamW if hp.optimizer == "adamw" else torch.optim.Adam
        params = list(self.parameters())
        # on CUDA the fused implementation: one kernel for all parameters (Lightning moves the module to the
        # device before it asks for the optimizers)
        fused = bool(params) and all(p.is_cuda for p in params)
        opt = cls(params, lr=hp.lr, weight_decay=hp.weight_decay, fused=fused or None)
        ratio = hp.lr_final / hp.lr
        epochs = hp.lr_decay_epochs
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: ratio ** (min(e, epochs) / epochs))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    @property
    def displacement_target(self) -> str:
        """What the predicted displacement is: ``"total"`` (each vertex's position change, thesis §7.4; also
        every checkpoint saved before the choice existed) or ``"rigid_removed"`` (the object's best rigid
        motion removed, in its co-moving frame; see :mod:`defgraspnets.data.dataset`)."""
        return self._displacement_target or "total"

    def use_displacement_target(self, target: str) -> None:
        """Take the data's displacement target (``data.displacement``) if the model has none yet, else
        require the same one (resuming, testing or evaluating a checkpoint on data of another target)."""
        if self._displacement_target is None:
            self._displacement_target = target
        elif self._displacement_target != target:
            raise ValueError(
                f"data.displacement={target} differs from the {self._displacement_target!r} displacement "
                "target of the model"
            )

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["displacement_target"] = self.displacement_target

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # resuming (train.py ckpt_path=...): setup() has already taken the datamodule's target
        data_target, self._displacement_target = self._displacement_target, None
        self.use_displacement_target(checkpoint.get("displacement_target", "total"))
        if data_target is not None:
            self.use_displacement_target(data_target)

    @property
    def contact_radius_m(self) -> float:
        """The contact radius eps [m] the model was trained with (default 5 mm if never set)."""
        r = float(self.contact_radius)
        return DEFAULT_CONTACT_RADIUS if math.isnan(r) else r
