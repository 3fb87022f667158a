"""Depth image -> wrench datasets and the LightningDataModule of the wrench CNN (thesis §3.4).

Input normalization (one function, :func:`normalize_depth`, shared with inference in
:mod:`defgraspnets.models.wrench_module`): the network sees the *depth change* against the sample's
undeformed reference image (same PV state, no contact), in units of ``depth_scale``:

    x = (z - z_ref) / depth_scale,     x = 0 where z or z_ref is NaN (no return: no information),

so the input is zero without contact and negative where an indenter pushes the membrane towards the
camera (z < z_ref), and it does not depend on the camera geometry or on the PV state's inflated
shape. ``depth_scale = 0.01 m`` makes the
thesis's 0.5-2.5 cm indentations O(1). Targets are the wrenches in SI units (N, N m), unnormalized,
as in the thesis ("All force-torque values are recorded in SI units"; the MSE it reports is in SI).

Split (thesis: "An 80:20 train/test split", :func:`split_tactile_shards`): the split is made over
*nominal grid states*, never over single readings. The repeated forearm experiment
(:mod:`defgraspnets.tactile.datasets`) reads every grid state i once per repeat k, as sample id
``i + k n`` (n: the grid size), on a slightly re-placed forearm: the repeats of one state are
near-duplicates (same command, nearly the same image and wrench). Split row by row, almost every
validation reading would have a twin of its state in the training set (with 5 repeats, all but
0.2^4 = 0.16 % of them), so the validation error would measure recall of seen states, not
generalization to unseen ones, and would not be the thesis's held-out number. All readings of a state
therefore go to the same side, 80:20 by states. Since ``select_paths`` interleaves the repeated grid
over the shard files, the repeats of a state lie in different files, so the grouping spans files:

* An experiment (``attrs["experiment"]``) with repeats in any loaded shard (a finite ``repeat`` param
  > 0) is split as one block: its readings are grouped by nominal state id
  ``sample_id - repeat * n`` (:func:`nominal_state_ids`), and the sorted state ids are permuted by a
  generator seeded by ``(seed, crc32(experiment))`` (:func:`split_groups`). The split of a state does
  not depend on which file holds its readings, nor on the order the shards are listed.
* An experiment without repeats (``repeat`` NaN or 0 everywhere: poking, version 1 files, a forearm
  grid generated once) has one reading per state, so grouping changes nothing; every shard file is
  split on its own, exactly as before repeats existed (:func:`split_indices`, a permutation of its
  rows seeded by ``(seed, crc32(file name))``), and the split of a shard does not depend on which
  other shards are loaded (save for the twins below).

Identical commands under different ids (:func:`commanded_state_keys`). Two grid ids can command the
same indenter state: in the forearm grid the twist psi = +0 and -0 (``sign * pi n / 24``, n = 0, both
senses) at each of the 9 depths are the same pure press, ids ``1800 + 18 m`` and ``1809 + 18 m``
(m = 0..8; both are read, one after the other, in the direction-0 shear path of that depth, and their
repeats share that path's perturbation), so 9 pairs; in the poke grid the pole poke (rho = 0,
theta = 0: contact at the pole, pushed along -z) is the same for all 40 phi, at each of the 5 depths,
so 5 classes of 40 ids. No shear has distance 0. Such twins are a reading and its copy; on both sides
of the split they would leak as the repeats would. Every reading therefore also gets a canonical key
of its commanded state, computed from its command params and rounded to :data:`COMMAND_TOLERANCE`, and
all readings of one key take the side of the key's *representative*: its reading with the smallest
state id (nominal id with repeats, sample id without; ties by file path, then row). The base split
above is unchanged, so data without such twins split exactly as before, and so do the representatives;
only the other twins move, to their representative's side (the 80:20 proportion then holds up to the
moved twins). Without repeats a twin in another shard file (the 40 pole pokes lie in different
files) follows a representative that may lie in another file, so there the split of these rows, and
only of these, depends on which shards of the experiment are loaded.

Sample ids count within an experiment's grid (poke id 5 and forearm id 5 are different states), so
states are grouped per experiment and never across them: the combined dataset's validation set is
exactly the union of the poking and forearm validation sets (given the same shard files), and the
three models of §3.4 are compared on the same samples. The test set is the validation split (the
thesis has no third split).
"""

