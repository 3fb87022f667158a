"""Dataset samples, generalization splits and the LightningDataModule on synthetic shards."""

from __future__ import annotations

import logging

import h5py
import numpy as np
import pytest
import torch
from test_data_synthetic import make_shards

from defgraspnets.data.datamodule import GraspDataModule
from defgraspnets.data.dataset import DataError, GraspFieldDataset, discover_shards, sample_index
from defgraspnets.data.grasp_schema import GraspShard
from defgraspnets.data.splits import ShardInfo, make_split
from defgraspnets.grasp.metrics import best_rigid_transform, rigid_removed_deformation
from defgraspnets.models.graph import NODE_FINGER


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return make_shards(tmp_path_factory.mktemp("grasps"), grasps=5, num_steps=3)


@pytest.fixture(scope="module")
def shards(data_dir):
    return [GraspShard(p) for p in discover_shards(data_dir)]


def _keys(entries, shards, cols=(0, 2)):
    return {(shards[e[0]].object.name, *(int(e[c]) for c in cols)) for e in entries}


def test_sample_matches_shard(shards):
    ds = GraspFieldDataset(shards, sample_index(shards, np.array([[0, 2, 3]]), [1]), ramp_stride=1)
    g = ds[0]
    sh = shards[0]
    n, v = sh.num_vertices, len(sh.fingers.vertices)
    assert g.num_nodes == n + 2 * v
    np.testing.assert_allclose(g.pos[:n].numpy(), sh.object.points, atol=1e-9)
    np.testing.assert_allclose(
        g.pos[n:].numpy().reshape(2, v, 3), sh.fingers.vertices_at(sh.finger_contact_pose[3]), atol=1e-9
    )
    vm, d = sh.fields(2, 3, 1)
    np.testing.assert_array_equal(g.stress[:n].numpy(), vm)
    np.testing.assert_array_equal(g.displacement[:n].numpy(), d)
    travel = sh.finger_travel[2, 3, 1]
    np.testing.assert_allclose(
        g.displacement[n:].numpy(), np.repeat(travel[:, None] * sh.closing_direction[3], v, 0), rtol=1e-6
    )
    assert (
        float(g.force) == pytest.approx(sh.force[2, 3, 1])
        and float(g.youngs_modulus) == sh.object.youngs_modulus[2]
    )
    assert g.sample.tolist() == [[0, 2, 3, 1]]
    _, d0 = sh.fields(2, 3, 0)
    np.testing.assert_array_equal(g.prev_displacement[:n].numpy(), d0)
    assert (g.node_type[n:] == NODE_FINGER).all() and g.contact_edge_index.shape[1] > 0


def test_failed_squeezes_are_never_samples(shards):
    assert shards[0].status[1, 2] != 0
    with pytest.raises(DataError, match="not solved"):
        sample_index(shards, np.array([[0, 1, 2]]))
    split = make_split([ShardInfo.of(s) for s in shards], "unseen_grasps")
    for part in (split.train, split.val, split.test):
        assert not any((e[0], e[1], e[2]) == (0, 1, 2) for e in part)


def test_nan_in_solved_entry_is_a_clear_error(tmp_path, shards):
    path = tmp_path / "cuboid_b__shard0of1.h5"
    path.write_bytes(shards[2].path.read_bytes())
    with h5py.File(path, "a") as f:
        f["ramp/von_mises"][0, 0, 0, 5] = np.nan
    sh = GraspShard(path)
    ds = GraspFieldDataset([sh], sample_index([sh], np.array([[0, 0, 0]]), [0]))
    with pytest.raises(DataError, match=r"von_mises\[k=0, g=0, s=0\] contains NaN"):
        ds[0]


