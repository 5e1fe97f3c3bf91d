"""Checkpoint files: written atomically, read without executing code.

A crash while writing leaves the previous checkpoint intact (write to a temporary file in the
same folder, fsync, then rename over the old one). Reading uses ``torch.load(weights_only=True)``:
only tensors, numbers, strings, lists and dicts come back, so a checkpoint someone sends you
cannot run code.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write `state` to `path` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            torch.save(state, stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint safely; a file that holds code or objects is refused."""
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError...
        raise ValueError(f"{path} is not a valid checkpoint: {exc}") from exc
    if not isinstance(state, dict):
        raise ValueError(f"{path} is not a valid checkpoint: expected a dict")
    return state
