"""Train / validation / test splits for the four generalization levels of thesis §7.6.

Entries are solved squeezes ``(shard, k, g)``; each split keeps all ramp steps of an entry together.

1. ``unseen_grasps``  unseen grasps on seen objects: per object, 80 / 20 over its grasps (all moduli).
2. ``unseen_E``       unseen moduli on seen objects: per object, 7 / 3 over its distinct Young's moduli
                      (all grasps). Objects with a single modulus stay in training.
3. ``unseen_objects`` unseen primitives within a category: per category of ``primitive`` objects, 5 / 1 over
                      objects (at least one test object per category of two or more). Real objects are not
                      used at this level.
4. ``unseen_real``    unseen real-world objects: ``test_objects`` (default: every ``real`` object) are held
                      out; training uses ``train_objects`` (default: every other object). Table 7.1 trains
                      on small groups of objects through ``train_objects``.

Validation is carved from the training entries at the grasp level (``val_fraction`` of each object's
training grasps, and at least two of an object with four or more, so that the validation Kendall tau has
grasps to rank), so ``val`` always measures level-1 generalization and ``test`` the chosen level.
Randomness is seeded per object/category name (``seed`` and a CRC of the name), so adding an object does
not reshuffle the others.

What is held out is drawn in one of two ways (``draw``). ``"permutation"`` (the splits of checkpoints trained
before session 42) takes the first units of a seeded permutation of the *solved* units (grasps, axes,
moduli or objects) of an object or category, so when a regenerated data set solves one ramp more or fewer
(near-budget ramps flip between CUDA runs: 11 of 2160 in session 42), that object's whole held-out part is
drawn anew and a model resumed on the new data trains on some of its old test grasps. ``"stable"`` gives
every unit its own seeded random key (from the object or category name, the unit's index or modulus, and
``seed``) and holds out the units with the lowest keys: a flipped unit enters or leaves alone, and the count
(a fraction, rounded) moves by at most one, so the rest of the held-out part stays where it was (validation,
drawn from what the test part leaves, may move one unit more).

``holdout="axis"`` holds out whole grasp axes at level 1 and in validation instead of single grasps. The
antipodal sampler makes up to 4 grasps per axis (the same contact points, the approach turned about the
axis), so a single held-out grasp usually has siblings in training. Measured (session 23,
``benchmarks/defgraspnets_long_training_h100.md``): the 18-object checkpoint, trained on a per-grasp split,
ranks its test grasps at 15 N with tau_s 0.79, but 12 new grasps (new axes) on each of 6 of its training
meshes with tau_s 0.22 on average.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from defgraspnets.data.grasp_schema import STATUS_SOLVED, GraspShard

__all__ = [
    "SPLITS",
    "HOLDOUTS",
    "DEFAULT_TEST_FRACTION",
    "DRAWS",
    "ShardInfo",
    "Split",
    "grasp_axis_ids",
    "make_split",
    "named_rng",
]

log = logging.getLogger(__name__)

SPLITS = ("unseen_grasps", "unseen_E", "unseen_objects", "unseen_real")
HOLDOUTS = ("grasp", "axis")
DRAWS = ("stable", "permutation")
LEVEL = {"unseen_grasps": 1, "unseen_E": 2, "unseen_objects": 3, "unseen_real": 4}
DEFAULT_TEST_FRACTION = {
    "unseen_grasps": 0.2,
    "unseen_E": 0.3,
    "unseen_objects": 1.0 / 6.0,
    "unseen_real": None,
}


@dataclass(frozen=True)
class ShardInfo:
    """What the splitter needs of a shard: identity, moduli (K,) [Pa], solver status (K, G) and the grasp
    axis of each grasp (G,) (None: every grasp its own axis)."""

    object_name: str
    category: str
    source: str
    youngs_modulus: np.ndarray
    status: np.ndarray
    grasp_axis: np.ndarray | None = None

    @classmethod
    def of(cls, shard: GraspShard) -> ShardInfo:
        o = shard.object
        axis = grasp_axis_ids(shard.grasp_pose, shard.closing_direction)
        return cls(o.name, o.category, o.source, o.youngs_modulus, shard.status, axis)


def grasp_axis_ids(
    grasp_pose: np.ndarray, closing_direction: np.ndarray, tolerance: float = 1e-6
) -> np.ndarray:
    """(G,) one id per grasp axis: grasps whose gripper poses (G, 4, 4) share the origin and whose fingers
    (G, 2, 3) close along the same direction, to ``tolerance`` [m, unitless], are rotations about one axis.

    The antipodal sampler makes up to ``rotations_per_axis`` (4) grasps per axis (same contact points,
    approach turned about the axis); holding out single grasps would leave a test grasp's contact points in
    training through its siblings."""
    key = np.concatenate([grasp_pose[:, :3, 3], closing_direction[:, 0]], axis=1)
    _, ids = np.unique(np.round(key / tolerance).astype(np.int64), axis=0, return_inverse=True)
    return ids.ravel()


@dataclass
class Split:
    """Entries (P, 3) ``(shard, k, g)`` of each part, and the object names of train and test; ``solved``
    holds every solved entry of the data, whatever the part (objects a level does not use included)."""

    name: str
    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    train_objects: list[str] = field(default_factory=list)
    test_objects: list[str] = field(default_factory=list)
    solved: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))

    def summary(self) -> dict:
        return {
            "split": self.name,
            "level": LEVEL[self.name],
            "entries": {"train": len(self.train), "val": len(self.val), "test": len(self.test)},
            "train_objects": self.train_objects,
            "test_objects": self.test_objects,
        }


def named_rng(seed: int, name: str) -> np.random.Generator:
    """A generator seeded by ``seed`` and a CRC of ``name``: draws for one object (file, category, ...) that
    do not change when others are added, and are the same in every run."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def _lowest_keys(
    candidates: Sequence, count: int, draw: str, rng_name: str, seed: int, key_names=None
) -> list:
    """The ``count`` held-out ones of ``candidates`` (in their given order): the first of a seeded
    permutation (``draw="permutation"``), or those with the lowest per-candidate keys (``"stable"``;
    ``key_names[i]`` names candidate i's key, default its value)."""
    candidates = list(candidates)
    if draw == "permutation":
        order = named_rng(seed, rng_name).permutation(len(candidates))
    else:
        names = candidates if key_names is None else list(key_names)
        keys = [named_rng(seed, f"{rng_name}/{name}").random() for name in names]
        order = np.argsort(keys, kind="stable")
    return [candidates[i] for i in order[:count]]