def test_generalization_splits(shards):
    infos = [ShardInfo.of(s) for s in shards]
    names = {s.object.name for s in shards}

    s1 = make_split(infos, "unseen_grasps", seed=3)
    train, test = _keys(np.concatenate([s1.train, s1.val]), shards), _keys(s1.test, shards)
    assert train and test and not train & test  # no grasp on both sides
    assert {n for n, *_ in test} == names  # every object has unseen grasps
    assert not _keys(s1.train, shards) & _keys(s1.val, shards)
    # validation ranks grasps: two or more of every object with four or more training grasps
    for name in names:
        kept = {k for k in _keys(np.concatenate([s1.train, s1.val]), shards) if k[0] == name}
        held = {k for k in _keys(s1.val, shards) if k[0] == name}
        assert len(held) >= 2 or len(kept) < 4, (name, len(held), len(kept))

    s2 = make_split(infos, "unseen_E")
    e = {
        p: {(shards[x[0]].object.name, shards[x[0]].object.youngs_modulus[x[1]]) for x in getattr(s2, p)}
        for p in ("train", "val", "test")
    }
    assert not (e["train"] | e["val"]) & e["test"]
    assert all(len([1 for n2, _ in e["test"] if n2 == n]) == 1 for n in names)  # 1 of 3 moduli (7/3 of 3)

    s3 = make_split(infos, "unseen_objects")
    assert len([n for n in s3.test_objects if n.startswith("cuboid")]) == 1
    assert len([n for n in s3.test_objects if n.startswith("slab")]) == 1
    assert "strawberry" not in s3.test_objects + s3.train_objects
    assert not set(s3.train_objects) & set(s3.test_objects)
    assert {shards[x[0]].object.name for x in s3.test} == set(s3.test_objects)

    s4 = make_split(infos, "unseen_real")
    assert s4.test_objects == ["strawberry"] and "strawberry" not in s4.train_objects
    g = make_split(infos, "unseen_real", train_objects=["cuboid_a", "slab_a"])
    assert {shards[x[0]].object.name for x in np.concatenate([g.train, g.val])} == {"cuboid_a", "slab_a"}

    with pytest.raises(ValueError, match="unknown split"):
        make_split(infos, "unseen_colors")
    with pytest.raises(ValueError, match=r"\['banana'\] are not in the data"):
        make_split(infos, "unseen_real", test_objects=["banana"])
    # splits are reproducible and depend on the seed
    assert np.array_equal(make_split(infos, "unseen_grasps", seed=3).test, s1.test)


def test_datamodule(data_dir):
    dm = GraspDataModule(
        str(data_dir), split="unseen_E", eval_steps=[-1], batch_size=3, statistics_samples=10
    )
    dm.setup("fit")
    summary = dm.summary()
    assert summary["level"] == 2 and summary["samples"]["train"] == 3 * len(dm.split.train)
    assert summary["samples"]["test"] == len(dm.split.test)  # final step only
    batch = next(iter(dm.train_dataloader()))
    assert batch.graph_count == 3 and batch.force.shape == (3,) and batch.sample.shape == (3, 4)
    assert batch.mesh_edge_index.max() < batch.num_nodes and batch.contact_edge_index.max() < batch.num_nodes
    assert sum(b.graph_count for b in dm.statistics_dataloader()) == 10
    assert all(torch.isfinite(b.stress).all() for b in dm.test_dataloader())


def test_datamodule_errors(tmp_path, data_dir):
    with pytest.raises(FileNotFoundError, match="not found"):
        GraspDataModule(str(tmp_path / "missing")).setup("fit")
    (tmp_path / "cube__shard0of1.partial.h5").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match="1 unfinished"):
        GraspDataModule(str(tmp_path)).setup("fit")
    with pytest.raises(ValueError, match="data.split"):
        GraspDataModule(str(data_dir), split="nope")
    with pytest.raises(ValueError, match="no shard"):
        GraspDataModule(str(data_dir), objects=["cuboid_a", "pear"]).setup("fit")


def _deformed(g, disp):
    return (g.pos.double() + disp.double()).numpy()


