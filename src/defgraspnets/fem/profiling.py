"""Where a solve spends its time: synchronized wall-clock seconds per phase of the Newton loop.

    with PhaseTimer(solver) as phases:
        squeeze_ramp(solver, 15.0, 50)
    phases.summary()  # {"linear_solve": {"seconds": ..., "calls": ...}, ...}

Each phase is one method of :class:`~defgraspnets.fem.solver.QuasiStaticSolver`; the timer wraps it on
this instance only (the class and other solvers are untouched) and synchronizes the device (Warp and, on
CUDA, PyTorch's dense solves) before and after every call, so the seconds are the phase's own and not
whatever asynchronous work happened to finish inside it. A phase called inside another (the assembly of
the reaction forces inside ``results``) counts for itself only, not for the outer phase too. The
synchronization costs time itself: profile a run, then time it without the timer
(``scripts/benchmark_fem.py profile_phases=true`` records both).
"""

from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
import warp as wp

#: phase name -> solver method: everything of a Newton iteration but its bookkeeping
PHASES = {
    "assemble": "_assemble",  # energy gradient and Hessian (elasticity, contact, loads) and constraints
    "linear_solve": "_linear_solve",  # the Newton step (dense / sparse direct / CG / AMG)
    "line_search": "_line_search",  # Armijo backtracking: trial states and their energies
    "friction_relag": "_relag_friction",  # lagged normal forces (Aitken relaxation)
    "friction_check": "_friction_inconsistent",  # lag consistency of converged states
    "start_increment": "_start_increment",  # predictor and loads of a load increment
    "commit": "_commit",  # accept converged states (friction memory, predictor data)
    "results": "_results",  # the equilibria returned (stress, contact forces, reactions), per level
}


def synchronize(device) -> None:
    """Wait for Warp's and, on CUDA, PyTorch's queued work on ``device``."""
    wp.synchronize_device(device)
    if device.is_cuda:
        import torch

        torch.cuda.synchronize(wp.device_to_torch(device))


class PhaseTimer:
    """Context manager timing the :data:`PHASES` of one solver (module docstring)."""

    def __init__(self, solver):
        self.solver = solver
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.wall = 0.0
        self._start = 0.0
        self._inner: list[float] = []  # per running phase: seconds of the phases called inside it

    def _sync(self):
        synchronize(self.solver.device)

    def _wrap(self, phase: str, method):
        def timed(*args, **kwargs):
            self._sync()
            start = time.perf_counter()
            self._inner.append(0.0)
            try:
                return method(*args, **kwargs)
            finally:
                self._sync()
                seconds = time.perf_counter() - start
                self.seconds[phase] += seconds - self._inner.pop()
                self.calls[phase] += 1
                if self._inner:
                    self._inner[-1] += seconds

        return timed

    def __enter__(self) -> PhaseTimer:
        for phase, name in PHASES.items():
            setattr(self.solver, name, self._wrap(phase, getattr(self.solver, name)))
        self._sync()
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self._sync()
        self.wall += time.perf_counter() - self._start
        for name in PHASES.values():
            self.solver.__dict__.pop(name, None)  # back to the class's methods

    def summary(self) -> dict:
        """Seconds and calls per phase, the rest of the wall time as ``"other"``, and the wall time."""
        out = {p: {"seconds": round(self.seconds[p], 4), "calls": self.calls[p]} for p in PHASES}
        out["other"] = {"seconds": round(self.wall - sum(self.seconds.values()), 4), "calls": 0}
        out["wall_seconds"] = round(self.wall, 4)
        return out


def time_linear_solves(
    solver, methods=("dense", "banded"), counts=(1, 16), repeats: int = 3, seed: int = 0
) -> dict:
    """Seconds to factor and solve the Newton systems of a solver's current state with each factorizing
    linear solver of :class:`~defgraspnets.fem.system.BatchedSystem` (``"dense"``, ``"banded"``,
    ``"direct"``), for the first ``count`` problems of its batch at once.

    The Hessians are the solver's own, assembled at its current state (contacts, friction, gas and
    constraints included); the right-hand sides are random. Each timed call starts without stored
    factors and is synchronized (Warp and PyTorch). Returns {"methods": {method: [{"problems", "seconds"
    (best of ``repeats``), "seconds_all", "residual"}, ...]}, "max_relative_difference": largest
    |x_method - x_first| / |x_first| over the problems, "unknowns", "banded_flops_ratio"}."""
    B, sysm = solver.batch_size, solver.system
    active = solver._active_array(np.ones(B, dtype=bool))
    solver._assemble(active)
    rng = np.random.default_rng(seed)
    rhs = rng.normal(size=(B, 3 * solver.rows_per_problem)) * solver._free.numpy().reshape(1, -1)
    out = {
        "methods": {},
        "unknowns": int(rhs.shape[1]),
        "banded_flops_ratio": sysm.banded_layout().flops_ratio(),
    }
    solutions = {}
    for method in methods:
        solve = getattr(sysm, f"solve_{method}")
        rows = []
        for count in counts:
            count = min(int(count), B)
            b = rhs.copy()
            b[count:] = 0.0
            seconds, residual = [], 0.0
            for _ in range(repeats):
                sysm.forget_factors()
                sysm.rhs.assign(b.reshape(-1, 3))
                synchronize(solver.device)
                start = time.perf_counter()
                _, residual = solve()
                synchronize(solver.device)
                seconds.append(time.perf_counter() - start)
            rows.append(
                {"problems": count, "seconds": min(seconds), "seconds_all": seconds, "residual": residual}
            )
            solutions[method] = sysm.increment.numpy().reshape(B, -1)[:count].copy()
        out["methods"][method] = rows
    sysm.forget_factors()
    first = solutions[methods[0]]
    out["max_relative_difference"] = max(
        float(np.max(np.linalg.norm(x - first[: len(x)], axis=1) / np.linalg.norm(first[: len(x)], axis=1)))
        for x in solutions.values()
    )
    return out
