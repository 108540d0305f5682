"""The deformation field's forward and backward in a training step, replayed from a CUDA graph.

A training step runs the field's MLP on every Gaussian and back: a few dozen small kernels whose launches cost the
host more time than the GPU spends on them (benchmarks/results/train_profile_fast_*). For a fixed count of
Gaussians the whole forward and backward can be captured once (torch.cuda.make_graphed_callables) and replayed
with the step's positions and time copied in; a new count (densification, pruning, compaction) captures anew.
Off the GPU, without gradients, or when the setting is off, the field runs as it is.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Tuple, Union

import torch
from torch import Tensor, nn

Offsets = Tuple[Tensor, Tensor, Tensor]


class _FieldCall(nn.Module):
    """The field as a module of (positions [N, 3], time [1, 1]): the form make_graphed_callables captures."""

    def __init__(self, field: nn.Module) -> None:
        super().__init__()
        self.field = field

    def forward(self, xyz: Tensor, time: Tensor) -> Offsets:
        return self.field(xyz, time)


class GraphedField:
    """Calls `field()` (the model's current field) like the field itself; with `enabled`, on CUDA and with
    gradients, through a CUDA graph captured for the count of Gaussians, the field object and the TF32 setting."""

    def __init__(self, field: Callable[[], nn.Module], enabled: bool = False) -> None:
        self.field = field
        self.enabled = bool(enabled)
        self.key: Optional[Tuple[Any, ...]] = None
        self.graphed: Optional[Callable[..., Offsets]] = None
        self.captures = 0

    def __call__(self, xyz: Tensor, time: Union[float, Tensor]) -> Offsets:
        field = self.field()
        if not (self.enabled and xyz.is_cuda and torch.is_grad_enabled() and field.training):
            return field(xyz, time)
        if isinstance(time, Tensor):
            t = time.detach().to(device=xyz.device, dtype=xyz.dtype).reshape(1, 1)
        else:
            t = torch.full((1, 1), float(time), dtype=xyz.dtype, device=xyz.device)
        key = (xyz.shape[0], xyz.dtype, xyz.device, id(field), torch.backends.cuda.matmul.allow_tf32)
        if key != self.key:
            self.graphed = None  # the old graph's memory first
            samples = (xyz.detach().clone(), t.clone())
            self.graphed = torch.cuda.make_graphed_callables(_FieldCall(field), samples)
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return self.graphed(xyz.detach(), t)
