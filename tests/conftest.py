"""Shared pytest fixtures: quiet Warp, offline W&B, device selection."""

import os

import pytest

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")


def _torch_cuda() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:
        return False


# without a GPU, Triton kernels (the fused message passing) run in Triton's CPU interpreter; the flag is read
# when a kernel is defined, so it is set before any test imports one
if not _torch_cuda():
    os.environ.setdefault("TRITON_INTERPRET", "1")


def _cuda_available() -> bool:
    try:
        import warp as wp

        wp.config.quiet = True
        wp.init()
        return wp.get_cuda_device_count() > 0
    except Exception:
        return False


def pytest_collection_modifyitems(config, items):
    if _cuda_available():
        return
    skip_gpu = pytest.mark.skip(reason="no CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(scope="session")
def cuda_available() -> bool:
    return _cuda_available()


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny graphs and networks: intra-op threads only add synchronization (and stall badly on a busy
    2-core machine). Use with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
