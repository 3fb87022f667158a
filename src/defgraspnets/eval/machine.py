"""What a benchmark ran on: every published number names its machine."""

from __future__ import annotations

import os
import platform

__all__ = ["machine_info"]


def machine_info(device: str = "cpu") -> dict:
    """Platform, Python, CPU model and core count, torch version, and the GPU's name when ``device``
    is a CUDA device (``"cuda"``, ``"cuda:1"``)."""
    import torch

    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        if names:
            info["cpu"] = names[0]
    except OSError:
        pass
    device = str(device)
    info["device"] = torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu"
    return info
