"""Grasp shard schema: write -> read round trip, validation errors, resumable atomic writes."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_data_synthetic import box_object, grasp_poses, pad_fingers, ramp_fields

from defgraspnets.data.grasp_schema import (
    SCHEMA_VERSION,
    GraspShard,
    GraspShardWriter,
    ShardSchemaError,
    parse_shard_name,
    shard_file_name,
)

S = 3


def _inputs(grasps=3):
    obj = box_object("cube", divisions=(2, 2, 2))
    pose, fpose, cdir = grasp_poses(obj, grasps, 0)
    return obj, pad_fingers(), pose, fpose, cdir


def _write_all(writer, obj, fpose, cdir, entries=None):
    for k, g in entries if entries is not None else writer.pending():
        writer.write(k, g, *ramp_fields(obj, fpose[g], cdir[g], obj.youngs_modulus[k], S))


def _datasets(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None
        )
        out["attrs"] = {k: v for k, v in f.attrs.items() if k != "created"}
    return out


def test_round_trip(tmp_path):
    obj, fingers, pose, fpose, cdir = _inputs()
    path = tmp_path / shard_file_name("cube", 0, 1)
    w = GraspShardWriter.create(
        path, obj, fingers, pose, fpose, cdir, S, generator_version="1.2", config="a: 1"
    )
    assert w.partial_path.exists() and not path.exists()
    _write_all(w, obj, fpose, cdir)
    assert w.finalize() == path and path.exists() and not w.partial_path.exists()

    shard = GraspShard(path)
    assert shard.attrs["schema"] == SCHEMA_VERSION and shard.attrs["generator_version"] == "1.2"
    assert shard.attrs["config"] == "a: 1" and shard.attrs["object_source"] == "primitive"
    np.testing.assert_array_equal(shard.object.points, obj.points)
    np.testing.assert_array_equal(shard.object.tets, obj.tets)
    np.testing.assert_array_equal(shard.object.surface_faces, obj.surface_faces)
    np.testing.assert_array_equal(shard.object.youngs_modulus, obj.youngs_modulus)
    assert shard.object.material_model == obj.material_model == "corotated"
    np.testing.assert_array_equal(shard.fingers.vertices, fingers.vertices)
    np.testing.assert_array_equal(shard.fingers.closing_axis, fingers.closing_axis)
    np.testing.assert_array_equal(shard.grasp_pose, pose)
    np.testing.assert_array_equal(shard.finger_contact_pose, fpose)
    for k in range(obj.num_moduli):
        for g in range(len(pose)):
            force, vm, disp, travel = ramp_fields(obj, fpose[g], cdir[g], obj.youngs_modulus[k], S)
            np.testing.assert_array_equal(shard.force[k, g], force)
            np.testing.assert_array_equal(shard.finger_travel[k, g], travel)
            for s in range(S):
                got_vm, got_d = shard.fields(k, g, s)
                np.testing.assert_array_equal(got_vm, vm[s].astype(np.float32))
                np.testing.assert_array_equal(got_d, disp[s].astype(np.float32))
    assert (shard.status == 0).all() and len(shard.solved()) == obj.num_moduli * len(pose)
    with h5py.File(path) as f:
        assert f["ramp/von_mises"].compression == "lzf" and "progress" not in f
    assert parse_shard_name(path) == ("cube", 0, 1)


def test_material_model_round_trip_and_shards_without_it(tmp_path):
    obj, fingers, pose, fpose, cdir = _inputs()
    obj = dataclasses.replace(obj, material_model="neohookean")
    path = tmp_path / shard_file_name("cube", 0, 1)
    w = GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test")
    _write_all(w, obj, fpose, cdir)
    w.finalize()
    assert GraspShard(path).object.material_model == "neohookean"
    # a shard written before the attribute existed reads as the co-rotated model it was made with
    with h5py.File(path, "a") as f:
        del f["material"].attrs["model"]
    assert GraspShard(path).object.material_model == "corotated"
    with pytest.raises(ValueError, match="material_model"):
        dataclasses.replace(obj, material_model="hookean")


def test_unfinished_shard_of_another_material_model_is_not_resumed(tmp_path):
    obj, fingers, pose, fpose, cdir = _inputs()
    path = tmp_path / shard_file_name("cube", 0, 1)
    w = GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test")
    _write_all(w, obj, fpose, cdir, entries=w.pending()[:1])
    w.close()
    other = dataclasses.replace(obj, material_model="neohookean")
    with pytest.raises(ValueError, match="different object/material"):
        GraspShardWriter.create(path, other, fingers, pose, fpose, cdir, S, "test")


def test_unfinished_shard_of_other_solver_settings_is_not_resumed(tmp_path):
    """The writer records the solver settings it is given; an unfinished shard is resumed only with the same
    ones (none recorded counts as other settings), and the error names what differs."""
    obj, fingers, pose, fpose, cdir = _inputs()
    path = tmp_path / shard_file_name("cube", 0, 1)
    settings = {"squeeze": {"rtol": 1e-5, "friction_lag_check": 1000.0}}
    w = GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test", solver_settings=settings)
    _write_all(w, obj, fpose, cdir, entries=w.pending()[:1])
    w.close()
    other = {"squeeze": {"rtol": 1e-5, "friction_lag_check": 1.0}}
    with pytest.raises(ValueError, match=r"solver settings \(squeeze.friction_lag_check: 1000.0 -> 1.0\)"):
        GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test", solver_settings=other)
    with pytest.raises(ValueError, match="recorded on one side only"):
        GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test")
    w = GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, "test", solver_settings=settings)
    assert len(w.pending()) == obj.num_moduli * len(pose) - 1  # resumed
    _write_all(w, obj, fpose, cdir, entries=w.pending())
    w.finalize()
    assert GraspShard(path).solver_settings == settings


def test_resumed_write_equals_uninterrupted(tmp_path):
    obj, fingers, pose, fpose, cdir = _inputs()
    a = tmp_path / "a" / "cube__shard0of1.h5"
    w = GraspShardWriter.create(a, obj, fingers, pose, fpose, cdir, S, generator_version="t")
    _write_all(w, obj, fpose, cdir)
    w.finalize()

    # a generator process killed (os._exit, no close) after 4 of 9 entries
    b = tmp_path / "b" / "cube__shard0of1.h5"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_data_synthetic import box_object, grasp_poses, pad_fingers, ramp_fields
        from defgraspnets.data.grasp_schema import GraspShardWriter
        obj = box_object("cube", divisions=(2, 2, 2)); pose, fpose, cdir = grasp_poses(obj, 3, 0)
        w = GraspShardWriter.create({str(b)!r}, obj, pad_fingers(), pose, fpose, cdir, {S},
                                    generator_version="t")
        for k, g in w.pending()[:4]:
            w.write(k, g, *ramp_fields(obj, fpose[g], cdir[g], obj.youngs_modulus[k], {S}))
        os._exit(0)
    """)
    subprocess.run([sys.executable, "-c", script], check=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert not b.exists() and GraspShardWriter.partial_path_for(b).exists()
    with pytest.raises(ShardSchemaError, match="partial"):
        GraspShard(GraspShardWriter.partial_path_for(b))

    w = GraspShardWriter.create(b, obj, fingers, pose, fpose, cdir, S, generator_version="t")
    assert len(w.pending()) == 9 - 4
    with pytest.raises(RuntimeError, match="not written"):
        w.finalize()
    _write_all(w, obj, fpose, cdir)
    w.finalize()
    da, db = _datasets(a), _datasets(b)
    assert da.keys() == db.keys()
    for key in da:
        if key == "attrs":
            assert da[key] == db[key]
        else:
            np.testing.assert_array_equal(da[key], db[key], err_msg=key)


def test_writer_refuses_bad_input(tmp_path):
    obj, fingers, pose, fpose, cdir = _inputs()
    path = tmp_path / "cube__shard0of1.h5"
    with pytest.raises(ValueError, match="grasp arrays"):
        GraspShardWriter.create(path, obj, fingers, pose[:2], fpose, cdir, S, generator_version="t")
    with pytest.raises(ShardSchemaError, match="form"):
        GraspShardWriter.create(
            tmp_path / "cube.h5", obj, fingers, pose, fpose, cdir, S, generator_version="t"
        )
    w = GraspShardWriter.create(path, obj, fingers, pose, fpose, cdir, S, generator_version="t")
    force, vm, disp, travel = ramp_fields(obj, fpose[0], cdir[0], 1e5, S)
    with pytest.raises(ValueError, match="shape"):
        w.write(0, 0, force, vm[:, :-1], disp, travel)
    vm[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        w.write(0, 0, force, vm, disp, travel)
    w.write(0, 0, force, vm, disp, travel, status=2)  # failures may hold NaN
    w.close()
    # a partial file of a different object is not silently resumed
    other = box_object("cube", divisions=(3, 2, 2))
    with pytest.raises(ValueError, match="different"):
        GraspShardWriter.create(path, other, fingers, pose, fpose, cdir, S, generator_version="t")


def _finished(tmp_path) -> Path:
    obj, fingers, pose, fpose, cdir = _inputs(grasps=2)
    w = GraspShardWriter.create(
        tmp_path / "cube__shard0of1.h5", obj, fingers, pose, fpose, cdir, S, generator_version="t"
    )
    _write_all(w, obj, fpose, cdir)
    return w.finalize()


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda f: f.attrs.__setitem__("schema", "defgraspnets.grasps/0"), "not supported"),
        (lambda f: f.attrs.__delitem__("schema"), "'schema' missing"),
        (lambda f: f.attrs.__delitem__("object_category"), "missing root attributes"),
        (lambda f: f.__delitem__("ramp/displacement"), "/ramp/displacement missing"),
        (
            lambda f: (
                f.__delitem__("material/density"),
                f.create_dataset("material/density", data=np.ones(2)),
            ),
            r"dimension 0 is 2 but K=3",
        ),
        (
            lambda f: (
                f.__delitem__("object/tets"),
                f.create_dataset("object/tets", data=np.zeros((3, 4), "i4")),
            ),
            "dtype int32",
        ),
        (lambda f: f["object/points"].__setitem__((0, 0), np.nan), "NaN"),
        (lambda f: f["ramp/force"].__setitem__((0, 0, 0), np.nan), r"force\[k=0, g=0\]"),
    ],
)
def test_reader_rejects_bad_files(tmp_path, corrupt, message):
    path = _finished(tmp_path)
    with h5py.File(path, "a") as f:
        corrupt(f)
    with pytest.raises(ShardSchemaError, match=message):
        GraspShard(path)


def test_reader_missing_and_non_hdf5(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        GraspShard(tmp_path / "nope__shard0of1.h5")
    bad = tmp_path / "junk__shard0of1.h5"
    bad.write_text("not hdf5")
    with pytest.raises(ShardSchemaError, match="not a readable HDF5"):
        GraspShard(bad)
