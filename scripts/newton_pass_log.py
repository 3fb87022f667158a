"""Log every Newton pass of a batched FEM run: wall time and the problems iterating in it.

    python scripts/newton_pass_log.py OUT.json scripts/benchmark_tactile.py device=cuda stride=4 limit=64
    python scripts/newton_pass_log.py OUT.json scripts/benchmark_fem.py device=cuda num_grasps=100

Runs the given script (with its Hydra overrides) with ``QuasiStaticSolver._newton_pass`` wrapped, then
writes to OUT.json the number of passes, their total seconds, the problem-passes (problems iterating,
summed over the passes) against the slot-passes (batch size times passes), the seconds and passes
spent with at most 1, 2, 4, ..., 32 problems iterating, and the mean pass time by that count. It shows how
much of a batch's time its slowest problems take alone (the tail) and how a pass's cost grows with
the problems in it.
"""

from __future__ import annotations

import json
import runpy
import sys
import time

import numpy as np


def summarize(log: list[tuple[float, int, int]]) -> dict:
    """Summary of (seconds, problems iterating, batch size) per pass (module docstring)."""
    out: dict = {"passes": len(log)}
    if not log:
        return out
    a = np.array(log, dtype=np.float64)
    d, n, b = a[:, 0], a[:, 1], a[:, 2]
    out.update(pass_seconds=float(d.sum()), problem_passes=int(n.sum()), slot_passes=int(b.sum()))
    for k in (1, 2, 4, 8, 16, 32):
        m = n <= k
        out[f"seconds_working_le_{k}"] = float(d[m].sum())
        out[f"passes_working_le_{k}"] = int(m.sum())
    buckets = ((0, 1), (1, 4), (4, 16), (16, 64), (64, np.inf))
    out["mean_pass_ms_by_working"] = {
        f"{lo:g}-{hi:g}": float(1e3 * d[(n > lo) & (n <= hi)].mean())
        for lo, hi in buckets
        if ((n > lo) & (n <= hi)).any()
    }
    return out


def main(argv: list[str]) -> dict:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    from defgraspnets.fem.solver import QuasiStaticSolver

    out_path, script = argv[0], argv[1]
    log: list[tuple[float, int, int]] = []
    newton_pass = QuasiStaticSolver._newton_pass

    def logged(self, run):
        working, t0 = int(run.working.sum()), time.perf_counter()
        newton_pass(self, run)
        log.append((time.perf_counter() - t0, working, self.batch_size))

    QuasiStaticSolver._newton_pass = logged
    sys.argv = argv[1:]
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as stop:  # Hydra ends its apps with SystemExit
        if stop.code not in (None, 0):
            raise
    finally:
        QuasiStaticSolver._newton_pass = newton_pass
    summary = {"command": " ".join(argv[1:]), **summarize(log)}
    with open(out_path, "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main(sys.argv[1:])
