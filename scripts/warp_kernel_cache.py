"""Build the CUDA kernel cache of the project's Warp kernels on a CPU machine (no GPU needed).

    python scripts/warp_kernel_cache.py            # sm_90 CUBIN + PTX into .warpcache/ (minutes, 2 cores)
    export WARP_CACHE_PATH=$PWD/.warpcache         # then, on the GPU machine, before any run

See defgraspnets.fem.kernel_cache. Config: configs/warp_kernel_cache.yaml.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="../configs", config_name="warp_kernel_cache")
def main(cfg: DictConfig) -> None:
    import warp as wp

    from defgraspnets.fem.kernel_cache import compile_cuda_kernels, instantiate_kernels

    wp.config.quiet = True
    start = time.perf_counter()
    instantiate_kernels()
    paths = compile_cuda_kernels(cfg.out, archs=list(cfg.archs), formats=list(cfg.formats))
    size = sum(p.stat().st_size for p in paths if p.exists())
    for p in paths:
        print(p.relative_to(Path(cfg.out).resolve()))
    seconds = time.perf_counter() - start
    print(f"{len(paths)} CUDA binaries, {size / 1e6:.1f} MB, in {seconds:.0f} s -> {cfg.out}")
    print(
        f"on the GPU machine: export WARP_CACHE_PATH={Path(cfg.out).resolve()} (or the carried copy's path)"
    )


if __name__ == "__main__":
    main()
