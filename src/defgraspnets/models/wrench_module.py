"""LightningModule training the wrench CNN (thesis §3.4) and mapping depth images to wrenches.

Loss (``target_scaling``): ``"si"`` (default, the thesis's) = mean squared error over the six wrench
components in SI units (N^2 and (N m)^2 mixed, as the thesis reports it: validation MSE 0.03 poking,
0.057 forearm, 0.1 combined). There torques of a few 0.01 N m weigh ~1e-4 of forces of several newtons,
and a twist torque is not learnt (README). ``"standardize"``: the network predicts each component
standardized by the mean and standard deviation of the training split's wrenches (computed at fit
set-up from the datamodule's ``train_wrenches()``, stored in the checkpoint as the buffers
``wrench_mean`` / ``wrench_std``), the loss is the MSE of the standardized components, and the module
still returns SI wrenches. The per-component metrics below are in SI units either way. Optimizer: SGD,
learning rate 0.01 "with no decay"; the thesis does not state a momentum, so the default is plain
SGD (momentum 0, the Keras and PyTorch default), overridable.

Logged metrics (``train/``, ``val/``, ``test/``): ``loss`` (the MSE), ``mse_<component>`` per
component, ``force_rmse`` = sqrt(mean over samples and x, y, z of the squared force error) [N] and
``torque_rmse`` likewise [N m].

Inference: :meth:`WrenchRegressionModule.predict_wrench` takes raw depth images (numpy or torch,
(H, W) or (B, H, W)) with their reference image(s), applies the training normalization
(:func:`defgraspnets.data.tactile_datamodule.normalize_depth`) and returns (6,) or (B, 6) in the
input's type. The reference image of a single-PV-state datamodule is kept in the checkpoint.
"""

from __future__ import annotations

import lightning as L
import numpy as np
import torch
from torch import nn
from torchmetrics import MeanSquaredError

from defgraspnets.data.tactile_datamodule import normalize_depth
from defgraspnets.data.tactile_schema import WRENCH_COMPONENTS

__all__ = ["WrenchRegressionModule"]

_SHORT = ("fx", "fy", "fz", "tx", "ty", "tz")
TARGET_SCALINGS = ("si", "standardize")
_STAGES = ("train", "val", "test")
assert len(_SHORT) == len(WRENCH_COMPONENTS)


