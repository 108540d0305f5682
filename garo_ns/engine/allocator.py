"""How training asks PyTorch's CUDA caching allocator for memory.

Densification changes the number of Gaussians every hundred steps, so every per-Gaussian tensor (parameters,
optimizer states, the field's activations) comes back a little larger each time. The caching allocator keeps the
old blocks for reuse, but they no longer fit, and the memory it holds grows far past what the tensors need: on
teddy (a phone video) the baseline held 29.9 GB for 6.6 GB of tensors at 350k Gaussians, and under a 24 GB cap it
stopped at step 5.1k of 20k. With segments that grow in place (PyTorch's `expandable_segments`) the same run passed
step 10.6k using 8.6 GB (benchmarks/results/real_memory_teddy_H200.json).
"""

from __future__ import annotations

import os
from typing import Union

import torch

# PyTorch reads its allocator settings from these (the second is the newer name); a user's choice stays theirs.
SETTING_VARIABLES = ("PYTORCH_CUDA_ALLOC_CONF", "PYTORCH_ALLOC_CONF")


def extend_segments_in_place(device: Union[str, torch.device]) -> bool:
    """Let the CUDA caching allocator grow its segments in place from here on (new memory only; what it holds
    already stays as it is). Nothing is done off CUDA or where the user set the allocator's options in the
    environment. Returns whether the setting was applied."""
    if torch.device(device).type != "cuda" or any(os.environ.get(v) for v in SETTING_VARIABLES):
        return False
    torch.cuda.memory._set_allocator_settings("expandable_segments:True")
    return True
