"""The check every data generator makes of its output directory before any work is done."""

from __future__ import annotations

import os
from pathlib import Path


def check_output_dir(out_dir: str | Path, key: str = "out_dir") -> None:
    """Raise unless ``out_dir`` is, or can be made, a writable directory, naming the config ``key`` and
    what is in the way (a file at the path or above it, an unwritable parent). Called before any simulation,
    so a bad path fails in seconds and nothing is written."""
    out_dir = Path(out_dir)
    existing = out_dir
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        what = "is" if existing == out_dir else f"lies under {existing}, which is"
        raise NotADirectoryError(f"{key} {out_dir} {what} a file, not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{key} {out_dir}: {existing} is not writable")
