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

On ``fit``, if its normalizers are not fitted yet (fresh run), the module measures them on
``trainer.datamodule.statistics_dataloader()`` and records the datamodule's contact radius; both are stored in
the checkpoint (buffers), so a checkpoint alone suffices for :mod:`defgraspnets.models.predictor`.
"""

from __future__ import annotations

import math

import torch
from lightning import LightningModule

from defgraspnets.eval.metrics import FieldMetrics
from defgraspnets.models.graph import DEFAULT_CONTACT_RADIUS, GraspGraph
from defgraspnets.models.meshgraphnet import DefGraspNet

__all__ = ["DefGraspNetsModule"]


class DefGraspNetsModule(LightningModule):
    """Training wrapper of :class:`~defgraspnets.models.meshgraphnet.DefGraspNet`.

    Args:
        latent, num_blocks, hidden_layers, outputs, prediction, num_steps, force_feature, force_on,
            stress_reference, modulus_reference: see :class:`DefGraspNet`.
        stress_weight, displacement_weight: loss weights.
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
        stress_weight: float = 1.0,
        displacement_weight: float = 1.0,
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
        )
        self.register_buffer("contact_radius", torch.tensor(float("nan"), dtype=torch.float64))
        self.metrics = {"val": FieldMetrics(), "test": FieldMetrics()}
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
            self.net.fit_normalizers(dm.statistics_dataloader())
        if self.hparams.compile and stage == "fit" and self._compiled is None:
            object.__setattr__(self, "_compiled", torch.compile(self.net))

    @property
    def network(self) -> DefGraspNet | torch.nn.Module:
        """The network the training step runs: ``net``, or its ``torch.compile`` wrapper after
        ``setup("fit")`` with ``compile=True`` (tested with ``is None``, not truthiness: a compiled module
        proxies ``len()``, which raises TypeError for a DefGraspNet)."""
        return self.net if self._compiled is None else self._compiled

    # -------------------------------------------------------------- steps
    def loss(self, batch: GraspGraph, pred: torch.Tensor | None = None):
        """(total, stress, displacement) MSE of standardized targets over the loss nodes.

        ``pred``: standardized network outputs (n, 4) if already computed.
        """
        if pred is None:
            pred = self.network(batch)
        target = self.net.normalized_targets(batch)
        mask_s, mask_d = self.net.loss_mask(batch)
        stress = (pred[mask_s, 0] - target[mask_s, 0]).square().mean()
        disp = (pred[mask_d, 1:] - target[mask_d, 1:]).square().mean()
        hp = self.hparams
        return hp.stress_weight * stress + hp.displacement_weight * disp, stress, disp

    def training_step(self, batch: GraspGraph, batch_idx: int) -> torch.Tensor:
        total, stress, disp = self.loss(batch)
        b = batch.graph_count
        self.log("train/loss", total, on_step=True, on_epoch=True, prog_bar=True, batch_size=b)
        self.log_dict(
            {"train/loss_stress": stress, "train/loss_displacement": disp}, on_epoch=True, batch_size=b
        )
        return total

    def _eval_step(self, batch: GraspGraph, stage: str) -> None:
        pred = self.net(batch)
        total, stress, disp = self.loss(batch, pred)
        b = batch.graph_count
        self.log(f"{stage}/loss", total, prog_bar=True, batch_size=b, sync_dist=True)
        self.log_dict(
            {f"{stage}/loss_stress": stress, f"{stage}/loss_displacement": disp}, batch_size=b, sync_dist=True
        )
        # fields in Pa and m: one-step reuses the pass above, multi-step rolls out from the rest state
        s, d = (
            self.net.to_physical(pred, batch) if self.net.prediction == "one_step" else self.net.fields(batch)
        )
        self.metrics[stage].update(s, d, batch)

    def _eval_epoch_end(self, stage: str) -> None:
        m = self.metrics[stage]
        m.gather()
        if len(m):
            values = m.compute()
            values.pop("samples", None)
            # identical on every rank after gather(); sync_dist only averages equal values
            self.log_dict({f"{stage}/{k}": float(v) for k, v in values.items()}, sync_dist=True)
        m.reset()

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
        opt = cls(self.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        ratio = hp.lr_final / hp.lr
        epochs = hp.lr_decay_epochs
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: ratio ** (min(e, epochs) / epochs))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    @property
    def contact_radius_m(self) -> float:
        """The contact radius eps [m] the model was trained with (default 5 mm if never set)."""
        r = float(self.contact_radius)
        return DEFAULT_CONTACT_RADIUS if math.isnan(r) else r