def test_rigid_removed_target_is_the_total_field_in_the_object_frame(shards):
    """The rigid-removed target moves every node (object and fingers) by one rigid transform: node-to-node
    distances are those of the total field, the object part has no rigid motion left and its magnitudes are
    the §6.5 rigid-removed deformation."""
    solved = [(i, *kg) for i in (0, 1) for kg in np.argwhere(shards[i].status == 0)[:1]]
    samples = sample_index(shards, np.array(solved), None)
    total = GraspFieldDataset(shards, samples)
    removed = GraspFieldDataset(shards, samples, displacement="rigid_removed")
    for i in range(len(samples)):
        a, b = total[i], removed[i]
        torch.testing.assert_close(a.stress, b.stress)
        torch.testing.assert_close(a.pos, b.pos)
        n = shards[int(a.sample[0, 0])].num_vertices
        xa, xb = _deformed(a, a.displacement), _deformed(b, b.displacement)
        pick = np.r_[0:n:7, n : len(xa) : 11]  # object and finger nodes
        da = np.linalg.norm(xa[pick, None] - xa[None, pick], axis=-1)
        db = np.linalg.norm(xb[pick, None] - xb[None, pick], axis=-1)
        np.testing.assert_allclose(db, da, atol=2e-7)
        rest = a.pos[:n].double().numpy()
        R, t = best_rigid_transform(rest, xb[:n])
        np.testing.assert_allclose(R, np.eye(3), atol=1e-6)
        np.testing.assert_allclose(t, 0.0, atol=1e-7)
        expected = rigid_removed_deformation(rest, xa[:n])
        np.testing.assert_allclose(
            np.linalg.norm(b.displacement[:n].double().numpy(), axis=1), expected, atol=2e-7
        )


def test_rigid_motion_of_the_object_leaves_no_rigid_removed_displacement(shards):
    """A rigidly turned and shifted object (fingers carried along) has zero rigid-removed displacement."""
    ds = GraspFieldDataset(shards, sample_index(shards, np.array([[0, 2, 3]]), [0]))
    g = ds[0]
    angle = np.radians(14.0)
    rot = torch.tensor(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )
    pos = g.pos.double()
    disp = (pos @ rot.T + torch.tensor([1e-3, 5e-3, -3e-3], dtype=torch.float64) - pos).float()
    out = GraspFieldDataset._remove_rigid_motion(g.pos, disp, shards[0].num_vertices)
    assert out.abs().max() < 1e-7


def test_displacement_target_config_errors(shards, data_dir):
    samples = sample_index(shards, np.array([[0, 2, 3]]), [1])
    with pytest.raises(ValueError, match="displacement='rigid' is not one of"):
        GraspFieldDataset(shards, samples, displacement="rigid")
    with pytest.raises(ValueError, match="ramp_stride"):
        GraspFieldDataset(shards, samples, ramp_stride=1, displacement="rigid_removed")
    with pytest.raises(ValueError, match="data.displacement='x' is not one of"):
        GraspDataModule(str(data_dir), displacement="x")
    with pytest.raises(ValueError, match="data.ramp_stride"):
        GraspDataModule(str(data_dir), displacement="rigid_removed", ramp_stride=1)


def _axis_infos():
    """Two objects of 16 grasps in 6 axes (4, 4, 2, 2, 3, 1 rotations), 2 moduli, every squeeze solved."""
    axis = np.array([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 3, 3, 4, 4, 4, 5])
    return [
        ShardInfo(name, "cuboid", "primitive", np.array([1e5, 1e6]), np.zeros((2, 16), np.int8), axis)
        for name in ("cuboid_a", "cuboid_b")
    ]


def _axes(entries, infos):
    return {(infos[sh].object_name, int(infos[sh].grasp_axis[g])) for sh, _, g in entries}


def test_axis_holdout_keeps_every_grasp_axis_on_one_side():
    infos = _axis_infos()
    for seed in range(5):
        s = make_split(infos, "unseen_grasps", seed=seed, holdout="axis")
        train, val, test = (_axes(getattr(s, p), infos) for p in ("train", "val", "test"))
        assert test and val and train
        assert not (train | val) & test and not train & val
        assert {n for n, _ in test} == {"cuboid_a", "cuboid_b"}
        # one of six axes is 0.2 of them (rounded): every rotation about it
        for name in ("cuboid_a", "cuboid_b"):
            assert len({a for n, a in test if n == name}) == 1
    # holding out single grasps leaves siblings of test grasps in training (what holdout=axis prevents)
    leaks = 0
    for seed in range(5):
        s = make_split(infos, "unseen_grasps", seed=seed, holdout="grasp")
        leaks += len(_axes(s.train, infos) & _axes(s.test, infos))
        # the grasps themselves are disjoint either way
        assert not _keys_of(s.train) & _keys_of(s.test)
    assert leaks > 0
    with pytest.raises(ValueError, match="unknown holdout"):
        make_split(infos, "unseen_grasps", holdout="rotation")
    no_axes = [ShardInfo(i.object_name, i.category, i.source, i.youngs_modulus, i.status) for i in infos]
    with pytest.raises(ValueError, match="cuboid_a: no grasp axes known"):
        make_split(no_axes, "unseen_grasps", holdout="axis")


