"""Benchmark grasp planning with DefGraspNets and write the timings as JSON.

    python scripts/benchmark_planning.py               # 2-core CPU
    python scripts/benchmark_planning.py device=cuda   # goals: score 100 grasps <= 50 ms,
                                                       # refine 100 x 12 steps <= 5 s within 40 GB

Scoring is timed end to end (finger joint states, multigraph, forward pass, objective) as the median of
``repeats`` warm runs; refinement runs once after a warm-up. Config: configs/benchmark_planning.yaml.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402


def _network(cfg):
    import torch

    from defgraspnets.models.meshgraphnet import DefGraspNet

    if cfg.ckpt_path:
        from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

        module = DefGraspNetsModule.load_from_checkpoint(cfg.ckpt_path, map_location="cpu")
        return module.net, module.contact_radius_m, "checkpoint"
    torch.manual_seed(0)
    net = DefGraspNet(latent=cfg.latent, num_blocks=cfg.num_blocks, hidden_layers=cfg.hidden_layers)
    for norm in net.normalizers:  # placeholder statistics: timing only
        norm.accumulate(torch.randn(64, norm.dim, dtype=torch.float64))
        norm.finalize()
    return net, 0.005, "random weights, placeholder statistics"


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_planning")
def main(cfg: DictConfig) -> None:
    import copy

    import torch

    from defgraspnets.eval.machine import machine_info
    from defgraspnets.grasp.datagen import structured_box
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.models.predictor import DefGraspNetsPredictor
    from defgraspnets.planning import PRESETS, GraspPlanner

    dev = torch.device(cfg.device)
    cuda = dev.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(dev)

    mesh = structured_box(cfg.object.size, cfg.object.divisions)
    grasps = sample_antipodal_grasps(mesh, cfg.n_grasps, seed=0)
    net, radius, weights = _network(cfg)
    result = {
        "machine": machine_info(cfg.device),
        "device": cfg.device,
        "object": {"name": mesh.name, "vertices": mesh.num_vertices, "tets": mesh.num_tets},
        "grasps": len(grasps),
        "network": {"latent": cfg.latent, "num_blocks": cfg.num_blocks, "weights": weights},
        "refine_steps": cfg.refine_steps,
        "variants": [],
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for v in cfg.variants:
        if v.precision == "bf16" and not cuda:
            continue
        predictor = DefGraspNetsPredictor(
            copy.deepcopy(net),
            radius,
            device=dev,
            precision=v.precision,
            compile=v.compile,
            activation_checkpointing=v.activation_checkpointing,
        )
        planner = GraspPlanner(predictor, mesh, cfg.youngs_modulus, PRESETS["min_max_stress"], cfg.force)
        row = {"name": v.name, **OmegaConf.to_container(v)}
        t = time.perf_counter()
        planner.score(grasps.poses)  # warm-up (compilation)
        sync()
        row["first_score_s"] = time.perf_counter() - t
        times = []
        for _ in range(cfg.repeats):
            sync()
            t = time.perf_counter()
            q, feasible, _ = planner.score(grasps.poses)
            sync()
            times.append(time.perf_counter() - t)
        row["score_s"] = float(np.median(times))
        row["score_s_all"] = times
        row["feasible"] = int(feasible.sum())
        print(f"{v.name}: score {len(grasps)} grasps {1e3 * row['score_s']:.1f} ms (median of {cfg.repeats})")
        if cfg.refine:
            planner.refine(grasps.poses[:2], steps=1)  # warm-up of the backward pass
            if cuda:
                torch.cuda.reset_peak_memory_stats(dev)
            sync()
            try:
                r = planner.refine(grasps.poses, steps=cfg.refine_steps)
                sync()
                row["refine_s"] = r.seconds
                row["refine_accepted_steps"] = int((r.accepted > 0).sum())
                if cuda:
                    row["refine_peak_memory_gb"] = torch.cuda.max_memory_allocated(dev) / 2**30
                print(f"{v.name}: refine {len(grasps)} x {cfg.refine_steps} steps {r.seconds:.2f} s")
            except torch.OutOfMemoryError as e:
                row["refine_error"] = f"out of memory: {str(e)[:200]}"
                print(f"{v.name}: refine out of memory")
        result["variants"].append(row)
        out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
