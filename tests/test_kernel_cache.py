"""Ahead-of-time CUDA builds of Warp kernels on a machine without a GPU (NVRTC ships with warp-lang)."""

from pathlib import Path

import pytest


def test_cuda_kernels_land_in_the_kernel_cache_layout_under_the_modules_cuda_hash(tmp_path):
    """A module built for sm_90 lands where Warp's loader looks on a GPU machine whose WARP_CACHE_PATH is
    that folder: <cache>/<warp version>/<identifier>/<identifier>.sm90.{cubin,ptx}, the identifier
    carrying the module's hash for CUDA's block size (the cache folder is the one a fresh Warp process
    given WARP_CACHE_PATH reports); the default cache directory is restored afterwards."""
    import os
    import subprocess
    import sys

    import warp as wp

    import defgraspnets.fem.system  # noqa: F401  (defines the module's kernels)
    from defgraspnets.fem.kernel_cache import compile_cuda_kernels

    wp.init()
    default = wp.config.kernel_cache_dir
    paths = compile_cuda_kernels(
        tmp_path, archs=[90], formats=["cubin", "ptx"], modules=["defgraspnets.fem.system"]
    )
    identifier = wp.get_module("defgraspnets.fem.system").get_module_identifier()
    assert sorted(p.name for p in paths) == [f"{identifier}.sm90.cubin", f"{identifier}.sm90.ptx"]
    reported = (
        subprocess.run(
            [
                sys.executable,
                "-c",
                "import warp; warp.config.quiet = True; warp.init(); print(warp.config.kernel_cache_dir)",
            ],
            env={**os.environ, "WARP_CACHE_PATH": str(tmp_path)},
            capture_output=True,
            text=True,
            check=True,
        )
        .stdout.strip()
        .splitlines()[-1]
    )
    for p in paths:
        assert p.parent == Path(reported).resolve() / identifier and p.stat().st_size > 1000
    assert wp.config.kernel_cache_dir == default


def test_bad_requests_are_named(tmp_path):
    from defgraspnets.fem.kernel_cache import compile_cuda_kernels

    with pytest.raises(ValueError, match="formats"):
        compile_cuda_kernels(tmp_path, formats=["elf"])
    with pytest.raises(KeyError, match="no_such_module"):
        compile_cuda_kernels(tmp_path, modules=["no_such_module"])
