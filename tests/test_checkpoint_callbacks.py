"""The shipped callback config keeps two checkpoints: the best epoch by val/loss and the latest epoch
(last.ckpt, what `train.py ckpt_path=...` resumes from), also when the validation loss stops improving."""

from __future__ import annotations

import os
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]


class WorseningModel(L.LightningModule):
    """A tiny regression whose logged val/loss grows every epoch: the best epoch is the first."""

    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        x, y = batch
        return torch.nn.functional.mse_loss(self.layer(x), y)

    def validation_step(self, batch, batch_idx):
        self.log("val/loss", float(self.current_epoch + 1))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def _loader():
    x = torch.randn(8, 2)
    data = torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True))
    return torch.utils.data.DataLoader(data, batch_size=4)


def _callbacks(output_dir: Path):
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train.yaml", overrides=[f"paths.output_dir={output_dir}"])
    # the checkpoint callbacks of the default set (lr_monitor needs a logger, model_summary prints)
    return [hydra.utils.instantiate(cfg.callbacks[k]) for k in ("model_checkpoint", "last_checkpoint")]


def _fit(tmp_path: Path, epochs: int, ckpt_path: str | None = None) -> None:
    trainer = L.Trainer(
        max_epochs=epochs,
        callbacks=_callbacks(tmp_path),
        logger=False,
        enable_progress_bar=False,
        accelerator="cpu",
    )
    trainer.fit(WorseningModel(), _loader(), _loader(), ckpt_path=ckpt_path)


def test_last_checkpoint_is_the_latest_epoch_when_validation_worsens(tmp_path):
    _fit(tmp_path, epochs=3)
    ckpts = tmp_path / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir()) == ["epoch_000.ckpt", "last.ckpt"]
    assert torch.load(ckpts / "last.ckpt", weights_only=False)["epoch"] == 2
    assert torch.load(ckpts / "epoch_000.ckpt", weights_only=False)["epoch"] == 0


def test_resume_from_last_continues_after_the_latest_epoch(tmp_path):
    _fit(tmp_path, epochs=2)
    _fit(tmp_path, epochs=4, ckpt_path=str(tmp_path / "checkpoints" / "last.ckpt"))
    last = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["epoch"] == 3 and last["global_step"] == 4 * 2  # 2 batches per epoch, no epoch repeated
