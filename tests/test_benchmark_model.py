"""scripts/benchmark_model.py on CPU: training and inference rates of every variant in the JSON, graph sizes,
failed variants recorded (not fatal), bad overrides named."""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "benchmark_model.py"

# a 20 mm box of 27 vertices, the Franka pads (640 vertices each), a tiny network, one timed iteration
TINY = [
    "object.size=[0.02,0.02,0.02]",
    "object.divisions=[2,2,2]",
    "n_grasps=2",
    "model.latent=8",
    "model.num_blocks=1",
    "model.hidden_layers=1",
    "batch_sizes=[1,2]",
    "inference_batch_sizes=[2]",
    "warmup=1",
    "iterations=1",
    "threads=1",
    "progress=false",
]
VARIANTS = (
    "variants=[{name:fp32,precision:fp32},{name:tf32,precision:tf32},"
    "{name:bf16_ckpt,precision:bf16,activation_checkpointing:true}]"
)


def _run(tmp_path, *overrides):
    cmd = [sys.executable, str(SCRIPT), *TINY, f"out={tmp_path / 'model.json'}", *overrides]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)


def _expected_graph_size():
    from defgraspnets.grasp.datagen import structured_box
    from defgraspnets.grasp.gripper import FRANKA_HAND
    from defgraspnets.models.graph import unique_edges

    box = structured_box((0.02, 0.02, 0.02), (2, 2, 2))
    pad_vertices, pad_faces = FRANKA_HAND.pad_mesh
    nodes = box.num_vertices + 2 * len(pad_vertices)
    mesh_edges = 2 * (len(unique_edges(box.tets)) + 2 * len(unique_edges(np.asarray(pad_faces))))
    return box.num_vertices, nodes, mesh_edges


def test_benchmark_model_script_writes_rates_of_every_variant(tmp_path):
    done = _run(tmp_path, VARIANTS)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((tmp_path / "model.json").read_text())
    assert report["machine"]["device"] == "cpu" and report["machine"]["cpu_count"] >= 1
    assert report["config"]["model"]["latent"] == 8
    object_vertices, nodes, mesh_edges = _expected_graph_size()
    g = report["graph"]
    assert g["object_vertices"] == object_vertices and g["nodes_per_graph"] == nodes
    assert g["mesh_edges_per_graph"] == mesh_edges
    assert 0 < g["contact_edges_per_graph_min"] <= g["contact_edges_per_graph_max"]
    rows = report["results"]
    # 3 variants x (2 training + 1 inference batch sizes)
    assert [(r["variant"], r["mode"], r["batch_size"]) for r in rows] == [
        (v, m, b)
        for v in ("fp32", "tf32", "bf16_ckpt")
        for m, b in (("train", 1), ("train", 2), ("inference", 2))
    ]
    for r in rows:
        assert r["error"] is None, r
        assert math.isfinite(r["graphs_per_s"]) and r["graphs_per_s"] > 0, r
        assert r["nodes_per_batch"] == r["batch_size"] * nodes
        assert r["edges_per_batch"] >= r["batch_size"] * mesh_edges
        if r["mode"] == "train":
            assert math.isfinite(r["loss"]) and r["ms_per_step"] > 0
            assert r["graphs_per_s"] == pytest.approx(1e3 * r["batch_size"] / r["ms_per_step"])
        else:
            assert r["ms_per_batch"] > 0 and len(r["ms_per_batch_all"]) == 1
    assert rows[-1]["precision"] == "bf16" and rows[-1]["activation_checkpointing"] is True
    assert "graphs/s" in done.stdout and "bf16_ckpt" in done.stdout


def test_benchmark_model_bad_overrides_are_named(tmp_path):
    typo = _run(tmp_path, "batch_size=[4]")
    assert typo.returncode != 0 and "batch_size" in typo.stderr
    bad = _run(tmp_path, "variants=[{name:half,precision:fp16}]")
    assert bad.returncode != 0 and "precision must be one of" in bad.stderr and "fp16" in bad.stderr
    assert not (tmp_path / "model.json").exists()


@pytest.mark.usefixtures("one_torch_thread")
def test_benchmark_model_records_a_failing_variant_and_goes_on(tmp_path, monkeypatch):
    """A variant whose torch.compile fails is recorded with its error; the next variant still runs."""
    import torch
    from hydra import compose, initialize_config_dir

    spec = importlib.util.spec_from_file_location("benchmark_model", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)

    def no_compiler(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(torch, "compile", no_compiler)
    overrides = [o for o in TINY if not o.startswith("threads=")]
    overrides += [
        "variants=[{name:compiled,precision:fp32,compile:true},{name:eager,precision:fp32}]",
        "batch_sizes=[1]",
        "inference_batch_sizes=[1]",
        f"out={tmp_path / 'model.json'}",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("benchmark_model", overrides=overrides)
    script.main(cfg)
    rows = json.loads((tmp_path / "model.json").read_text())["results"]
    assert [(r["variant"], r["mode"]) for r in rows] == [
        ("compiled", "train"),
        ("compiled", "inference"),
        ("eager", "train"),
        ("eager", "inference"),
    ]
    for r in rows[:2]:
        assert r["error"] == "RuntimeError: no compiler here" and "graphs_per_s" not in r
    for r in rows[2:]:
        assert r["error"] is None and r["graphs_per_s"] > 0
