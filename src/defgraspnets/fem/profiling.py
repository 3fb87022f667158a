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

Whether the GPU or the host is the limit (:class:`KernelProfile`, ``profile_kernels=true``): PyTorch's
profiler (CUPTI) records every kernel the process runs, Warp's included, with its start and end on the GPU.
The union of those intervals against the wall time says how busy the GPU was; the host's busiest operations
(self time per PyTorch op and CUDA runtime call, such as ``cudaLaunchKernel``) say what the host did instead.

    with KernelProfile(solver.device) as profile:
        squeeze_ramp(solver, 15.0, 50)
    profile.summary(passes=solver.newton_passes)  # {"gpu_busy_fraction": ..., "top_kernels": [...], ...}

What the host's Python does meanwhile (:class:`HostProfile`, ``profile_host=true``): Python's own profiler
(cProfile) around the run. Each function's self time holds what it waits for inside the library calls it
makes (a device read of Warp's ``numpy()`` or PyTorch's ``tolist()`` blocks until the GPU reaches it), so
the repository's functions by cumulative time, and the callers of the costliest built-ins, say where a
Newton pass's host time goes, waits included.

    with HostProfile(solver.device) as host:
        squeeze_ramp(solver, 15.0, 50)
    host.summary(passes=solver.newton_passes)  # {"top_self": [...], "top_repository": [...], ...}
