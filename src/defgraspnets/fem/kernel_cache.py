"""Ahead-of-time CUDA builds of the Warp kernels, made on a machine without a GPU.

Warp compiles a module's kernels the first time they run on a device and caches the binaries. On a fresh
GPU machine that first compile is slow: NVRTC builds ``defgraspnets.fem.elasticity`` for sm_90 in 240 s
on a 2-core CPU (single-threaded, most of it the Neo-Hookean Hessian's projection), ``fem.contact`` in
25 s, the rest in seconds. A short GPU lease spent that way measures nothing (a benchmark stopped after
100 s had not finished its first solve). warp-lang bundles NVRTC, so a CPU machine can build the cache:

    python scripts/warp_kernel_cache.py                       # sm_90 (H100, H200) into .warpcache/
    WARP_CACHE_PATH=$PWD/.warpcache python scripts/benchmark_fem.py device=cuda    # on the GPU machine

:func:`instantiate_kernels` first runs small CPU solves through every path (squeeze with each linear
solver, the sealed membrane with its depth camera), so that the kernels Warp generates on demand (sparse
matrix and Krylov kernels per block type, generic kernels' overloads) exist; :func:`compile_cuda_kernels`
then builds every Warp module that holds kernels into Warp's cache layout. Warp loads a CUBIN for the
GPU's own architecture where the driver is older than Warp's bundled CUDA toolkit (the device tool's H100:
driver 13.0, toolkit 13.4) and otherwise a PTX for min(arch, 75): build ``formats=("ptx",), archs=(75,)``
for such a machine.
Module hashes depend on the kernels' source and Warp's version and options, not on the machine, so the
GPU machine loads them as cached (its load lines say ``(cached)``); a module missing from the cache is
compiled there as before.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["instantiate_kernels", "compile_cuda_kernels", "kernel_cache_root"]


def instantiate_kernels() -> None:
    """Run tiny CPU solves through the engine's code paths so that every kernel they launch exists."""
    from . import Control, Material, Plane, QuasiStaticSolver, RigidBody, SolverOptions, TetMesh

    L = 0.02
    mesh = TetMesh.box(size=(L, L, L), divisions=(2, 2, 3))
    for model in ("corotated", "neohookean"):
        for linear_solver in ("cg", "dense", "banded", "direct", "amg"):
            floor = RigidBody("floor", Plane(point=(0, 0, 0), normal=(0, 0, 1)), friction=0.5)
            press = RigidBody(
                "press", Plane(point=(0, 0, L), normal=(0, 0, -1)), control=Control.force(axis=(0, 0, -1))
            )
            solver = QuasiStaticSolver(
                mesh,
                [floor, press],
                Material(1e5, 0.3, 1000.0, model=model),
                device="cpu",
                options=SolverOptions(
                    linear_solver=linear_solver, stabilization=1e-4, stabilization_release=True
                ),
            )
            solver.solve(targets={"press": 0.01}).require_converged()
    _instantiate_tactile()


def _instantiate_tactile() -> None:
    from ..tactile.camera import PICO_FLEXX
    from ..tactile.indenters import SphereIndenter
    from ..tactile.membrane import ATMOSPHERIC_PRESSURE, PVState, build_membrane
    from ..tactile.sensor import MembraneSimulator

    sensor = build_membrane(cap_divisions=4, layers=2)
    gas = PVState(ATMOSPHERIC_PRESSURE + 1000.0, sensor.cavity_volume + sensor.dimensions.housing_volume)
    sim = MembraneSimulator(
        sensor, SphereIndenter(radius=0.01), gas, closed=True, intrinsics=PICO_FLEXX.scaled(0.1), device="cpu"
    )
    sim.indent([sim.pole_indentation(0.002)])


def kernel_cache_root(cache_dir) -> Path:
    """The folder where Warp, given ``WARP_CACHE_PATH=cache_dir``, looks for cached modules:
    ``cache_dir/<warp version>`` (``warp._src.build.init_kernel_cache``), so that a cache built by one
    Warp version is never loaded by another."""
    import warp as wp

    return Path(cache_dir).resolve() / wp.config.version


def compile_cuda_kernels(cache_dir, archs=(90,), formats=("cubin",), modules=None) -> list[Path]:
    """Build every Warp module that holds kernels (or those named in ``modules``) for the CUDA
    architectures ``archs`` (e.g. 90: H100, H200) as CUBIN and/or PTX under ``cache_dir``, laid out as
    Warp's kernel cache for ``WARP_CACHE_PATH=cache_dir`` (:func:`kernel_cache_root`: Warp looks in a
    subfolder named after its version). Generic kernels are built for the overloads that exist (run
    :func:`instantiate_kernels` first). Returns the artifacts' paths."""
    import warp as wp
    from warp._src.context import user_modules

    unknown = set(formats) - {"cubin", "ptx"}
    if unknown:
        raise ValueError(f"formats must be 'cubin' and/or 'ptx', got {sorted(unknown)}")
    wp.init()
    if modules is None:
        selected = sorted(user_modules.items())
    else:
        missing = sorted(set(modules) - set(user_modules))
        if missing:
            raise KeyError(f"no Warp module named {missing} has been imported")
        selected = [(name, user_modules[name]) for name in modules]
    cache = kernel_cache_root(cache_dir)
    cache.mkdir(parents=True, exist_ok=True)
    default = wp.config.kernel_cache_dir
    wp.config.kernel_cache_dir = str(cache)  # compile_aot_module writes to <cache>/<module identifier>/
    paths = []
    try:
        for name, module in selected:
            if not any(not k.is_generic or k.overloads for k in module.kernels.values()):
                continue
            for fmt in formats:
                try:
                    paths += wp.compile_aot_module(module, arch=[int(a) for a in archs], use_ptx=fmt == "ptx")
                except RuntimeError as error:
                    log.warning("skipped Warp module %s (%s): %s", name, fmt, error)
    finally:
        wp.config.kernel_cache_dir = default
    return [Path(p) for p in paths]
