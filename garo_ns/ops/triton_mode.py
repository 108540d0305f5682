"""Where the project's Triton kernels run: a CUDA device, or any device under Triton's interpreter (TRITON_INTERPRET=1,
how the CPU tests run them). Triton reads the interpreter setting when a kernel is decorated, so the modules that
make kernels make them once per setting (`functools.lru_cache` on `interpreting()`)."""

from __future__ import annotations

import functools
import importlib.util
import os

import torch


def interpreting() -> bool:
    """Whether Triton's interpreter is on: kernels then run on CPU tensors."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


@functools.lru_cache(maxsize=None)
def has_triton() -> bool:
    """Whether Triton is installed."""
    return importlib.util.find_spec("triton") is not None


def runs_on(device: torch.device) -> bool:
    """Whether a kernel can run on `device`: a CUDA device with Triton, or any under the interpreter."""
    return has_triton() and (torch.device(device).type == "cuda" or interpreting())