"""

from __future__ import annotations

import cProfile
import pstats
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


def busy_seconds(intervals) -> float:
    """Length of the union of ``(start, end)`` intervals (overlaps counted once), in their unit."""
    total, end = 0.0, None
    for lo, hi in sorted(intervals):
        if end is None or lo > end:
            total += hi - lo
            end = hi
        elif hi > end:
            total += hi - end
            end = hi
    return total


class KernelProfile:
    """Context manager: PyTorch's profiler around a run on ``device`` (module docstring).

    CUDA activities are recorded where ``device`` is a CUDA device; on the CPU only the host's operations
    are (then ``gpu_kernels`` is 0). The device is synchronized at entry and exit, so the wall time holds
    the run's own GPU work. The profiler's own overhead lengthens the run: time it without the profile.
    """

    def __init__(self, device, top: int = 25):
        self.device = wp.get_device(device)
        self.top = int(top)
        self.wall = 0.0
        self._profiler = None

    def __enter__(self) -> KernelProfile:
        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU]
        if self.device.is_cuda:
            activities.append(ProfilerActivity.CUDA)
        synchronize(self.device)
        self._profiler = profile(activities=activities)
        self._profiler.__enter__()
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        synchronize(self.device)
        self.wall = time.perf_counter() - self._start
        self._profiler.__exit__(*exc)

    def summary(self, passes: int | None = None) -> dict:
        """Wall seconds; GPU kernels, their busy seconds (union of their intervals), busy fraction of the
        wall time and of the span from the first kernel's start to the last one's end; the ``top`` kernels
        by GPU time and the ``top`` host operations by self CPU time; per pass where ``passes`` is given."""
        from torch.autograd import DeviceType

        kernels = [e for e in self._profiler.events() if e.device_type == DeviceType.CUDA]
        spans = [(e.time_range.start * 1e-6, e.time_range.end * 1e-6) for e in kernels]
        busy = busy_seconds(spans)
        span = (max(hi for _, hi in spans) - min(lo for lo, _ in spans)) if spans else 0.0
        by_name: dict[str, list] = defaultdict(lambda: [0, 0.0])
        for e, (lo, hi) in zip(kernels, spans):
            by_name[e.name][0] += 1
            by_name[e.name][1] += hi - lo
        top_kernels = sorted(by_name.items(), key=lambda kv: -kv[1][1])[: self.top]
        host = sorted(
            (a for a in self._profiler.key_averages() if a.self_cpu_time_total > 0),
            key=lambda a: -a.self_cpu_time_total,
        )[: self.top]
        out = {
            "wall_seconds": round(self.wall, 4),
            "gpu_kernels": len(kernels),
            "gpu_busy_seconds": round(busy, 4),
            "gpu_busy_fraction": round(busy / self.wall, 4) if self.wall > 0 else None,
            "kernel_span_seconds": round(span, 4),
            "gpu_busy_fraction_of_span": round(busy / span, 4) if span > 0 else None,
            "top_kernels": [
                {"name": name[:160], "calls": n, "seconds": round(t, 5), "mean_us": round(1e6 * t / n, 2)}
                for name, (n, t) in top_kernels
            ],
            "top_host_ops": [
                {
                    "name": a.key[:160],
                    "calls": a.count,
                    "self_seconds": round(a.self_cpu_time_total * 1e-6, 5),
                }
                for a in host
            ],
        }
        if passes:
            out["passes"] = int(passes)
            out["gpu_kernels_per_pass"] = round(len(kernels) / passes, 2)
            out["wall_ms_per_pass"] = round(1e3 * self.wall / passes, 3)
            out["gpu_busy_ms_per_pass"] = round(1e3 * busy / passes, 3)
        return out


def _function_name(key, package: str) -> str:
    """'file:line(function)' of a pstats key, the file relative to ``package``'s parent (``package/...``) or
    to site-packages."""
    filename, line, name = key
    if filename == "~":  # a built-in
        return name
    mine = f"/{package}/"
    if mine in filename:
        filename = package + "/" + filename.split(mine, 1)[1]
    elif "/site-packages/" in filename:
        filename = filename.split("/site-packages/", 1)[1]
    return f"{filename}:{line}({name})"


class HostProfile:
    """Context manager: cProfile around a run on ``device`` (module docstring). The device is synchronized
    at entry and exit, so the wall time holds the run's own work. The profiler's overhead lengthens the run
    (every Python call is counted): time it without the profile."""

    def __init__(self, device, top: int = 25, package: str = "defgraspnets"):
        self.device = wp.get_device(device)
        self.top = int(top)
        self.package = package
        self.wall = 0.0
        self._profile = cProfile.Profile()

    def __enter__(self) -> HostProfile:
        synchronize(self.device)
        self._start = time.perf_counter()
        self._profile.enable()
        return self

    def __exit__(self, *exc) -> None:
        synchronize(self.device)
        self._profile.disable()
        self.wall = time.perf_counter() - self._start

    def summary(self, passes: int | None = None) -> dict:
        """Wall seconds; the ``top`` functions by self time (any code); the ``top`` functions of
        ``package`` by cumulative time; for the five costliest functions by self time, their three
        costliest callers; per Newton pass where ``passes`` is given."""
        # key -> (primitive calls, calls, self, cumulative, callers)
        stats = pstats.Stats(self._profile).stats

        def row(key):
            _, calls, own, cumulative, _ = stats[key]
            out = {
                "function": _function_name(key, self.package),
                "calls": int(calls),
                "self_seconds": round(own, 5),
                "cumulative_seconds": round(cumulative, 5),
            }
            if passes:
                out["self_ms_per_pass"] = round(1e3 * own / passes, 4)
            return out

        by_self = sorted(stats, key=lambda k: -stats[k][2])
        mine = [k for k in stats if f"/{self.package}/" in k[0]]
        by_cumulative = sorted(mine, key=lambda k: -stats[k][3])
        callers = {}
        for key in by_self[:5]:
            # callers: caller key -> (primitive calls, calls, self, cumulative) of this function from it
            ranked = sorted(stats[key][4].items(), key=lambda kv: -kv[1][2])[:3]
            callers[_function_name(key, self.package)] = [
                {
                    "caller": _function_name(c, self.package),
                    "calls": int(v[1]),
                    "self_seconds": round(v[2], 5),
                }
                for c, v in ranked
            ]
        out = {
            "wall_seconds": round(self.wall, 4),
            "profiled_seconds": round(sum(v[2] for v in stats.values()), 4),
            "top_self": [row(k) for k in by_self[: self.top]],
            "top_repository": [row(k) for k in by_cumulative[: self.top]],
            "callers_of_top_self": callers,
        }
        if passes:
            out["passes"] = int(passes)
            out["wall_ms_per_pass"] = round(1e3 * self.wall / passes, 3)
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
