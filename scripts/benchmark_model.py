"""Benchmark DefGraspNets training throughput and inference latency and write them as JSON.

    python scripts/benchmark_model.py                  # quick CPU run (< 1 min on 2 cores, small graphs)

Thesis-size graphs and network on one H100 (goal of the issue: training >= 350 graphs/s; the thesis trains
~27 graphs/s on an RTX 3090):

    python scripts/benchmark_model.py device=cuda 'variants=${variant_sets.gpu}' \
        object.size=[0.05,0.05,0.05] object.divisions=[10,10,12] n_grasps=64 \
        model.latent=128 model.num_blocks=15 model.hidden_layers=2 \
        batch_sizes=[1,8,32] pool_batches=4 warmup=10 iterations=30

(2853 nodes and ~29.8k directed edges per graph.) Measured on one H100 (torch 2.11, 2026-11-23), training
graphs/s at batch 1 / 8 / 32: fp32 14 / 72 / 92, tf32 13 / 85 / 118, bf16 10 / 78 / 130, tf32 compiled
18 / 114 / 206; bf16 compiled 317 at batch 32 and 346 at batch 64 (34 GB; 350 / 357.5 / 363 at batch
64 / 96 / 128 since session 16: fused Adam, compiled gathers by advanced indexing); forward at batch 32:
fp32 223, bf16 compiled 866 graphs/s. Each compiled (variant, batch size, mode) spends 30-95 s compiling in
its warm-up, so the whole command above takes about 20 minutes.

Graphs are built as the grasp data sets build them: ``sample_antipodal_grasps`` on a structured box, the
Franka finger pads at first contact (``finger_contact_poses``), one ``build_grasp_graph`` per grasp and PyG's
``Batch.from_data_list`` (the DataLoader's collation). Targets are synthetic (random fields of the right
shapes, the finger nodes carry a rigid travel along their closing direction); the normalizers are fitted
on the graphs with ``DefGraspNet.fit_normalizers``. The network has random weights.

Training: one step is ``DefGraspNetsModule.training_step`` (its loss; its ``self.log`` calls return at once
without a Trainer), ``backward`` and the step of the optimizer of ``configure_optimizers`` (Adam), as in
Lightning's automatic optimization; the batch is copied host -> device in the step (``transfer``), not
collated there (DataLoader workers do that). ``graphs_per_s = batch_size * iterations / time`` over the
timed iterations after ``warmup`` untimed ones, with ``torch.cuda.synchronize`` before and after.
Inference: the network's forward pass (standardized outputs) under ``torch.inference_mode``, synchronized
per call; the median latency is reported. Variants (``variants``): precision fp32 (TF32 off), tf32
(``torch.backends.cuda.matmul.allow_tf32``), bf16 (``torch.autocast`` bfloat16); the module's own
``torch.compile`` (``model.compile``); activation checkpointing of the message-passing blocks. A
measurement that fails (out of memory, no compiler, ...) is recorded with its error and the rest go on.
Config: configs/benchmark_model.yaml.
"""

from __future__ import annotations

import contextlib
import copy
import gc
import json
import math
import os
import time
import warnings
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

PRECISIONS = ("fp32", "tf32", "bf16")
VARIANT_KEYS = {"name", "precision", "compile", "activation_checkpointing"}


def check_config(cfg: DictConfig) -> list[dict]:
    """The variants as dicts; a ValueError naming the bad entry otherwise."""

    def sizes(key):
        v = list(cfg[key])
        if not all(isinstance(b, int) and b >= 1 for b in v):
            raise ValueError(f"{key} must be a list of integers >= 1, got {v}")
        return v

    sizes("batch_sizes")
    sizes("inference_batch_sizes")
    for key in ("warmup", "iterations", "pool_batches", "n_grasps"):
        if not isinstance(cfg[key], int) or cfg[key] < (0 if key == "warmup" else 1):
            raise ValueError(f"{key} must be an integer >= {0 if key == 'warmup' else 1}, got {cfg[key]!r}")
    variants = []
    for i, v in enumerate(OmegaConf.to_container(cfg.variants, resolve=True)):
        if not isinstance(v, dict):
            raise ValueError(f"variants[{i}] must be a mapping with keys {sorted(VARIANT_KEYS)}, got {v!r}")
        unknown = set(v) - VARIANT_KEYS
        if unknown:
            raise ValueError(
                f"variants[{i}]: unknown keys {sorted(unknown)} (allowed: {sorted(VARIANT_KEYS)})"
            )
        v = {"compile": False, "activation_checkpointing": False, **v}
        v.setdefault("name", f"{v.get('precision')}{'_compiled' if v['compile'] else ''}")
        if v.get("precision") not in PRECISIONS:
            raise ValueError(f"variants[{i}] ({v['name']}): precision must be one of {PRECISIONS}, got "
                             f"{v.get('precision')!r}")  # fmt: skip
        variants.append(v)
    names = [v["name"] for v in variants]
    if len(set(names)) != len(names):
        raise ValueError(f"variant names must be unique, got {names}")
    return variants


