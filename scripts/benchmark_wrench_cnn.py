"""Benchmark wrench-CNN inference (thesis §3.4) and write the rates as JSON.

    python scripts/benchmark_wrench_cnn.py                         # CPU; goal >= 200 Hz at batch 1
    python scripts/benchmark_wrench_cnn.py device=cuda             # goal >= 2 kHz at batch 1
    python scripts/benchmark_wrench_cnn.py ckpt_path=checkpoints/wrench_poke.ckpt

Times :meth:`WrenchRegressionModule.predict_wrench` end to end from a raw depth image (numpy, host
memory) to a wrench on the host: normalization, transfer, forward pass, copy back; the median over
``repeats`` calls after ``warmup`` calls, at each batch size. Without ``ckpt_path`` the network has
random weights of the configured size (the timing of a trained one). Config:
configs/benchmark_wrench_cnn.yaml.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

os.environ.setdefault("PROJECT_ROOT", str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402


@hydra.main(version_base="1.3", config_path="../configs", config_name="benchmark_wrench_cnn")
def main(cfg: DictConfig) -> None:
    import torch
    from hydra.utils import instantiate

    from defgraspnets.eval.machine import machine_info
    from defgraspnets.models.wrench_module import WrenchRegressionModule

    torch.set_num_threads(cfg.threads) if cfg.threads else None
    if cfg.ckpt_path:
        module, weights = WrenchRegressionModule.from_checkpoint(cfg.ckpt_path), "checkpoint"
    else:
        torch.manual_seed(0)
        module, weights = WrenchRegressionModule(instantiate(cfg.net)), "random"
    module = module.to(cfg.device).eval()
    h, w = module.net.image_shape
    rng = np.random.default_rng(0)
    if module.reference_depth is None:
        module.reference_depth = torch.from_numpy(0.05 + 0.01 * rng.random((h, w), dtype=np.float32))
    reference = np.asarray(module.reference_depth, dtype=np.float32)
    cuda = str(cfg.device).startswith("cuda")
    sync = (lambda: torch.cuda.synchronize(cfg.device)) if cuda else (lambda: None)
    eager = module.net
    record = {
        "benchmark": "wrench_cnn_inference",
        "machine": machine_info(cfg.device),
        "threads": torch.get_num_threads(),
        "weights": weights,
        "image_shape": [h, w],
        "parameters": sum(p.numel() for p in module.parameters()),
        "timing": "predict_wrench(depth) from a host numpy depth image to a host wrench (stored reference "
        "image), median of repeats",
        "results": [],
    }
    for variant in cfg.variants:
        torch.backends.cudnn.benchmark = bool(variant.cudnn_benchmark)
        module.net = torch.compile(eager, mode=variant.compile) if variant.compile else eager
        for batch in cfg.batch_sizes:
            depth = reference - 0.005 * rng.random((batch, h, w), dtype=np.float32)
            for _ in range(cfg.warmup):
                module.predict_wrench(depth)
            sync()
            seconds = []
            for _ in range(cfg.repeats):
                t0 = time.perf_counter()
                module.predict_wrench(depth)
                sync()
                seconds.append(time.perf_counter() - t0)
            median = float(np.median(seconds))
            record["results"].append(
                {
                    "variant": variant.name,
                    "batch_size": int(batch),
                    "median_latency_s": median,
                    "calls_per_s": 1.0 / median,
                    "images_per_s": batch / median,
                }
            )
            print(
                f"{variant.name:>16} batch {batch:4d}: {median * 1e3:8.3f} ms, {batch / median:9.1f} images/s"
            )
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    record["config"] = OmegaConf.to_container(cfg, resolve=True)
    out.write_text(json.dumps(record, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