from __future__ import annotations

import glob
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import ConcatDataset, DataLoader, Dataset

from defgraspnets.data.splits import named_rng
from defgraspnets.data.tactile_schema import (
    COMMAND_PARAM_NAMES,
    PARAM_NAMES,
    TactileShard,
    read_tactile_shard,
)

__all__ = [
    "COMMAND_TOLERANCE",
    "TactileWrenchDataModule",
    "TactileWrenchDataset",
    "commanded_state_keys",
    "grid_size",
    "has_repeats",
    "nominal_state_ids",
    "normalize_depth",
    "split_groups",
    "split_indices",
    "split_tactile_shards",
]

_REPEAT = PARAM_NAMES.index("repeat")
_P = {name: PARAM_NAMES.index(name) for name in COMMAND_PARAM_NAMES}

#: Step [m, rad, unit-vector components] to which :func:`commanded_state_keys` rounds the canonical
#: coordinates of a command: commands that agree to it are one state (grid values differ by >= 1e-3).
COMMAND_TOLERANCE = 1e-9


def normalize_depth(depth, reference, depth_scale: float):
    """Network input ``(z - z_ref) / depth_scale`` with NaN -> 0 (numpy or torch, any matching shape)."""
    if depth_scale <= 0 or not np.isfinite(depth_scale):
        raise ValueError(f"depth_scale must be a finite length > 0 m, got {depth_scale!r}")
    if isinstance(depth, torch.Tensor):
        reference = torch.as_tensor(reference, dtype=depth.dtype, device=depth.device)
        return torch.nan_to_num((depth - reference) / depth_scale, nan=0.0)
    x = (np.asarray(depth, dtype=np.float32) - np.asarray(reference, dtype=np.float32)) / np.float32(
        depth_scale
    )
    return np.nan_to_num(x, nan=0.0)


