"""Benchmark tactile data generation (thesis §3.3) and write the rate as JSON.

    python scripts/benchmark_tactile.py                                     # 8 poke paths, CPU
    python scripts/benchmark_tactile.py device=cuda stride=4 limit=64 batch_size=64
    python scripts/benchmark_tactile.py dataset=forearm device=cuda         # any datagen/tactile key

Runs :func:`~defgraspnets.tactile.datasets.generate_tactile_from_config` exactly as
``datagen/tactile.py`` does (the shard goes to a temporary directory and is deleted) and records the
seconds per state, the failed readings and the time the whole grid would take at that rate (the poking
grid: goal <= 10 min on one H100). Config: configs/benchmark_tactile.yaml.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

GOAL_MINUTES = {"poke": 10.0}  # issue goal: the 10,000 poking states on one H100


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_tactile")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets.eval.machine import machine_info
    from defgraspnets.tactile.datasets import generate_tactile_from_config
    from defgraspnets.tactile.indenters import forearm_grid, poke_grid

    if cfg.device is not None:
        wp.set_device(cfg.device)
    device = str(wp.get_device())
    kind = "cuda" if device.startswith("cuda") else "cpu"
    config = OmegaConf.to_container(cfg, resolve=True)
    with tempfile.TemporaryDirectory() as tmp:
        counts = generate_tactile_from_config(config, out_path=Path(tmp) / "shard.h5")
    states = counts["samples"] + counts["failed"]
    if states == 0:
        raise ValueError(f"no states were simulated (stride={cfg.stride}, limit={cfg.limit})")
    grid = len(poke_grid()) if cfg.dataset == "poke" else len(forearm_grid()) * cfg.repeats
    per_state = counts["seconds"] / states
    options = counts["solver_options"]
    record = {
        "benchmark": "tactile_datagen",
        "machine": machine_info(device if kind == "cuda" else "cpu"),
        "device": device,
        "dataset": cfg.dataset,
        "membrane": dict(config["membrane"]),
        "indenter": dict(config["indenter"] if cfg.dataset == "poke" else config["forearm"]),
        "gas": dict(config["gas"]),
        "solver": {k: getattr(options, k) for k in ("linear_solver", "rtol", "contact_smoothing")},
        "selection": {"stride": cfg.stride, "limit": cfg.limit, "batch_size": cfg.batch_size},
        # true: the paths of a batch wait for each other at every load step
        "barrier": bool(cfg.barrier),
        "stream": bool(cfg.stream),
        "timing": "generate_tactile_from_config end to end: simulator build and inflation, solves, "
        "rendering, shard writing",
        "paths": counts["paths"],
        "states": states,
        "samples": counts["samples"],
        "failed": counts["failed"],
        # the batch's Newton passes (device-independent work; absent where the shard was already finished)
        "newton_passes": counts.get("newton_passes"),
        "seconds": round(counts["seconds"], 3),
        "seconds_per_state": round(per_state, 4),
        "grid_states": grid,
        "extrapolated_grid_minutes": round(per_state * grid / 60, 2),
        "goal_minutes": GOAL_MINUTES.get(cfg.dataset),
    }
    out = Path(cfg.out or Path(cfg.paths.root_dir) / "benchmarks" / f"tactile_{cfg.dataset}_{kind}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    print(
        json.dumps(
            {
                k: record[k]
                for k in ("states", "failed", "seconds", "seconds_per_state", "extrapolated_grid_minutes")
            }
        )
    )


if __name__ == "__main__":
    main()
