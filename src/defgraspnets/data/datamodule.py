"""LightningDataModule of DefGraspNets: grasp shards -> split -> multigraph samples -> PyG batches.

Configured by Hydra (``configs/data/defgraspnets.yaml``); every argument is overridable from the command
line (``data.split=unseen_E data.batch_size=4``). The model pulls normalization statistics from
:meth:`GraspDataModule.statistics_dataloader` (a seeded subset of the training split) in its ``setup``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from lightning import LightningDataModule
from torch.utils.data import Subset
from torch_geometric.loader import DataLoader

from defgraspnets.data.dataset import (
    GraspFieldDataset,
    check_displacement_target,
    discover_shards,
    sample_index,
)
from defgraspnets.data.grasp_schema import GraspShard
from defgraspnets.data.splits import DRAWS, SPLITS, ShardInfo, Split, make_split
from defgraspnets.models.graph import DEFAULT_CONTACT_RADIUS

__all__ = ["GraspDataModule"]

log = logging.getLogger(__name__)


def _as_list(x):
    return None if x is None else [v for v in x]


class GraspDataModule(LightningDataModule):
    """Grasp-field samples of every shard in ``data_dir``, split for one generalization level.

    Args:
        data_dir: directory of ``<object>__shard<i>of<n>.h5`` files.
        split: ``unseen_grasps`` | ``unseen_E`` | ``unseen_objects`` | ``unseen_real`` (thesis §7.6).
        seed: split seed. test_fraction, val_fraction, test_objects, train_objects: see
            :func:`defgraspnets.data.splits.make_split`.
        objects: optional subset of object names to use at all.
        train_steps, eval_steps: ramp step indices used for training / for validation and test
            (``None``: all steps; negative indices count from the end, ``[-1]`` = final force).
        contact_radius: eps [m] of the contact edges (thesis: 5 mm).
        contact_backend: ``kdtree`` | ``torch`` | ``torch_cluster`` | ``auto`` (see ``contact_pairs``).
        ramp_stride: steps between the previous and the target state for multi-step training (ablation V2);
            ``None`` for one-step models.
        displacement: displacement target, ``"total"`` (thesis §7.4) or ``"rigid_removed"`` (the object's
            best rigid motion removed, see :mod:`defgraspnets.data.dataset`); stored in the checkpoint.
        batch_size: graphs per training batch (thesis: 1). eval_batch_size: default ``batch_size``.
        num_workers, pin_memory, persistent_workers: DataLoader options.
        statistics_samples: training samples used for the normalization statistics.
        holdout: ``"axis"`` holds out whole grasp axes (unseen-grasps test part and validation),
            ``"grasp"`` single grasps (the default here, so that checkpoints saved before the key existed
            rebuild their split; the Hydra config defaults to ``axis``). See
            :func:`~defgraspnets.data.splits.make_split`.
        holdout_draw: ``"stable"`` draws held-out units by per-unit keys (a ramp that flips between solved
            and failed in regenerated data moves only itself, so a model can resume on regenerated data),
            ``"permutation"`` by a permutation of the solved units (the default here, so that checkpoints
            saved before the key existed rebuild their split; the Hydra config defaults to ``stable``).
    """

    def __init__(
        self,
        data_dir: str,
        split: str = "unseen_grasps",
        seed: int = 0,
        test_fraction: float | None = None,
        val_fraction: float = 0.1,
        objects: Sequence[str] | None = None,
        test_objects: Sequence[str] | None = None,
        train_objects: Sequence[str] | None = None,
        train_steps: Sequence[int] | None = None,
        eval_steps: Sequence[int] | None = None,
        contact_radius: float = DEFAULT_CONTACT_RADIUS,
        contact_backend: str = "kdtree",
        ramp_stride: int | None = None,
        displacement: str = "total",
        batch_size: int = 1,
        eval_batch_size: int | None = None,
        num_workers: int = 0,
        pin_memory: bool = False,
        persistent_workers: bool = False,
        statistics_samples: int = 512,
        holdout: str = "grasp",
        holdout_draw: str = "permutation",
    ):
        super().__init__()
        if split not in SPLITS:
            raise ValueError(f"data.split={split!r} is not one of {SPLITS}")
        if holdout_draw not in DRAWS:
            raise ValueError(f"data.holdout_draw={holdout_draw!r} is not one of {DRAWS}")
        if batch_size < 1:
            raise ValueError(f"data.batch_size must be >= 1, got {batch_size}")
        if contact_radius <= 0:
            raise ValueError(f"data.contact_radius must be positive [m], got {contact_radius}")
        check_displacement_target(displacement, ramp_stride, prefix="data.")
        self.save_hyperparameters(logger=False)
        self.displacement = displacement
        self.data_dir = Path(data_dir)
        self.split_name = split
        self.contact_radius = float(contact_radius)
        self.ramp_stride = ramp_stride
        self.objects, self.test_objects, self.train_objects = map(
            _as_list, (objects, test_objects, train_objects)
        )
        self.train_steps, self.eval_steps = _as_list(train_steps), _as_list(eval_steps)
        self.shards: list[GraspShard] = []
        self.object_names: list[str] = []
        self.split: Split | None = None
        self.datasets: dict[str, GraspFieldDataset] = {}

    # -------------------------------------------------------------- setup
    def setup(self, stage: str | None = None) -> None:
        if self.split is not None:
            return
        hp = self.hparams
        shards = [GraspShard(p) for p in discover_shards(self.data_dir)]
        if self.objects is not None:
            missing = sorted(set(self.objects) - {s.object.name for s in shards})
            if missing:
                raise ValueError(f"data.objects {missing} have no shard in {self.data_dir}")
            shards = [s for s in shards if s.object.name in self.objects]
        self.shards = shards
        self.object_names = sorted({s.object.name for s in shards})
        object_ids = [self.object_names.index(s.object.name) for s in shards]
        self.split = make_split(
            [ShardInfo.of(s) for s in shards],
            self.split_name,
            hp.seed,
            hp.test_fraction,
            hp.val_fraction,
            self.test_objects,
            self.train_objects,
            hp.holdout,
            hp.holdout_draw,
        )
        # "all": every solved squeeze of the data, whatever the split (scripts/evaluate.py part=all)
        parts = {
            "train": (self.split.train, self.train_steps),
            "val": (self.split.val, self.eval_steps),
            "test": (self.split.test, self.eval_steps),
            "all": (self.split.solved, self.eval_steps),
        }
        for part, (entries, steps) in parts.items():
            samples = sample_index(shards, entries, steps)
            self.datasets[part] = GraspFieldDataset(
                shards,
                samples,
                object_ids,
                self.contact_radius,
                hp.contact_backend,
                self.ramp_stride,
                self.displacement,
            )
        log.info(
            "grasp data %s: %s shards, split %s, samples train/val/test = %d/%d/%d",
            self.data_dir,
            len(shards),
            self.split_name,
            *(len(self.datasets[p]) for p in ("train", "val", "test")),
        )

    def summary(self) -> dict:
        """Split summary plus sample counts (after :meth:`setup`)."""
        if self.split is None:
            raise RuntimeError("call setup() first")
        out = self.split.summary()
        out["samples"] = {p: len(d) for p, d in self.datasets.items()}
        out["data_dir"] = str(self.data_dir)
        return out

    def object_surface(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Rest surface (points (N, 3) [m], faces (F, 3)) of object ``name``."""
        for s in self.shards:
            if s.object.name == name:
                return s.object.points, s.object.surface_faces
        raise KeyError(f"object {name!r} not in the data ({self.object_names})")

    # -------------------------------------------------------------- loaders
    def _loader(self, dataset, batch_size: int, shuffle: bool) -> DataLoader:
        hp = self.hparams
        return DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            num_workers=hp.num_workers,
            pin_memory=hp.pin_memory,
            persistent_workers=hp.persistent_workers and hp.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["train"], self.hparams.batch_size, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(
            self.datasets["val"], self.hparams.eval_batch_size or self.hparams.batch_size, False
        )

    def test_dataloader(self) -> DataLoader:
        return self._loader(
            self.datasets["test"], self.hparams.eval_batch_size or self.hparams.batch_size, False
        )

    def statistics_dataloader(self) -> DataLoader:
        """A seeded subset of ``statistics_samples`` training samples (normalization statistics)."""
        train = self.datasets["train"]
        n = min(len(train), int(self.hparams.statistics_samples))
        idx = np.sort(np.random.default_rng(self.hparams.seed).choice(len(train), n, replace=False))
        return self._loader(Subset(train, idx.tolist()), max(self.hparams.batch_size, 8), shuffle=False)
