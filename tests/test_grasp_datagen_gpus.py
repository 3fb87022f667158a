"""scripts/grasp_datagen_gpus.sh: an object set dealt round-robin to worker processes, resumable."""

import os
import subprocess
from pathlib import Path

from defgraspnets.data.grasp_schema import GraspShard

ROOT = Path(__file__).resolve().parents[1]
SET = ["ellipsoid_20x20x20", "cylinder_r20_h40", "cuboid_30x30x30"]  # configs/objects/ci_small.yaml


def _run(tmp_path, *args):
    env = dict(os.environ, OUT=str(tmp_path / "out"), OMP_NUM_THREADS="1")
    cmd = ["bash", str(ROOT / "scripts" / "grasp_datagen_gpus.sh"), *args]
    return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


def test_workers_share_the_object_set_and_a_rerun_resumes(tmp_path):
    overrides = ["num_grasps=2", "steps=2", "youngs_modulus=[1e6]", f"paths.data_dir={tmp_path / 'data'}"]
    done = _run(tmp_path, "0", "ci_small", *overrides)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    workers = [line for line in summary if line.startswith("worker")]
    assert len(workers) == 2 and all("(cpu, rc 0)" in w for w in workers)
    # round-robin: worker 0 gets objects 0 and 2, worker 1 object 1, each object once
    w0 = next(w for w in workers if w.startswith("worker 0"))
    w1 = next(w for w in workers if w.startswith("worker 1"))
    assert w0.endswith(f"{SET[0]} {SET[2]}") and w1.endswith(SET[1])
    for name in SET:
        shard = GraspShard(tmp_path / "data" / "grasps" / f"{name}__shard0of1.h5")
        assert shard.num_grasps == 2 and shard.num_moduli == 1
    again = _run(tmp_path, "0", "ci_small", *overrides)
    assert again.returncode == 0
    assert again.stdout.count("already finished") == len(SET)


def test_an_unknown_object_set_is_named(tmp_path):
    done = _run(tmp_path, "0", "no_such_set")
    assert done.returncode == 2 and "configs/objects/no_such_set.yaml" in done.stderr
