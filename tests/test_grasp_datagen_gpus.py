"""scripts/grasp_datagen_gpus.sh: an object set shared by worker processes on demand, resumable."""

import os
import subprocess
from pathlib import Path

from defgraspnets.data.grasp_schema import GraspShard

ROOT = Path(__file__).resolve().parents[1]
SET = ["ellipsoid_20x20x20", "cylinder_r20_h40", "cuboid_30x30x30"]  # configs/objects/ci_small.yaml


def _run(tmp_path, *args, env=None):
    env = dict(os.environ, OUT=str(tmp_path / "out"), OMP_NUM_THREADS="1", **(env or {}))
    cmd = ["bash", str(ROOT / "scripts" / "grasp_datagen_gpus.sh"), *args]
    return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


def test_workers_share_the_object_set_and_a_rerun_resumes(tmp_path):
    overrides = ["num_grasps=2", "steps=2", "youngs_modulus=[1e6]", f"paths.data_dir={tmp_path / 'data'}"]
    done = _run(tmp_path, "0", "ci_small", *overrides)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    workers = [line for line in summary if line.startswith("worker")]
    assert len(workers) == 2 and all("(cpu, rc 0)" in w for w in workers)
    # by demand: each object claimed by exactly one worker (both walk the whole set), both did some work
    mine = [w.rsplit(": ", 1)[1].split() for w in workers]
    assert sorted(sum(mine, [])) == sorted(SET) and all(mine)
    claimed = [
        (tmp_path / "out" / f"worker_{k}.log").read_text().count("claimed by another worker") for k in (0, 1)
    ]
    assert sum(claimed) == len(SET)  # every object skipped by the worker that did not claim it
    for name in SET:
        shard = GraspShard(tmp_path / "data" / "grasps" / f"{name}__shard0of1.h5")
        assert shard.num_grasps == 2 and shard.num_moduli == 1
    again = _run(tmp_path, "0", "ci_small", *overrides)
    assert again.returncode == 0
    assert again.stdout.count("already finished") == len(SET)


def test_an_unknown_object_set_is_named(tmp_path):
    done = _run(tmp_path, "0", "no_such_set")
    assert done.returncode == 2 and "configs/objects/no_such_set.yaml" in done.stderr


def test_a_bad_worker_count_is_named(tmp_path):
    done = _run(tmp_path, "1", "ci_small", env={"WORKERS_PER_GPU": "0"})
    assert done.returncode == 2 and "WORKERS_PER_GPU must be a positive integer" in done.stderr
