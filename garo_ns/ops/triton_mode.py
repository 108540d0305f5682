"""Where the project's Triton kernels run: a CUDA device, or any device under Triton's interpreter (TRITON_INTERPRET=1,
how the CPU tests run them). Triton reads the interpreter setting when a kernel is decorated, so the modules that
make kernels make them once per setting (`per_mode`)."""

from __future__ import annotations

import functools
import importlib.util
import os
from typing import Callable, Dict, TypeVar

import torch

T = TypeVar("T")


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


def per_mode(make: Callable[[], T]) -> Callable[[], T]:
    """`make` (which decorates the kernels) called once per interpreter setting; the same kernels after."""
    made: Dict[bool, T] = {}

    @functools.wraps(make)
    def kernels() -> T:
        mode = interpreting()
        if mode not in made:
            made[mode] = make()
        return made[mode]

    return kernels