def split_indices(n: int, val_fraction: float, seed: int, key: str) -> tuple[np.ndarray, np.ndarray]:
    """Seeded (train, val) index split of ``n`` samples; ``key`` (e.g. the file name) decorrelates shards."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction!r}")
    perm = named_rng(seed, key).permutation(n)
    n_val = int(round(val_fraction * n))
    if n - n_val < 1:
        raise ValueError(f"{key}: {n} samples leave no training data at val_fraction={val_fraction}")
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def split_groups(groups, val_fraction: float, seed: int, key: str) -> tuple[np.ndarray, np.ndarray]:
    """Seeded (train, val) row split that keeps every group on one side.

    ``groups`` (N,) labels each row (e.g. its nominal grid state); the sorted distinct labels are split
    by :func:`split_indices` (``round(val_fraction * groups)`` of them to validation) and every row
    follows its label, so the proportion holds by groups (by rows only on average). With distinct,
    increasing labels (one row per group, rows in label order) this is exactly ``split_indices(N)``.
    """
    labels, inverse = np.unique(np.asarray(groups), return_inverse=True)
    _, val = split_indices(len(labels), val_fraction, seed, key)
    is_val = np.zeros(len(labels), dtype=bool)
    is_val[val] = True
    rows = is_val[inverse.ravel()]
    return np.flatnonzero(~rows), np.flatnonzero(rows)


def grid_size(experiment: str) -> int:
    """Number of states of an experiment's grid: the ``n`` of repeat ids ``i + k n``
    (:mod:`defgraspnets.tactile.datasets`; only the forearm experiment repeats)."""
    if experiment == "forearm":
        from defgraspnets.tactile.indenters import forearm_grid  # lazy: pulls in the FEM modules

        return len(forearm_grid())
    raise ValueError(f"experiment {experiment!r} has no repeated grid (only 'forearm' repeats)")


def has_repeats(shard: TactileShard) -> bool:
    """Whether a shard holds readings of a repeat k >= 1 (``repeat`` NaN = not recorded = nominal)."""
    repeat = shard.samples.params[:, _REPEAT]
    return bool(np.any(np.isfinite(repeat) & (repeat > 0)))


def nominal_state_ids(shard: TactileShard, n: int) -> np.ndarray:
    """(N,) the grid state i of every reading: ``sample_id - repeat * n`` (repeat NaN counts as 0).

    Raises:
        ValueError: a repeat is not an integer >= 0, or a sample id does not lie in its repeat's id
            range ``[k n, (k + 1) n)`` (the shard was made on a grid of another size).
    """
    s = shard.samples
    repeat = s.params[:, _REPEAT]
    repeat = np.where(np.isnan(repeat), 0.0, repeat)
    if np.any(~np.isfinite(repeat) | (repeat < 0) | (repeat != np.round(repeat))):
        raise ValueError(f"{shard.path}: the repeat params must be integers >= 0, got {np.unique(repeat)}")
    k = repeat.astype(np.int64)
    ids = s.sample_id.astype(np.int64) - k * int(n)
    bad = (ids < 0) | (ids >= n)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{shard.path}: sample id {int(s.sample_id[j])} of repeat {int(k[j])} is not a state of a "
            f"{shard.experiment} grid of {n} states (ids i + repeat * {n}, 0 <= i < {n})"
        )
    return ids


def commanded_state_keys(params, experiment: str) -> np.ndarray:
    """(N, K) canonical coordinates of every reading's commanded indenter state (module docstring).

    Rows are equal exactly when the commands are the same physical state, up to
    :data:`COMMAND_TOLERANCE` (the coordinates are rounded to it, -0 to +0):

    * ``"poke"`` (:class:`~defgraspnets.tactile.indenters.PokeCommand`, a rotationally symmetric
      sphere): the contact point's ``(rho cos phi, rho sin phi)`` on the hemisphere, the push direction
      ``-(sin theta cos phi, sin theta sin phi, cos theta)`` and the depth; phi drops out at
      rho = theta = 0.
    * ``"forearm"`` (:class:`~defgraspnets.tactile.indenters.ForearmCommand`): the depth, the shear
      vector ``s (cos phi_s, sin phi_s)`` and the twist psi, which fix the forearm's commanded motion;
      psi = +0 and -0 are the same press, and the shear direction drops out at s = 0.

    A row is NaN where a param it needs is not finite (not recorded), and every row of another
    experiment is NaN: such readings are no one's twin.

    Args:
        params: (N, len(PARAM_NAMES)) the readings' params (``TactileSamples.params``).
        experiment: the shards' ``experiment`` attribute.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < len(COMMAND_PARAM_NAMES):
        raise ValueError(f"params must be (N, >= {len(COMMAND_PARAM_NAMES)}), got {p.shape}")
    if experiment == "poke":
        phi, rho, theta, depth = (p[:, _P[k]] for k in ("phi", "contact_radius", "theta", "depth"))
        keys = np.stack(
            [
                rho * np.cos(phi),
                rho * np.sin(phi),
                np.sin(theta) * np.cos(phi),
                np.sin(theta) * np.sin(phi),
                np.cos(theta),
                depth,
            ],
            axis=1,
        )
    elif experiment == "forearm":
        depth, phi_s, s, psi = (p[:, _P[k]] for k in ("depth", "shear_direction", "shear_distance", "twist"))
        phi_s = np.where(s == 0.0, 0.0, phi_s)  # no shear: its direction is not part of the state
        keys = np.stack([depth, s * np.cos(phi_s), s * np.sin(phi_s), psi], axis=1)
    else:
        return np.full((len(p), 1), np.nan)
    keys = np.round(keys / COMMAND_TOLERANCE) * COMMAND_TOLERANCE + 0.0  # + 0.0: -0 -> +0
    keys[~np.isfinite(keys).all(axis=1)] = np.nan
    return keys


def _commanded_state_labels(keys: np.ndarray) -> np.ndarray:
    """(N,) integer labels, equal for equal key rows; a NaN row is a label of its own."""
    labels = np.arange(len(keys), dtype=np.int64) + len(keys)  # NaN rows: unique, above the others
    known = np.isfinite(keys).all(axis=1)
    if known.any():
        _, inverse = np.unique(keys[known], axis=0, return_inverse=True)
        labels[known] = inverse.ravel()
    return labels


def _join_twins(is_val, states, files, rows, keys) -> np.ndarray:
    """``is_val`` with every commanded-state class (equal ``keys``) on its representative's side: the
    reading with the smallest state id, then file rank, then row (module docstring)."""
    labels = _commanded_state_labels(keys)
    order = np.lexsort((rows, files, states, labels))
    first = np.ones(len(order), dtype=bool)
    first[1:] = labels[order][1:] != labels[order][:-1]
    side = np.zeros(labels.max() + 1 if len(labels) else 0, dtype=bool)
    side[labels[order][first]] = is_val[order][first]
    return side[labels]