def grasp_graphs(cfg: DictConfig):
    """One multigraph per sampled grasp, with synthetic targets; and a description of their sizes."""
    import torch

    from defgraspnets.grasp.datagen import gripper_fingers, structured_box
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.grasp.squeeze import finger_contact_poses
    from defgraspnets.models.graph import (
        NODE_FINGER,
        FingerTemplate,
        ObjectTemplate,
        build_grasp_graph,
        contact_pairs,
    )

    mesh = structured_box(cfg.object.size, cfg.object.divisions)
    grasps = sample_antipodal_grasps(mesh, cfg.n_grasps, seed=cfg.seed)
    if len(grasps) == 0:
        raise RuntimeError(f"no antipodal grasp could be sampled on {mesh.name}")
    fingers = gripper_fingers()
    pose = finger_contact_poses(grasps)  # (G, 2, 4, 4), as the data generator stores them
    closing = pose[:, :, :3, :3] @ fingers.closing_axis  # (G, 2, 3)
    obj = ObjectTemplate.from_tet_mesh(mesh)
    finger = FingerTemplate.from_mesh(fingers.vertices, fingers.faces)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    log_e = np.log10(np.atleast_1d(np.asarray(cfg.youngs_modulus, dtype=float)))  # a range or one value
    graphs = []
    for g in range(len(grasps)):
        vertices = fingers.vertices_at(pose[g])  # (2, V, 3)
        # contact pairs from float64 positions, as GraspFieldDataset.contact_pairs
        pairs = contact_pairs(
            torch.tensor(mesh.points),
            torch.as_tensor(vertices.reshape(-1, 3)),
            float(cfg.contact_radius),
            backend="kdtree",
        )
        data = build_grasp_graph(
            obj,
            finger,
            torch.as_tensor(vertices, dtype=torch.float32),
            torch.as_tensor(closing[g], dtype=torch.float32),
            float(cfg.max_force) * (1.0 - rng.random()),
            float(10 ** rng.uniform(log_e.min(), log_e.max())),
            float(cfg.contact_radius),
            pairs=pairs,
        )
        is_finger = data.node_type == NODE_FINGER
        n = data.num_nodes
        # synthetic targets of the data set's shapes: stress [Pa] (zero on fingers), displacement [m]
        # (fingers: a rigid travel along their closing direction)
        data.stress = torch.where(is_finger, 0.0, 2e4 * torch.rand(n, generator=gen))
        travel = 1e-3 * torch.rand(n, 1, generator=gen)
        data.displacement = torch.where(
            is_finger[:, None], travel * data.closing_dir, 1e-4 * torch.randn(n, 3, generator=gen)
        )
        graphs.append(data)
    contacts = np.array([d.contact_edge_index.shape[1] for d in graphs])
    mesh_edges = graphs[0].mesh_edge_index.shape[1]
    info = {
        "object": mesh.name,
        "object_vertices": mesh.num_vertices,
        "object_tets": mesh.num_tets,
        "finger_vertices": finger.num_nodes,
        "grasps": len(graphs),
        "nodes_per_graph": graphs[0].num_nodes,
        "mesh_edges_per_graph": mesh_edges,
        "contact_edges_per_graph_mean": float(contacts.mean()),
        "contact_edges_per_graph_min": int(contacts.min()),
        "contact_edges_per_graph_max": int(contacts.max()),
        "edges_per_graph_mean": float(mesh_edges + contacts.mean()),
        "edges": "directed (both directions of every mesh edge and contact pair)",
    }
    return graphs, info


def make_batches(graphs, batch_size: int, count: int):
    """``count`` collated batches of ``batch_size`` graphs, cycling through ``graphs``."""
    from torch_geometric.data import Batch

    k = len(graphs)
    return [
        Batch.from_data_list([graphs[(j * batch_size + i) % k] for i in range(batch_size)])
        for j in range(count)
    ]


@contextlib.contextmanager
def precision_context(precision: str, device):
    """TF32 flags for the whole block; returns a factory of the autocast context of one step."""
    import torch

    old = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    tf32 = precision == "tf32"
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32
    try:
        if precision == "bf16":
            yield lambda: torch.autocast(device_type=device.type, dtype=torch.bfloat16)
        else:
            yield contextlib.nullcontext
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def _reset_dynamo() -> None:
    """Fresh torch.compile caches for a compiled variant, with room for its recompilations (batch sizes,
    contact-edge counts, grad and inference mode) before dynamo would silently fall back to eager."""
    import torch._dynamo

    torch._dynamo.reset()
    config = torch._dynamo.config
    key = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"
    setattr(config, key, max(getattr(config, key), 64))


