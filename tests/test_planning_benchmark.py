"""scripts/benchmark_planning.py on the CPU, tiny: end-to-end scoring time, the time split by stage, and the
refinement's forward / backward evaluations in the JSON."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_planning_writes_stage_split(tmp_path):
    out = tmp_path / "planning.json"
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "benchmark_planning.py"),
        "threads=1",
        "n_grasps=4",
        "object.size=[0.03,0.03,0.03]",
        "object.divisions=[3,3,3]",
        "latent=8",
        "num_blocks=1",
        "hidden_layers=1",
        "repeats=1",
        "refine_steps=1",
        "variants=[{name: fp32, precision: fp32, activation_checkpointing: true}]",
        f"out={out}",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    (row,) = json.loads(out.read_text())["variants"]
    assert row["score_s"] > 0 and not row["static_shapes"] and row["share_object"]
    stages = row["score_stages"]
    assert set(stages) == {"fingers", "graph", "features", "network", "objective"}
    assert sum(s["seconds"] for s in stages.values()) > 0
    e = row["refine_evaluations"]
    assert e["forward_grad"] == 1 and e["backward"] == 1 and e["forward_trial"] >= 1
    assert e["grasps_grad"] == 4 and e["forward_grad_s_each"] > 0
    assert row["refine_stages"]["refine.gradient"]["calls"] == 1
