"""Benchmark grasp planning with DefGraspNets and write the timings as JSON.

    python scripts/benchmark_planning.py               # 2-core CPU
    python scripts/benchmark_planning.py device=cuda   # goals: score 100 grasps <= 50 ms,
                                                       # refine 100 x 12 steps <= 5 s within 40 GB

Scoring is timed end to end (finger joint states, multigraph, forward pass, objective) as the median of
``repeats`` warm runs with the stage timer off; then ``repeats`` more runs with
:class:`~defgraspnets.planning.timing.StageTimer` on (device synchronized around every stage) give
``score_stages``, seconds per scoring call of

    fingers     finger joint states from the poses (analytic closing distances), finger poses and vertices
    graph       multigraph construction: contact search, contact-edge padding, node and edge indices
    features    featurization and normalization (edge vectors, lengths, force channel)
    network     encode-process-decode forward and output scaling
    objective   Q and feasibility

Refinement runs once after a warm-up (when compiling, a whole refinement with another annealing seed, which
compiles every padded batch size; else two grasps, one step), with the timer
on: ``refine_stages`` holds the same stages summed over the run plus ``refine.gradient`` (forward passes with
autograd), ``refine.backward``, ``refine.trial`` (line-search forward passes without gradients, and the
initial evaluation) and ``refine.collisions``, each with its calls and seconds per call, and the numbers of
grasps evaluated; ``refine_evaluations`` summarizes them. With ``compile`` the JSON counts the graphs
Dynamo compiled in each phase (``compiled_graphs``): after the warm-ups, a phase that compiles is a
recompilation. Config: configs/benchmark_planning.yaml.
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

PREDICTOR_OPTIONS = (
    "precision",
    "compile",
    "activation_checkpointing",
    "static_shapes",
    "share_object",
    "fused_message_passing",
    "contact_backend",
)
PLANNER_OPTIONS = ("pad_levels", "compile_geometry")  # GraspPlanner
REFINE_OPTIONS = ("reuse_rejected",)  # GraspPlanner.refine


def _network(cfg):
    import torch

    from defgraspnets.models.meshgraphnet import DefGraspNet

    if cfg.ckpt_path:
        from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

        module = DefGraspNetsModule.load_from_checkpoint(cfg.ckpt_path, map_location="cpu")
        return module.net, module.contact_radius_m, f"checkpoint {Path(cfg.ckpt_path).name}"
    torch.manual_seed(0)
    net = DefGraspNet(latent=cfg.latent, num_blocks=cfg.num_blocks, hidden_layers=cfg.hidden_layers)
    for norm in net.normalizers:  # placeholder statistics: timing only
        norm.accumulate(torch.randn(64, norm.dim, dtype=torch.float64))
        norm.finalize()
    return net, 0.005, "random weights, placeholder statistics"


class _Compiles:
    """Graphs compiled by Dynamo per phase (``torch._dynamo.utils.counters``)."""

    def __init__(self):
        self.last = self._graphs()
        self.phases: dict[str, int] = {}

    @staticmethod
    def _graphs() -> int:
        from torch._dynamo.utils import counters

        return int(counters["stats"]["unique_graphs"])

    def mark(self, phase: str) -> None:
        now = self._graphs()
        self.phases[phase] = now - self.last
        self.last = now


def _evaluations(stages: dict) -> dict:
    """Forward / backward evaluation counts and seconds per evaluation of a refinement."""

    def get(name, key):
        return stages.get(name, {}).get(key, 0)

    return {
        "forward_grad": get("refine.gradient", "calls"),
        "forward_grad_s_each": get("refine.gradient", "seconds_per_call"),
        "backward": get("refine.backward", "calls"),
        "backward_s_each": get("refine.backward", "seconds_per_call"),
        "forward_trial": get("refine.trial", "calls"),
        "forward_trial_s_each": get("refine.trial", "seconds_per_call"),
        "grasps_grad": get("refine.gradient_grasps", "count"),
        "grasps_trial": get("refine.trial_grasps", "count"),
        "collisions_s": get("refine.collisions", "seconds"),
    }


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_planning")
def main(cfg: DictConfig) -> None:
    import copy

    import torch

    from defgraspnets.eval.machine import machine_info
    from defgraspnets.grasp.datagen import structured_box
    from defgraspnets.grasp.sampler import sample_antipodal_grasps
    from defgraspnets.models.predictor import DefGraspNetsPredictor
    from defgraspnets.planning import PRESETS, GraspPlanner
    from defgraspnets.planning.timing import StageTimer

    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
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
        v = OmegaConf.to_container(v, resolve=True)
        if v.get("precision") == "bf16" and not cuda:
            continue
        options = {k: v[k] for k in PREDICTOR_OPTIONS if k in v}
        predictor = DefGraspNetsPredictor(copy.deepcopy(net), radius, device=dev, **options)
        planner = GraspPlanner(
            predictor,
            mesh,
            cfg.youngs_modulus,
            PRESETS["min_max_stress"],
            cfg.force,
            **{k: v[k] for k in PLANNER_OPTIONS if k in v},
        )
        refine_options = {k: v[k] for k in REFINE_OPTIONS if k in v}
        row = {
            "name": v["name"],
            **v,
            "static_shapes": predictor.static_shapes,
            "share_object": predictor.share_object,
            "fused_message_passing": predictor.fused_message_passing,
            "compile_geometry": planner.compile_geometry,
        }
        compiles = _Compiles()
        t = time.perf_counter()
        planner.score(grasps.poses)  # warm-up (compilation)
        sync()
        row["first_score_s"] = time.perf_counter() - t
        compiles.mark("first_score")
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
        timer = StageTimer(dev)
        planner.timer = timer
        for _ in range(cfg.repeats):
            planner.score(grasps.poses)
        planner.timer = None
        row["score_stages"] = timer.summary(repeats=cfg.repeats)
        compiles.mark("score")
        split = ", ".join(f"{k} {1e3 * s['seconds']:.1f}" for k, s in row["score_stages"].items())
        print(
            f"{v['name']}: score {len(grasps)} grasps {1e3 * row['score_s']:.1f} ms (median of {cfg.repeats})"
        )
        print(f"{v['name']}: score stages [ms]: {split}")
        if cfg.refine:
            t = time.perf_counter()
            if v.get("compile") or planner.compile_geometry:  # warm-up: compiles every batch size
                planner.refine(grasps.poses, steps=cfg.refine_steps, seed=1, **refine_options)
            else:  # warm-up of the backward pass
                planner.refine(grasps.poses[:2], steps=1, **refine_options)
            sync()
            row["refine_warmup_s"] = time.perf_counter() - t
            compiles.mark("refine_warmup")
            if cuda:
                torch.cuda.reset_peak_memory_stats(dev)
            timer = StageTimer(dev)
            planner.timer = timer
            sync()
            try:
                r = planner.refine(grasps.poses, steps=cfg.refine_steps, **refine_options)
                sync()
                row["refine_s"] = r.seconds
                row["refine_accepted_steps"] = int((r.accepted > 0).sum())
                row["refine_stages"] = timer.summary()
                row["refine_evaluations"] = _evaluations(row["refine_stages"])
                if cuda:
                    row["refine_peak_memory_gb"] = torch.cuda.max_memory_allocated(dev) / 2**30
                e = row["refine_evaluations"]
                print(
                    f"{v['name']}: refine {len(grasps)} x {cfg.refine_steps} steps {r.seconds:.2f} s: "
                    f"{e['forward_grad']} forward+grad x {e['forward_grad_s_each']:.3f} s, "
                    f"{e['backward']} backward x {e['backward_s_each']:.3f} s, "
                    f"{e['forward_trial']} trial forward x {e['forward_trial_s_each']:.3f} s "
                    f"({e['grasps_trial']} grasps), collisions {e['collisions_s']:.2f} s"
                )
            except torch.OutOfMemoryError as e:
                row["refine_error"] = f"out of memory: {str(e)[:200]}"
                print(f"{v['name']}: refine out of memory")
            finally:
                planner.timer = None
            compiles.mark("refine")
        if predictor.static_shapes:
            row["contact_capacity"] = {str(k): c for k, c in predictor.contact_capacities.items()}
        if v.get("compile") or planner.compile_geometry:
            row["compiled_graphs"] = compiles.phases
        result["variants"].append(row)
        out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