def _dynamo_graphs() -> int:
    import torch._dynamo.utils

    return int(torch._dynamo.utils.counters["stats"]["unique_graphs"])


def _to_device(batch, device):
    """A device copy of a (pinned) host batch; the host batch stays as it is (``Data.to`` works in place)."""
    return copy.copy(batch).to(device, non_blocking=device.type == "cuda")


def _error(e: BaseException) -> str:
    text = f"{type(e).__name__}: {e}".strip()
    return text if len(text) <= 600 else text[:600] + " ..."


def measure_training(module, optimizer, batches, cfg, device, autocast) -> dict:
    import torch

    cuda = device.type == "cuda"
    if cuda and cfg.transfer:
        batches = [copy.copy(b).pin_memory() for b in batches]
    elif not cfg.transfer:
        batches = [_to_device(b, device) for b in batches]

    def step(i: int) -> torch.Tensor:
        batch = batches[i % len(batches)]
        if cfg.transfer:
            batch = _to_device(batch, device)
        optimizer.zero_grad(set_to_none=True)
        with autocast():
            loss = module.training_step(batch, i)
        loss.backward()
        optimizer.step()
        return loss

    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    module.train()
    first = None
    for i in range(cfg.warmup):
        t = time.perf_counter()
        step(i)
        sync()
        first = time.perf_counter() - t if first is None else first
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    sync()
    t = time.perf_counter()
    for i in range(cfg.iterations):
        loss = step(cfg.warmup + i)
    sync()
    seconds = time.perf_counter() - t
    row = {"seconds": seconds, "ms_per_step": 1e3 * seconds / cfg.iterations, "first_step_s": first}
    row["loss"] = float(loss.detach())
    if cuda:
        row["peak_memory_gb"] = torch.cuda.max_memory_allocated(device) / 2**30
    return row


def measure_inference(forward, batches, cfg, device, autocast) -> tuple[dict, float]:
    import torch

    cuda = device.type == "cuda"
    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    if cuda and cfg.transfer:
        batches = [copy.copy(b).pin_memory() for b in batches]
    elif not cfg.transfer:
        batches = [_to_device(b, device) for b in batches]
    times, first = [], None
    with torch.inference_mode():
        for i in range(cfg.warmup + cfg.iterations):
            batch = batches[i % len(batches)]
            if i == cfg.warmup and cuda:
                torch.cuda.reset_peak_memory_stats(device)
            sync()
            t = time.perf_counter()
            if cfg.transfer:
                batch = _to_device(batch, device)
            with autocast():
                out = forward(batch)
            sync()
            dt = time.perf_counter() - t
            if i < cfg.warmup:
                first = dt if first is None else first
            else:
                times.append(dt)
    if not bool(torch.isfinite(out).all()):
        raise FloatingPointError("non-finite network outputs")
    median = float(np.median(times))
    row = {"ms_per_batch": 1e3 * median, "ms_per_batch_all": [1e3 * x for x in times], "first_call_s": first}
    if cuda:
        row["peak_memory_gb"] = torch.cuda.max_memory_allocated(device) / 2**30
    return row, median


