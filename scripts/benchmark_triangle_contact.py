"""Sub-vertex FEM contact on the membrane: force against depth of a small sphere (default the thesis's 1 cm
fingertip) at four landing points of the coarse (cap 8) membrane, with vertex contact and with contact points
on the triangles (``contact_subdivisions`` n), against finer membranes.

    python scripts/benchmark_triangle_contact.py
    python scripts/benchmark_triangle_contact.py 'configs=[[8,1],[8,3],[16,1]]' radius=0.01
    python scripts/benchmark_triangle_contact.py 'configs=[[16,2],[24,1]]' out=benchmarks/x.json

Config: configs/benchmark_triangle_contact.yaml; all logic in :mod:`defgraspnets.tactile.landing_study`.
Results: ``benchmarks/fem_triangle_contact_cpu.md``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

log = logging.getLogger("benchmark_triangle_contact")


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_triangle_contact")
def main(cfg: DictConfig) -> dict:
    import warp as wp

    from defgraspnets.tactile.landing_study import run_landing_study

    wp.config.quiet = True
    wp.set_device(cfg.device)
    out = Path(cfg.out) if cfg.out else Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    if not cfg.out:
        out = out / "triangle_contact.json"

    def report(cap, n, name, run):
        forces = " ".join("  fail" if f is None else f"{f:6.3f}" for f in run["force"])
        log.info("cap %2d n %d %-8s F [N] %s   newton %4d  %6.1f s", cap, n, name, forces, run["newton"],
                 run["seconds"])  # fmt: skip

    results = run_landing_study(
        [tuple(c) for c in OmegaConf.to_container(cfg.configs)],
        list(cfg.depths),
        radius=cfg.radius,
        points=list(cfg.points),
        layers=cfg.layers,
        gauge_pressure=cfg.gauge_pressure,
        device=cfg.device,
        report=report,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    log.info("wrote %s", out)
    return results


if __name__ == "__main__":
    main()
