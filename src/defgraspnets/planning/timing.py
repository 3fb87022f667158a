r"""Wall time of the stages of grasp scoring and refinement (``scripts/benchmark_planning.py``).

The planner and the predictor call ``timer(name)`` around their stages; the default :data:`NO_TIMER` does
nothing (no device synchronization, no cost). A :class:`StageTimer` synchronizes the device before and after
each stage (so GPU work is charged to the stage that launched it) and accumulates seconds and calls:

    fingers     finger joint states from the gripper poses, finger poses and pad vertices (pose handling)
    graph       multigraph construction (contact search, padding, node and edge indices)
    features    featurization: edge vectors, lengths, force channel, normalization (shared-object path;
                otherwise part of ``network``)
    network     encode-process-decode forward pass and output scaling
    objective   objective Q and feasibility of the predicted fields
    refine.*    refinement: gradient (forward with autograd), backward, trial (line-search forward without
                gradients), collisions (open-gripper collision checks); ``count`` adds grasps evaluated

Stages nest (``refine.trial`` contains ``fingers`` ... ``objective``); the synchronizations cost a little, so
end-to-end times are taken with the timer off.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict

import torch

__all__ = ["NO_TIMER", "NullTimer", "StageTimer"]


class NullTimer:
    """The default timer: no-op contexts, no counters."""

    def __call__(self, name: str) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext()

    def count(self, name: str, n: int) -> None:
        pass


NO_TIMER = NullTimer()


class StageTimer:
    """Accumulated wall time per named stage, with device synchronization around each stage.

    Args:
        device: the device whose queued work each stage waits for (CUDA: ``torch.cuda.synchronize``).
    """

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.counts: dict[str, int] = defaultdict(int)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextlib.contextmanager
    def __call__(self, name: str):
        self._sync()
        t = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.seconds[name] += time.perf_counter() - t
            self.calls[name] += 1

    def count(self, name: str, n: int) -> None:
        """Add ``n`` to counter ``name`` (e.g. grasps evaluated)."""
        self.counts[name] += int(n)

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()
        self.counts.clear()

    def summary(self, repeats: int = 1) -> dict:
        """``{stage: {"seconds": total / repeats, "calls": calls / repeats, "seconds_per_call": ...}}`` and
        the counters (per repeat)."""
        out = {
            k: {
                "seconds": self.seconds[k] / repeats,
                "calls": self.calls[k] / repeats,
                "seconds_per_call": self.seconds[k] / max(self.calls[k], 1),
            }
            for k in self.seconds
        }
        out.update({k: {"count": v / repeats} for k, v in self.counts.items()})
        return out