def _check_commands(shards: list[TactileShard], states: list[np.ndarray]) -> None:
    """The readings grouped as one state must share its command (the first params columns)."""
    commands = np.concatenate([s.samples.params[:, : len(COMMAND_PARAM_NAMES)] for s in shards])
    labels, first, inverse = np.unique(np.concatenate(states), return_index=True, return_inverse=True)
    same = np.isclose(commands, commands[first][inverse.ravel()], rtol=1e-9, atol=1e-12, equal_nan=True)
    if not same.all():
        j = int(np.flatnonzero(~same.all(axis=1))[0])
        raise ValueError(
            f"{shards[0].experiment} readings of nominal state {int(labels[inverse.ravel()[j]])} have "
            "different commands: their sample ids do not follow the grid's i + repeat * n numbering"
        )


def split_tactile_shards(
    shards: list[TactileShard], val_fraction: float, seed: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (train rows, val rows) of every shard, split by nominal grid state (module docstring).

    Experiments with repeats are split as one block over their shards (:func:`split_groups` of
    :func:`nominal_state_ids`, key: the experiment name); the shards of experiments without repeats
    each on their own by rows (:func:`split_indices`, key: the file name), as before repeats existed.
    Then the readings of one commanded state under different ids (:func:`commanded_state_keys`) join
    the side of their representative, across the experiment's shards.
    """
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(shards)
    by_experiment: dict[str, list[int]] = {}
    for j, shard in enumerate(shards):
        by_experiment.setdefault(shard.experiment, []).append(j)
    for experiment, members in by_experiment.items():
        group = [shards[j] for j in members]
        if any(has_repeats(s) for s in group):
            n = grid_size(experiment)
            states = [nominal_state_ids(s, n) for s in group]
            _check_commands(group, states)
            _, val = split_groups(np.concatenate(states), val_fraction, seed, experiment)
            is_val = np.zeros(sum(map(len, states)), dtype=bool)
            is_val[val] = True
        else:
            states = [s.samples.sample_id.astype(np.int64) for s in group]
            is_val = np.zeros(sum(map(len, states)), dtype=bool)
            start = 0
            for s, ids in zip(group, states):
                _, val = split_indices(len(ids), val_fraction, seed, s.path.name)
                is_val[start + val] = True
                start += len(ids)
        rank = {p: r for r, p in enumerate(sorted(str(s.path) for s in group))}
        is_val = _join_twins(
            is_val,
            np.concatenate(states),
            np.concatenate([np.full(len(ids), rank[str(s.path)]) for s, ids in zip(group, states)]),
            np.concatenate([np.arange(len(ids)) for ids in states]),
            commanded_state_keys(np.concatenate([s.samples.params for s in group]), experiment),
        )
        start = 0
        for j, ids in zip(members, states):
            rows = is_val[start : start + len(ids)]
            out[j] = (np.flatnonzero(~rows), np.flatnonzero(rows))
            start += len(ids)
    return out


class TactileWrenchDataset(Dataset):
    """Samples ``(x (1, H, W) float32, wrench (6,) float32)`` of one shard (held in memory).

    Args:
        shard: a :class:`TactileShard` or the path of one.
        indices: the sample rows to use (default: all).
        depth_scale: normalization length [m], see :func:`normalize_depth`.
    """

    def __init__(self, shard: TactileShard | str | Path, indices=None, depth_scale: float = 0.01):
        self.shard = (
            shard if isinstance(shard, TactileShard) else read_tactile_shard(shard, load_points=False)
        )
        n = len(self.shard.samples)
        self.indices = np.arange(n) if indices is None else np.asarray(indices, dtype=np.int64)
        if len(self.indices) and (self.indices.min() < 0 or self.indices.max() >= n):
            raise IndexError(f"indices out of range for a shard of {n} samples")
        self.depth_scale = float(depth_scale)
        normalize_depth(np.zeros(1), np.zeros(1), self.depth_scale)  # validates the scale

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        row = self.indices[i]
        s = self.shard.samples
        x = normalize_depth(
            s.depth[row], self.shard.references.depth[s.reference_index[row]], self.depth_scale
        )
        return torch.from_numpy(x[None]), torch.from_numpy(s.wrench[row].astype(np.float32))


class TactileWrenchDataModule(L.LightningDataModule):
    """The §3.4 datasets: finger poking (batch 500), forearm (batch 400), or both combined (500).

    Args:
        shards: shard files or glob patterns (e.g. ``["data/tactile/poke/*.h5"]``); a combined
            dataset lists the patterns of both experiments.
        batch_size: training batch size (thesis: 500 poking and combined, 400 forearm).
        val_fraction: validation fraction (thesis: 0.2) of every shard's readings, or of an
            experiment's grid states where it has repeats (module docstring).
        seed: split seed.
        depth_scale: input normalization length [m].
        num_workers, pin_memory: DataLoader options.
    """

    def __init__(
        self,
        shards: list[str] | str,
        batch_size: int = 500,
        val_fraction: float = 0.2,
        seed: int = 0,
        depth_scale: float = 0.01,
        num_workers: int = 0,
        pin_memory: bool = False,
    ):
        super().__init__()
        self.save_hyperparameters(logger=False)
        self.shard_patterns = [shards] if isinstance(shards, str) else list(shards)
        if not self.shard_patterns:
            raise ValueError("no tactile shards given")
        if int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
        self.batch_size = int(batch_size)
        self.val_fraction = float(val_fraction)
        self.seed = int(seed)
        self.depth_scale = float(depth_scale)
        self.num_workers = int(num_workers)
        self.pin_memory = bool(pin_memory)
        self.shards: list[TactileShard] = []
        self.data_train: Dataset | None = None
        self.data_val: Dataset | None = None

    def shard_paths(self) -> list[Path]:
        """The shard files matched by the patterns, sorted; missing ones raise FileNotFoundError."""
        paths = []
        for pattern in self.shard_patterns:
            pattern = str(pattern)
            matches = sorted(glob.glob(pattern)) if any(c in pattern for c in "*?[") else [pattern]
            if not matches or not Path(matches[0]).exists():
                raise FileNotFoundError(f"no tactile shard matches {pattern!r}")
            paths += [Path(m) for m in matches]
        if len(set(paths)) != len(paths):
            raise ValueError(f"a shard is listed twice: {[str(p) for p in paths]}")
        return paths

    def setup(self, stage: str | None = None) -> None:
        if self.data_train is not None:
            return
        self.shards = [read_tactile_shard(p, load_points=False) for p in self.shard_paths()]
        shapes = {s.samples.image_shape for s in self.shards}
        if len(shapes) != 1:
            raise ValueError(f"tactile shards have different image sizes: {sorted(shapes)}")
        train, val = [], []
        for shard, (tr, va) in zip(
            self.shards, split_tactile_shards(self.shards, self.val_fraction, self.seed)
        ):
            train.append(TactileWrenchDataset(shard, tr, self.depth_scale))
            val.append(TactileWrenchDataset(shard, va, self.depth_scale))
        self.data_train, self.data_val = ConcatDataset(train), ConcatDataset(val)

    def train_wrenches(self) -> np.ndarray:
        """(N, 6) wrenches [N, N m] of the training split, in its order (the statistics of
        ``WrenchRegressionModule(target_scaling="standardize")``)."""
        if self.data_train is None:
            raise RuntimeError("call setup() first")
        parts = [d.shard.samples.wrench[d.indices] for d in self.data_train.datasets]
        return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 6))

    @property
    def image_shape(self) -> tuple[int, int]:
        if not self.shards:
            raise RuntimeError("call setup() first")
        return self.shards[0].samples.image_shape

    @property
    def reference_depth(self) -> np.ndarray | None:
        """The reference image if all shards share exactly one (a single PV state), else None."""
        refs = [s.references.depth[k] for s in self.shards for k in range(len(s.references))]
        if refs and all(np.array_equal(r, refs[0], equal_nan=True) for r in refs):
            return refs[0]
        return None

    def _loader(self, data, shuffle: bool) -> DataLoader:
        if data is None:
            raise RuntimeError("call setup() first")
        return DataLoader(
            data,
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.data_val, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_val, shuffle=False)