def _table(rows: list[dict]) -> str:
    head = f"{'mode':<9} {'variant':<20} {'batch':>5} {'graphs/s':>10} {'ms/step':>9} {'peak GB':>8}  error"
    lines = [head, "-" * len(head)]
    for r in rows:
        ms = r.get("ms_per_step", r.get("ms_per_batch"))
        gps = r.get("graphs_per_s")
        mem = r.get("peak_memory_gb")
        error = (r.get("error") or "").strip().split("\n")[0]
        lines.append(
            f"{r['mode']:<9} {r['variant']:<20} {r['batch_size']:>5} "
            f"{'-' if gps is None else f'{gps:10.1f}':>10} {'-' if ms is None else f'{ms:9.2f}':>9} "
            f"{'-' if mem is None else f'{mem:8.2f}':>8}  {error}"
        )
    return "\n".join(lines)


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_model")
def main(cfg: DictConfig) -> dict:
    import torch
    from tqdm.auto import tqdm

    from defgraspnets.eval.machine import machine_info
    from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

    variants = check_config(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    device = torch.device(cfg.device)
    cuda = device.type == "cuda"
    torch.manual_seed(cfg.seed)

    t = time.perf_counter()
    graphs, graph_info = grasp_graphs(cfg)
    graph_info["build_s"] = time.perf_counter() - t
    model_kwargs = OmegaConf.to_container(cfg.model, resolve=True)
    base = DefGraspNetsModule(**{**model_kwargs, "compile": False})
    base.net.fit_normalizers(
        make_batches(graphs, min(8, len(graphs)), math.ceil(len(graphs) / 8)), progress=False
    )
    state = base.state_dict()

    train_sizes = list(cfg.batch_sizes) if cfg.train else []
    infer_sizes = list(cfg.inference_batch_sizes)
    pools = {b: make_batches(graphs, b, cfg.pool_batches) for b in sorted({*train_sizes, *infer_sizes})}
    result = {
        "benchmark": "defgraspnets_model",
        "machine": machine_info(cfg.device),
        "device": str(device),
        "threads": torch.get_num_threads(),
        "graph": graph_info,
        "network": {
            **model_kwargs,
            "parameters": sum(p.numel() for p in base.net.parameters()),
            "weights": "random; normalizers fitted on the benchmark graphs (synthetic targets)",
        },
        "timing": {
            "train": "training_step (loss) + backward + Adam step per batch, host->device copy included if "
            "transfer; graphs_per_s = batch_size * iterations / wall time of the timed iterations",
            "inference": "forward pass (standardized outputs) under torch.inference_mode, synchronized per "
            "call; graphs_per_s = batch_size / median latency",
        },
        "goal_train_graphs_per_s": cfg.goal_train_graphs_per_s,
        "results": [],
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    warnings.filterwarnings("ignore", message=r".*self\.log\(\)")  # training_step without a Trainer

    jobs = [
        (v, m, b)
        for v in variants
        for m, sizes in (("train", train_sizes), ("inference", infer_sizes))
        for b in sizes
    ]
    bar = tqdm(total=len(jobs), desc="benchmark", unit="run", disable=not cfg.progress)
    for v in variants:
        module = optimizer = None
        setup_error = None
        if v["compile"]:
            _reset_dynamo()
        with precision_context(v["precision"], device) as autocast:
            try:
                module = DefGraspNetsModule(**{**model_kwargs, "compile": bool(v["compile"])})
                module.load_state_dict(state)
                module.to(device)
                for network in module.net.networks:
                    network.activation_checkpointing = bool(v["activation_checkpointing"])
                module.setup("fit")  # the module's own torch.compile of the network (normalizers are fitted)
                optimizer = module.configure_optimizers()["optimizer"]
            except Exception as e:  # noqa: BLE001 - recorded, the other variants go on
                setup_error = _error(e)
            for mode, sizes in (("train", train_sizes), ("inference", infer_sizes)):
                for b in sizes:
                    bar.set_postfix_str(f"{v['name']} {mode} batch {b}")
                    batches = pools[b]
                    row = {"mode": mode, "variant": v["name"]}
                    row.update({k: v[k] for k in ("precision", "compile", "activation_checkpointing")})
                    row.update(
                        batch_size=b,
                        nodes_per_batch=sum(x.num_nodes for x in batches) // len(batches),
                        edges_per_batch=sum(
                            x.mesh_edge_index.shape[1] + x.contact_edge_index.shape[1] for x in batches
                        )
                        / len(batches),
                        iterations=cfg.iterations,
                        warmup=cfg.warmup,
                        error=setup_error,
                    )
                    if setup_error is None:
                        try:
                            if mode == "train":
                                m = measure_training(module, optimizer, batches, cfg, device, autocast)
                                row.update(m, graphs_per_s=b * cfg.iterations / m["seconds"])
                            else:
                                module.eval()
                                forward = module.network  # compiled with the module's own torch.compile
                                m, median = measure_inference(forward, batches, cfg, device, autocast)
                                row.update(m, graphs_per_s=b / median)
                            if not math.isfinite(row.get("loss", 0.0)):
                                row["error"] = f"non-finite loss {row['loss']}"
                        except Exception as e:  # noqa: BLE001 - OOM, compiler missing, ...: recorded
                            row["error"] = _error(e)
                        finally:
                            if optimizer is not None:
                                optimizer.zero_grad(set_to_none=True)
                            gc.collect()
                            if cuda:
                                torch.cuda.empty_cache()
                    if v["compile"]:
                        row["dynamo_unique_graphs"] = _dynamo_graphs()
                    result["results"].append(row)
                    out.write_text(json.dumps(result, indent=2) + "\n")
                    bar.update()
        del module, optimizer
        gc.collect()
        if cuda:
            torch.cuda.empty_cache()
    bar.close()
    g = graph_info
    print(
        f"{g['object']}: {g['object_vertices']} vertices + 2 x {g['finger_vertices']} finger vertices = "
        f"{g['nodes_per_graph']} nodes, {g['mesh_edges_per_graph']} mesh + "
        f"{g['contact_edges_per_graph_mean']:.0f} contact edges per graph; network {model_kwargs}"
    )
    print(_table(result["results"]))
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