class WrenchRegressionModule(L.LightningModule):
    """Train / evaluate / run a depth-image -> wrench network.

    Args:
        net: the network, (B, 1, H, W) -> (B, 6), e.g. :class:`~defgraspnets.models.wrench_cnn.WrenchCNN`.
        lr: SGD learning rate (thesis: 0.01, constant).
        momentum: SGD momentum (not given in the thesis; 0).
        weight_decay: L2 penalty (0).
        depth_scale: input normalization length [m]; must equal the datamodule's.
        target_scaling: ``"si"`` (loss in SI units, thesis) or ``"standardize"`` (module docstring).
    """

    def __init__(
        self,
        net: nn.Module,
        lr: float = 0.01,
        momentum: float = 0.0,
        weight_decay: float = 0.0,
        depth_scale: float = 0.01,
        target_scaling: str = "si",
    ):
        super().__init__()
        if target_scaling not in TARGET_SCALINGS:
            raise ValueError(f"target_scaling must be one of {TARGET_SCALINGS}, got {target_scaling!r}")
        self.save_hyperparameters(logger=False, ignore=["net"])
        self.net = net
        self.loss_fn = nn.MSELoss()
        # wrench = wrench_mean + wrench_std * net(x); identity unless target_scaling="standardize"
        self.register_buffer("wrench_mean", torch.zeros(len(_SHORT)))
        self.register_buffer("wrench_std", torch.ones(len(_SHORT)))
        # keys must not shadow nn.Module attributes ("train"), hence the suffix
        self.metrics = nn.ModuleDict({f"{stage}_mse": MeanSquaredError(num_outputs=6) for stage in _STAGES})
        self.reference_depth: torch.Tensor | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) normalized input -> (B, 6) wrench [N, N m]."""
        return self.wrench_mean + self.wrench_std * self.net(x)

    def wrench_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The training loss of predicted against true wrenches [N, N m]: their MSE in SI units, or of the
        standardized components (``target_scaling="standardize"``)."""
        return self.loss_fn(pred / self.wrench_std, target / self.wrench_std)

    def fit_target_scaling(self, wrenches) -> None:
        """Set ``wrench_mean`` / ``wrench_std`` from (N, 6) training wrenches [N, N m]
        (``target_scaling="standardize"``; a constant component keeps the scale 1)."""
        w = torch.as_tensor(np.asarray(wrenches, dtype=np.float64))
        if w.ndim != 2 or w.shape[1] != len(_SHORT) or len(w) < 2:
            raise ValueError(f"need (N >= 2, 6) training wrenches, got shape {tuple(w.shape)}")
        if not torch.isfinite(w).all():
            raise ValueError("training wrenches contain NaN or inf")
        std = w.std(dim=0)
        std = torch.where(std > 1e-12 * std.max().clamp_min(1e-300), std, torch.ones_like(std))
        self.wrench_mean.copy_(w.mean(dim=0).to(self.wrench_mean))
        self.wrench_std.copy_(std.to(self.wrench_std))

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        # before a resumed checkpoint is restored (which then brings back the same statistics)
        if stage != "fit" or self.hparams.target_scaling != "standardize":
            return
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "train_wrenches"):
            raise ValueError(
                'target_scaling="standardize" needs a datamodule with train_wrenches() '
                "(e.g. TactileWrenchDataModule) to compute the wrench statistics"
            )
        dm.setup("fit")
        self.fit_target_scaling(dm.train_wrenches())

    def on_fit_start(self) -> None:
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None:
            return
        scale = getattr(dm, "depth_scale", None)
        if scale is not None and not np.isclose(scale, self.hparams.depth_scale):
            raise ValueError(
                f"model depth_scale {self.hparams.depth_scale} differs from the datamodule's {scale}: "
                "inference would normalize differently from training"
            )
        ref = getattr(dm, "reference_depth", None)
        if ref is not None:
            self.reference_depth = torch.as_tensor(np.asarray(ref, dtype=np.float32))

    def _step(self, batch, stage: str) -> torch.Tensor:
        x, y = batch
        pred = self(x)
        loss = self.wrench_loss(pred, y)
        self.metrics[f"{stage}_mse"].update(pred.detach(), y)
        self.log(
            f"{stage}/loss", loss, on_step=stage == "train", on_epoch=True, prog_bar=True, batch_size=len(y)
        )
        return loss

    def _log_epoch_metrics(self, stage: str) -> None:
        metric = self.metrics[f"{stage}_mse"]
        if metric.update_count == 0:
            return
        mse = metric.compute()
        for name, value in zip(_SHORT, mse):
            self.log(f"{stage}/mse_{name}", value)
        self.log(f"{stage}/force_rmse", mse[:3].mean().sqrt())
        self.log(f"{stage}/torque_rmse", mse[3:].mean().sqrt())
        metric.reset()

    def training_step(self, batch, batch_idx):
        return self._step(batch, "train")

    def validation_step(self, batch, batch_idx):
        self._step(batch, "val")

    def test_step(self, batch, batch_idx):
        self._step(batch, "test")

    def predict_step(self, batch, batch_idx):
        x = batch[0] if isinstance(batch, list | tuple) else batch
        return self(x)

    def on_train_epoch_end(self) -> None:
        self._log_epoch_metrics("train")

    def on_validation_epoch_end(self) -> None:
        self._log_epoch_metrics("val")

    def on_test_epoch_end(self) -> None:
        self._log_epoch_metrics("test")

    def configure_optimizers(self):
        return torch.optim.SGD(
            self.parameters(),
            lr=self.hparams.lr,
            momentum=self.hparams.momentum,
            weight_decay=self.hparams.weight_decay,
        )

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.reference_depth is not None:
            checkpoint["reference_depth"] = self.reference_depth.cpu()
        if isinstance(getattr(self.net, "config", None), dict):
            checkpoint["net_config"] = dict(self.net.config)

    @classmethod
    def from_checkpoint(cls, path, map_location="cpu") -> WrenchRegressionModule:
        """A trained module ready for :meth:`predict_wrench`, network rebuilt from the checkpoint
        (:class:`~defgraspnets.models.wrench_cnn.WrenchCNN` with its stored constructor arguments)."""
        from pathlib import Path

        from .checkpoints import read_checkpoint
        from .wrench_cnn import WrenchCNN

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"wrench checkpoint not found: {path}")
        checkpoint = read_checkpoint(path, "WrenchRegressionModule", map_location=map_location)
        if "net_config" not in checkpoint:
            raise ValueError(
                f"{path} stores no net_config (saved before it existed): load it with "
                "WrenchRegressionModule.load_from_checkpoint(path, net=WrenchCNN(...same arguments...))"
            )
        module = cls.load_from_checkpoint(
            path, map_location=map_location, net=WrenchCNN(**checkpoint["net_config"])
        )
        return module.eval()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.reference_depth = checkpoint.get("reference_depth")
        state = checkpoint.get("state_dict")
        if state is not None:  # checkpoints saved before the target scaling existed: SI (identity)
            state.setdefault("wrench_mean", torch.zeros(len(_SHORT)))
            state.setdefault("wrench_std", torch.ones(len(_SHORT)))

    # ------------------------------------------------------------------ inference
    def _reference_on(self, device: torch.device) -> torch.Tensor:
        """The stored reference image on ``device``, copied there once (not on every call)."""
        cached = getattr(self, "_reference_cache", None)
        if cached is None or cached[0] is not self.reference_depth or cached[1].device != device:
            ref = torch.as_tensor(self.reference_depth, dtype=torch.float32).to(device)
            self._reference_cache = (self.reference_depth, ref)
        return self._reference_cache[1]

    @torch.inference_mode()
    def predict_wrench(self, depth, reference=None):
        """Wrench [N, N m] for raw depth image(s) [m].

        Args:
            depth: (H, W) or (B, H, W) depth [m], numpy or torch; NaN = no return.
            reference: the undeformed image(s) of the same PV state, (H, W) or (B, H, W); default:
                the reference stored from the training datamodule (kept on the model's device).

        Returns:
            (6,) or (B, 6), numpy if ``depth`` is numpy, else a torch tensor on the model's device.
        """
        as_numpy = not isinstance(depth, torch.Tensor)
        d = torch.as_tensor(np.asarray(depth, dtype=np.float32) if as_numpy else depth, dtype=torch.float32)
        if d.ndim not in (2, 3):
            raise ValueError(f"depth must have shape (H, W) or (B, H, W), got {tuple(d.shape)}")
        if reference is None:
            if self.reference_depth is None:
                raise ValueError(
                    "no reference image: pass reference= (the undeformed depth image of the PV state)"
                )
            ref = self._reference_on(self.device)
        else:
            ref = torch.as_tensor(
                np.asarray(reference, dtype=np.float32)
                if not isinstance(reference, torch.Tensor)
                else reference,
                dtype=torch.float32,
            ).to(self.device)
        if ref.shape[-2:] != d.shape[-2:]:
            raise ValueError(f"reference shape {tuple(ref.shape)} does not match depth {tuple(d.shape)}")
        single = d.ndim == 2
        x = normalize_depth(d.to(self.device, non_blocking=True), ref, self.hparams.depth_scale)
        x = x.reshape(-1, 1, *x.shape[-2:])
        was_training = self.training
        if was_training:
            self.eval()
        try:
            wrench = self(x)
        finally:
            if was_training:
                self.train()
        wrench = wrench[0] if single else wrench
        return wrench.cpu().numpy() if as_numpy else wrench
