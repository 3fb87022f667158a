"""Reading the project's Lightning checkpoints with errors that name the file and what it holds.

A missing file, a file that is no PyTorch checkpoint (truncated, another format) and a checkpoint of the other
model (a wrench CNN given to the grasp planner, ...) each raise an error naming the path, instead of an
unpickling error (that suggests an unsafe ``weights_only=False``) or a state_dict key mismatch.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["CheckpointError", "check_checkpoint_for", "checkpoint_kind", "read_checkpoint"]


class CheckpointError(ValueError):
    """A file that is not a readable checkpoint of the expected model."""


def _is_defgraspnets(state: dict) -> bool:
    return "net.node_norm.mean" in state


def _is_wrench(state: dict) -> bool:
    return not _is_defgraspnets(state) and any(k.startswith("net.") for k in state)


_KINDS = {"DefGraspNetsModule": _is_defgraspnets, "WrenchRegressionModule": _is_wrench}


def checkpoint_kind(checkpoint: dict) -> str | None:
    """The LightningModule class a loaded checkpoint belongs to (one of ``_KINDS``), or None."""
    state = checkpoint.get("state_dict") if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict):
        return None
    return next((kind for kind, test in _KINDS.items() if test(state)), None)


def read_checkpoint(path, expected: str, map_location="cpu") -> dict:
    """The checkpoint dict at ``path`` (``torch.load``; trusted files only), checked to hold ``expected``
    (``"DefGraspNetsModule"`` or ``"WrenchRegressionModule"``).

    Raises:
        FileNotFoundError: no file at ``path``.
        CheckpointError: a directory, not a readable PyTorch file, no Lightning checkpoint, or one of another
            model; the message names the path.
    """
    import torch

    if expected not in _KINDS:
        raise ValueError(f"expected must be one of {sorted(_KINDS)}, got {expected!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    if not path.is_file():
        raise CheckpointError(f"{path}: not a file (a {expected} checkpoint file, .ckpt, was expected)")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:
        detail = (str(e).splitlines() or [""])[0][:200]
        raise CheckpointError(
            f"{path}: not a readable PyTorch checkpoint, truncated or another format "
            f"({type(e).__name__}: {detail})"
        ) from e
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("state_dict"), dict):
        raise CheckpointError(
            f"{path}: not a Lightning checkpoint (no state_dict), a {expected} one was expected"
        )
    kind = checkpoint_kind(checkpoint)
    if kind != expected:
        holds = f"it holds a {kind}" if kind else "its state_dict matches no model of this project"
        raise CheckpointError(f"{path}: not a {expected} checkpoint ({holds})")
    return checkpoint


def check_checkpoint_for(path, model_target: str) -> None:
    """Before a fit resumes from (or a test loads) ``path``: raise :class:`CheckpointError` unless it is a
    readable checkpoint of the model class ``model_target`` (a Hydra ``_target_``, e.g.
    ``defgraspnets.models.defgraspnets_module.DefGraspNetsModule``); models of other classes only need the
    file to exist.

    Raises:
        FileNotFoundError, CheckpointError: as :func:`read_checkpoint`.
    """
    kind = str(model_target).rsplit(".", 1)[-1]
    if kind in _KINDS:
        read_checkpoint(path, kind)
    elif not Path(path).is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