def test_axis_holdout_warns_when_a_part_ranks_rotations_about_one_axis(caplog):
    # 6 axes per object: the test part holds one (its tau would rank 4 rotations of one axis), and so does
    # the validation part (0.1 of the 5 left, at least one)
    with caplog.at_level(logging.WARNING, logger="defgraspnets.data.splits"):
        make_split(_axis_infos(), "unseen_grasps", holdout="axis")
    msgs = [r.getMessage() for r in caplog.records if "rotations about that axis" in r.getMessage()]
    assert len(msgs) == 2 and "test part" in msgs[0] and "val part" in msgs[1]
    assert "2 object(s) (cuboid_a, cuboid_b)" in msgs[0]
    # 20 axes per object: 4 test axes, 2 validation axes; single grasps: never this warning
    axis = np.repeat(np.arange(20), 2)
    many = [
        ShardInfo(n, "cuboid", "primitive", np.array([1e6]), np.zeros((1, 40), np.int8), axis) for n in "ab"
    ]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="defgraspnets.data.splits"):
        s = make_split(many, "unseen_grasps", holdout="axis")
        make_split(_axis_infos(), "unseen_grasps", holdout="grasp")
    assert len(_axes(s.test, many)) == 8 and len(_axes(s.val, many)) == 4
    assert not [r for r in caplog.records if "rotations about that axis" in r.getMessage()]


def _keys_of(entries):
    return {(int(sh), int(g)) for sh, _, g in entries}


def test_grasp_axis_ids_group_the_samplers_rotations():
    from defgraspnets.data.splits import grasp_axis_ids
    from defgraspnets.grasp.datagen import structured_box
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import finger_contact_poses

    box = structured_box((0.04, 0.03, 0.02), (4, 3, 2))
    grasps = sample_antipodal_grasps(box, num_grasps=16, seed=0)
    closing = finger_contact_poses(grasps)[:, :, :3, 1]  # each pad closes along its frame's +y
    ids = grasp_axis_ids(grasps.poses, closing)
    # the same partition as the sampler's own axis ids
    pairs = {(int(a), int(b)) for a, b in zip(ids, grasps.axis_ids)}
    assert len(pairs) == len(set(ids.tolist())) == len(set(grasps.axis_ids.tolist())) < 16


def _sample_rows(dataset) -> list[tuple]:
    return [tuple(int(v) for v in row) for row in dataset.samples]


@pytest.mark.parametrize("split", ["unseen_grasps", "unseen_objects"])
def test_all_part_holds_every_solved_squeeze(data_dir, shards, split):
    """The "all" part (scripts/evaluate.py part=all) is every solved entry of the data at the evaluation
    steps, once: for unseen_grasps the union of train, val and test; for unseen_objects also the real
    object the level does not use. Failed ramps are never part of it."""
    dm = GraspDataModule(str(data_dir), split=split, eval_steps=[-1], train_steps=[-1])
    dm.setup("test")
    solved = {(sh, int(k), int(g)) for sh, s in enumerate(dm.shards) for k, g in np.argwhere(s.status == 0)}
    assert {tuple(int(v) for v in e) for e in dm.split.solved} == solved
    assert len(dm.split.solved) == len(solved)
    rows = _sample_rows(dm.datasets["all"])
    assert len(rows) == len(set(rows)) == len(solved)  # one eval step, no duplicate
    assert {r[:3] for r in rows} == solved and {r[3] for r in rows} == {2}  # 3 steps: [-1] is step 2
    assert (0, 1, 2) not in {r[:3] for r in rows} and dm.shards[0].status[1, 2] != 0
    parts = [r for p in ("train", "val", "test") for r in _sample_rows(dm.datasets[p])]
    assert len(parts) == len(set(parts))
    if split == "unseen_grasps":
        assert set(parts) == set(rows)
    else:
        real = {sh for sh, s in enumerate(dm.shards) if s.object.source == "real"}
        assert real and set(parts) == {r for r in rows if r[0] not in real}
        assert {r[0] for r in rows} >= real
    assert dm.summary()["samples"]["all"] == len(rows)
