"""Fixes for nerfstudio 1.1.5 that every `ns-*` command needs; applied when the plugin is imported.

nerfstudio imports plugin entry points before it parses arguments or loads a checkpoint, so
importing `garo_ns.config` is early enough for all of them: checkpoints that load under torch >= 2.6,
one-line input errors, and crash-safe checkpoint writing and loading (`garo_ns.checkpoints`).
"""

from __future__ import annotations

import sys
from types import TracebackType
from typing import Optional, Type

import numpy as np
import torch

from garo_ns.errors import GaroError

_installed = False


def allow_numpy_scalars_in_checkpoints() -> None:
    """torch >= 2.6 loads with weights_only=True and rejects the numpy scalars that nerfstudio's
    schedulers leave in checkpoints (`_last_lr`). Allow exactly those types, nothing broader."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4 has no weights_only allow-list and loads them anyway
        return
    try:  # numpy >= 2 moved the module; numpy 1.x keeps it under np.core
        from numpy._core.multiarray import scalar
    except ImportError:
        from numpy.core.multiarray import scalar
    safe = [scalar, np.dtype]
    safe += [type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_)]
    add(safe)


def _excepthook(kind: Type[BaseException], err: BaseException, tb: Optional[TracebackType]) -> None:
    if isinstance(err, GaroError):
        print(f"error: {err}", file=sys.stderr)
        return
    _previous_hook(kind, err, tb)


_previous_hook = sys.excepthook


def install() -> None:
    """Apply the fixes once per process (the checkpoint patch as soon as nerfstudio's trainer is imported)."""
    global _installed, _previous_hook
    from garo_ns import checkpoints

    checkpoints.install()
    if _installed:
        return
    _installed = True
    allow_numpy_scalars_in_checkpoints()
    # Bad input gets one line, not a traceback wall; every other error keeps its traceback.
    _previous_hook = sys.excepthook
    sys.excepthook = _excepthook
