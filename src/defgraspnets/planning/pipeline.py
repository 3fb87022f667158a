r"""The sample-and-refine planning run of thesis §7.7, as one call: what ``scripts/plan_grasps.py`` runs.

1. sample N antipodal grasps of the object (seeded), score all N in batched forward passes;
2. the ``n_select`` predicted lowest-Q ("low") and highest-Q ("high") grasps; refine the low ones by
   minimizing Q and the high ones by maximizing it (``refine_steps`` gradient steps, one batch each);
3. the planned grasp: the best refined grasp in the objective's sense;
4. with ``verify``: simulate low, high, ``n_select`` random others, and both refined groups in the FEM
   squeeze (one batched problem), report the threshold hits (:func:`.verify.threshold_hits`), Kendall's tau
   of predicted vs simulated Q, and the box plot of simulated Q per group (Fig. 7.4).

Writes ``plan.json`` (everything, SI units), ``grasps.png`` (best and worst grasps, predicted stress) and,
when verifying, ``verification.png``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from defgraspnets.eval.metrics import kendall_tau
from defgraspnets.eval.report import write_json
from defgraspnets.grasp.sampler import sample_antipodal_grasps

from .planner import GraspPlanner, RefinementResult
from .plots import plot_grasps, plot_verification
from .verify import GraspPoses, simulate_grasps, threshold_hits

__all__ = ["plan_grasps"]

_log = logging.getLogger(__name__)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _refined_record(r: RefinementResult, source: np.ndarray) -> list[dict]:
    return [
        {
            "sample": int(source[i]),
            "initial_q": r.initial_q[i],
            "q": r.q[i],
            "pose": r.poses[i].tolist(),
            "closing_distance": r.closing_distance[i].tolist(),
            "translation_m": r.translation[i],
            "rotation_rad": r.rotation[i],
            "steps_accepted": int((r.accepted[:, i] > 0).sum()),
        }
        for i in range(len(source))
    ]


def plan_grasps(
    planner: GraspPlanner,
    out_dir: str | Path,
    n_samples: int = 100,
    seed: int = 0,
    friction: float = 0.7,
    n_select: int = 10,
    refine_steps: int = 12,
    refine_options: dict | None = None,
    verify: bool = False,
    verify_steps: int = 10,
    fem_device=None,
    poisson_ratio: float = 0.3,
    density: float = 1000.0,
    material_model: str = "neohookean",
    progress: bool = True,
) -> dict:
    """Run the planning pipeline (module docstring) and write its outputs to ``out_dir``; returns the
    report (also in ``plan.json``)."""
    if n_samples < 1 or n_select < 1:
        raise ValueError(f"n_samples and n_select must be >= 1, got {n_samples}, {n_select}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    obj = planner.objective
    mesh = planner.mesh
    timings = {}

    t = time.perf_counter()
    grasps = sample_antipodal_grasps(
        mesh, n_samples, planner.gripper, friction_coefficient=friction, seed=seed, progress=progress
    )
    timings["sample_s"] = time.perf_counter() - t
    if len(grasps) < 2 * n_select:
        raise RuntimeError(
            f"only {len(grasps)} antipodal grasps found on {mesh.name!r}; need at least 2 * n_select = "
            f"{2 * n_select} (lower n_select or check the object's size against the gripper's 80 mm opening)"
        )
    _sync(planner.device)
    t = time.perf_counter()
    q, feasible, _ = planner.score(grasps.poses)
    _sync(planner.device)
    timings["score_s"] = time.perf_counter() - t
    _log.info("scored %d grasps in %.3f s (%d feasible)", len(q), timings["score_s"], feasible.sum())
    ok = np.flatnonzero(feasible)
    if len(ok) < 2 * n_select:
        raise RuntimeError(f"only {len(ok)} of {len(q)} sampled grasps are feasible for the network")
    by_q = ok[np.argsort(q[ok], kind="stable")]
    low, high = by_q[:n_select], by_q[::-1][:n_select]

    options = dict(refine_options or {})
    refined = {}
    for name, idx, sense in (("low", low, "minimize"), ("high", high, "maximize")):
        refined[name] = planner.refine(
            grasps.poses[idx], refine_steps, sense=sense, progress=progress, **options
        )
        r = refined[name]
        timings[f"refine_{name}_s"] = r.seconds
        _log.info(
            "refined %d %s grasps x %d steps in %.2f s: predicted Q %.4g -> %.4g (median)",
            len(idx), name, refine_steps, r.seconds, np.median(r.initial_q), np.median(r.q),
        )  # fmt: skip
    best_group = refined["low"] if obj.sense == "minimize" else refined["high"]
    best_source = low if obj.sense == "minimize" else high
    b = int(np.argmin(obj.sign * best_group.q))

    report = {
        "object": mesh.name,
        "vertices": mesh.num_vertices,
        "youngs_modulus_pa": planner.youngs_modulus,
        "force_n": planner.force,
        "objective": {"name": obj.name, "terms": obj.terms, "sense": obj.sense, "units": obj.units},
        "displacement_target": planner.predictor.displacement_target,
        "device": str(planner.device),
        "timings": timings,
        "samples": [
            {
                "pose": grasps.poses[i].tolist(),
                "closing_distance": grasps.closing_distances[i].tolist(),
                "q": q[i],
                "feasible": bool(feasible[i]),
            }
            for i in range(len(q))
        ],
        "ranking": [int(i) for i in (by_q if obj.sense == "minimize" else by_q[::-1])],
        "low": low.tolist(),
        "high": high.tolist(),
        "refined_low": _refined_record(refined["low"], low),
        "refined_high": _refined_record(refined["high"], high),
        "best": {
            "sample": int(best_source[b]),
            "q": best_group.q[b],
            "pose": best_group.poses[b].tolist(),
            "closing_distance": best_group.closing_distance[b].tolist(),
        },
    }

    # best and worst grasps (in the objective's sense), refined, with their predicted stress
    good, bad = (
        (refined["low"], refined["high"]) if obj.sense == "minimize" else (refined["high"], refined["low"])
    )
    k = min(3, n_select)
    show_g = np.argsort(obj.sign * good.q)[:k]
    show_b = np.argsort(-obj.sign * bad.q)[:k]
    poses = np.concatenate([good.poses[show_g], bad.poses[show_b]])
    closing = np.concatenate([good.closing_distance[show_g], bad.closing_distance[show_b]])
    with torch.no_grad():
        pred = planner.evaluate(poses, keep_prediction=True).prediction
    gripper = planner.gripper
    finger_v = np.stack(
        [
            np.stack([v for v, _ in gripper.finger_meshes(p, gripper.opening_from_closing(c))])
            for p, c in zip(poses, closing)
        ]
    )
    unit = obj.units
    titles = [f"best {i + 1}: Q = {good.q[j]:.4g} {unit}" for i, j in enumerate(show_g)] + [
        f"worst {i + 1}: Q = {bad.q[j]:.4g} {unit}" for i, j in enumerate(show_b)
    ]
    report["figures"] = {
        "grasps": str(
            plot_grasps(
                out / "grasps.png",
                mesh.points,
                mesh.surface_faces,
                pred.stress.detach().cpu().double().numpy(),
                finger_v,
                gripper.pad_mesh[1],
                titles,
                f"{mesh.name}, E = {planner.youngs_modulus:.3g} Pa, F = {planner.force:g} N, {obj.name} "
                f"(refined, {refine_steps} steps)",
                columns=k,
            )
        )
    }

    if verify:
        rng = np.random.default_rng(seed)
        rest = np.setdiff1d(ok, np.concatenate([low, high]))
        rand = rng.choice(rest, size=min(n_select, len(rest)), replace=False)
        groups = {
            "low": GraspPoses(grasps.poses[low], grasps.closing_distances[low]),
            "high": GraspPoses(grasps.poses[high], grasps.closing_distances[high]),
            "random": GraspPoses(grasps.poses[rand], grasps.closing_distances[rand]),
            "low refined": GraspPoses(refined["low"].poses, refined["low"].closing_distance),
            "high refined": GraspPoses(refined["high"].poses, refined["high"].closing_distance),
        }
        batch = GraspPoses(
            np.concatenate([g.poses for g in groups.values()]),
            np.concatenate([g.closing_distances for g in groups.values()]),
        )
        sim = simulate_grasps(
            mesh, batch, planner.youngs_modulus, obj, planner.force, verify_steps, friction,
            poisson_ratio, density, planner.gripper, material_model, device=fem_device, progress=progress,
            displacement_target=planner.predictor.displacement_target,
        )  # fmt: skip
        timings["verify_s"] = sim.seconds
        bounds = np.cumsum([0] + [len(g) for g in groups.values()])
        true_q = {n: sim.q[bounds[i] : bounds[i + 1]] for i, n in enumerate(groups)}
        n_low, n_high, n_rand = len(low), len(high), len(rand)
        sampled_true = sim.q[: n_low + n_high + n_rand]
        hits = threshold_hits(sampled_true, np.arange(n_low), n_low + np.arange(n_high))
        predicted = np.concatenate([q[low], q[high], q[rand]])
        finite = np.isfinite(sampled_true)
        all_predicted = np.concatenate([predicted, refined["low"].q, refined["high"].q])
        all_finite = np.isfinite(sim.q)
        report["verification"] = {
            **hits,
            "kendall_tau_sampled": kendall_tau(predicted[finite], sampled_true[finite]),
            "random_indices": rand.tolist(),
            "true_q": {n: v.tolist() for n, v in true_q.items()},
            "predicted_q": {
                "low": q[low].tolist(),
                "high": q[high].tolist(),
                "random": q[rand].tolist(),
                "low refined": refined["low"].q.tolist(),
                "high refined": refined["high"].q.tolist(),
            },
            "kendall_tau_all": kendall_tau(all_predicted[all_finite], sim.q[all_finite]),
            "median_abs_error_q": float(np.median(np.abs(all_predicted - sim.q)[all_finite]))
            if all_finite.any()
            else float("nan"),
            "fem_steps": verify_steps,
        }
        report["figures"]["verification"] = str(
            plot_verification(
                out / "verification.png",
                {"sampled": sampled_true, **true_q},
                f"simulated {obj.name.split('_', 1)[1]} [{unit}]",
                f"{mesh.name}: FEM ground truth of the planner's grasps",
            )
        )
        _log.info(
            "verification: %.0f %% of threshold grasps hit (low %.0f %%, high %.0f %%); "
            "%d of %d FEM ramps failed",
            100 * hits["hit_rate"], 100 * hits["low_hits"], 100 * hits["high_hits"],
            int((~sim.converged).sum()), len(batch),
        )  # fmt: skip

    write_json(out / "plan.json", report)
    return report