def _count(n: int, fraction: float, what: str) -> int:
    """How many of n go to the held-out part: round(fraction n), clipped to [1, n - 1]."""
    if n < 2:
        raise ValueError(f"cannot hold out {what}: only {n} available")
    return int(np.clip(round(fraction * n), 1, n - 1))


def _solved(infos: Sequence[ShardInfo], shards: Sequence[int]) -> np.ndarray:
    parts = [
        np.concatenate([np.full((len(kg), 1), sh), kg], axis=1)
        for sh in shards
        for kg in [np.argwhere(infos[sh].status == STATUS_SOLVED)]
    ]
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 3), np.int64)


def _grasp_holdout(
    entries: np.ndarray,
    infos: Sequence[ShardInfo],
    fraction: float,
    seed: int,
    what: str,
    minimum: int = 1,
    holdout: str = "grasp",
    draw: str = "permutation",
):
    """Split entries per object by grasp ``(shard, g)`` (``holdout="grasp"``) or by grasp axis (``"axis"``:
    all rotations about one axis on the same side); returns (kept, held_out). At least ``minimum`` units
    are held out of an object that keeps as many. ``draw``: see the module docstring (a stable key names
    the unit by its shard's rank among the object's shards and its grasp or axis index)."""
    held = np.zeros(len(entries), dtype=bool)
    if fraction <= 0 or not len(entries):
        return entries, entries[held]
    unit = entries[:, 2]
    if holdout == "axis":
        unit = np.empty(len(entries), dtype=np.int64)
        for sh in np.unique(entries[:, 0]):
            on = entries[:, 0] == sh
            unit[on] = _grasp_axes(infos[sh])[entries[on, 2]]
    key = entries[:, 0] * 1_000_000 + unit
    names = np.array([infos[sh].object_name for sh in entries[:, 0]])
    single_axis = []
    for name in np.unique(names):
        on = names == name
        units = np.unique(key[on])
        if len(units) < 2:
            log.warning("object %s has %d %s %s(s): none held out", name, len(units), what, holdout)
            continue
        count = _count(len(units), fraction, what)
        if len(units) >= 2 * minimum:
            count = max(count, minimum)
        shard_rank = {sh: r for r, sh in enumerate(np.unique(units // 1_000_000))}
        unit_names = [f"{shard_rank[u // 1_000_000]}/{u % 1_000_000}" for u in units]
        pick = _lowest_keys(units, count, draw, f"{what}/{name}", seed, unit_names)
        held |= on & np.isin(key, pick)
        if holdout == "axis" and count == 1:
            single_axis.append(str(name))
    if single_axis:
        log.warning(
            "the %s part holds out one grasp axis of %d object(s) (%s): its Kendall tau ranks only the "
            "rotations about that axis, not grasps across the object; generate more axes per object, or "
            "evaluate on grasps drawn with another datagen seed (scripts/evaluate.py part=all)",
            what,
            len(single_axis),
            ", ".join(single_axis),
        )
    return entries[~held], entries[held]


def _grasp_axes(info: ShardInfo) -> np.ndarray:
    if info.grasp_axis is None:
        raise ValueError(f"{info.object_name}: no grasp axes known, cannot hold out by axis")
    return np.asarray(info.grasp_axis, dtype=np.int64)


def make_split(
    infos: Sequence[ShardInfo],
    split: str = "unseen_grasps",
    seed: int = 0,
    test_fraction: float | None = None,
    val_fraction: float = 0.1,
    test_objects: Sequence[str] | None = None,
    train_objects: Sequence[str] | None = None,
    holdout: str = "grasp",
    draw: str = "permutation",
) -> Split:
    """Split the solved entries of ``infos`` (one per shard) for generalization level ``split``.

    Args:
        infos: one :class:`ShardInfo` per shard (indices are shard numbers).
        split: one of :data:`SPLITS`.
        seed: split seed. test_fraction: held-out fraction (default per level: 0.2, 0.3, 1/6).
        val_fraction: fraction of each object's training grasps used for validation.
        test_objects, train_objects: object names for ``unseen_real`` (defaults in the module docstring).
        holdout: what the unseen-grasps test part and every validation part hold out per object: single
            grasps (``"grasp"``, the splits of checkpoints trained before session 23) or whole grasp axes
            (``"axis"``: a held-out grasp shares no contact points with a training grasp).
        draw: how held-out units are drawn: ``"permutation"`` (splits before session 42) or ``"stable"``
            (per-unit keys: a ramp that flips between solved and failed in regenerated data moves only
            itself; see the module docstring).

    Raises:
        ValueError: unknown split, unknown object names, or a split that would leave a part empty.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {SPLITS}")
    if holdout not in HOLDOUTS:
        raise ValueError(f"unknown holdout {holdout!r}; choose one of {HOLDOUTS}")
    if draw not in DRAWS:
        raise ValueError(f"unknown draw {draw!r}; choose one of {DRAWS}")
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    frac = DEFAULT_TEST_FRACTION[split] if test_fraction is None else float(test_fraction)
    if frac is not None and not 0 < frac < 1:
        raise ValueError(f"test_fraction must be in (0, 1), got {frac}")
    names = sorted({i.object_name for i in infos})
    shards_of = {n: [s for s, i in enumerate(infos) if i.object_name == n] for n in names}
    all_entries = _solved(infos, range(len(infos)))
    if not len(all_entries):
        raise ValueError("no solved (status 0) squeeze in the data: nothing to train on")

    if split == "unseen_grasps":
        train, test = _grasp_holdout(all_entries, infos, frac, seed, "test", holdout=holdout, draw=draw)
        test_names = train_names = names
    elif split == "unseen_E":
        held = np.zeros(len(all_entries), dtype=bool)
        for name in names:
            on = np.isin(all_entries[:, 0], shards_of[name])
            log_e = np.round(np.log10([infos[sh].youngs_modulus[k] for sh, k, _ in all_entries[on]]), 6)
            unique = np.unique(log_e)
            if len(unique) < 2:
                log.warning("object %s has a single Young's modulus: kept for training only", name)
                continue
            count = _count(len(unique), frac, "moduli")
            test_e = _lowest_keys(unique, count, draw, f"E/{name}", seed, [f"{e:.6f}" for e in unique])
            held[np.flatnonzero(on)[np.isin(log_e, test_e)]] = True
        train, test = all_entries[~held], all_entries[held]
        test_names = train_names = names
    elif split == "unseen_objects":
        prim = [n for n in names if infos[shards_of[n][0]].source == "primitive"]
        skipped = sorted(set(names) - set(prim))
        if skipped:
            log.info("unseen_objects: real objects %s are not used at this level", skipped)
        test_names = []
        for cat in sorted({infos[shards_of[n][0]].category for n in prim}):
            members = [n for n in prim if infos[shards_of[n][0]].category == cat]
            if len(members) < 2:
                log.warning("category %s has a single primitive (%s): kept for training only", cat, members)
                continue
            count = _count(len(members), frac, f"objects of {cat}")
            test_names += _lowest_keys(members, count, draw, f"objects/{cat}", seed)
        train_names = [n for n in prim if n not in test_names]
        test_names = sorted(test_names)
    else:  # unseen_real
        unknown = sorted((set(test_objects or []) | set(train_objects or [])) - set(names))
        if unknown:
            raise ValueError(f"unseen_real: objects {unknown} are not in the data (available: {names})")
        test_names = (
            sorted(test_objects)
            if test_objects
            else [n for n in names if infos[shards_of[n][0]].source == "real"]
        )
        train_names = sorted(train_objects) if train_objects else [n for n in names if n not in test_names]
        overlap = sorted(set(test_names) & set(train_names))
        if overlap:
            raise ValueError(f"unseen_real: objects {overlap} are both train and test objects")

    if split in ("unseen_objects", "unseen_real"):
        if not test_names:
            raise ValueError(
                f"{split}: no test object (need real objects, or categories with >= 2 primitives)"
            )
        train = _solved(infos, [s for n in train_names for s in shards_of[n]])
        test = _solved(infos, [s for n in test_names for s in shards_of[n]])
    # two grasps at least per object, so that validation ranks grasps (tau needs two per object, E and step)
    # (one axis holds up to 4 grasps: with holdout="axis" one axis is enough)
    minimum = 2 if holdout == "grasp" else 1
    train, val = _grasp_holdout(
        train, infos, val_fraction, seed, "val", minimum=minimum, holdout=holdout, draw=draw
    )
    for part, arr in (("train", train), ("test", test)):
        if not len(arr):
            raise ValueError(f"split {split!r} leaves the {part} part empty")
    if val_fraction > 0 and not len(val):
        raise ValueError(
            f"split {split!r}: no validation grasps (objects need >= 2 training grasps); "
            "set val_fraction=0 to train without validation"
        )
    return Split(split, train, val, test, list(train_names), list(test_names), all_entries)
