"""The deformation field's forward and backward in a training step, replayed from a CUDA graph.

A training step runs the field's MLP on every Gaussian and back: a few dozen small kernels whose launches cost the
host more time than the GPU spends on them (benchmarks/results/train_profile_fast_*). For a fixed count of
Gaussians the whole forward and backward can be captured once (torch.cuda.make_graphed_callables) and replayed
with the step's positions and time copied in; a new count (densification, pruning, compaction) captures anew.
Off the GPU, without gradients, or when the setting is off, the field runs as it is.

`GraphedSplats` widens the graph to the whole step from the canonical parameters to the rasterizer's inputs: the
field, the D-3DGS composition (offsets added, quaternions normalised, the scale term) and the activations (exp,
sigmoid, the SH concatenation). Those are another dozen small kernels each way, and as many autograd nodes whose
bookkeeping costs the host more than their work: with them in the graph, a step's deformation is one autograd node.
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from garo_ns.deformation import ScaleOffset
from garo_ns.render.frame import Canonical, Splats, activate, compose

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
        t = _time_tensor(time, xyz)
        key = (xyz.shape[0], xyz.dtype, xyz.device, id(field), torch.backends.cuda.matmul.allow_tf32)
        if key != self.key:
            self.graphed = None  # the old graph's memory first
            samples = (xyz.detach().clone(), t.clone())
            self.graphed = torch.cuda.make_graphed_callables(_FieldCall(field), samples)
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return self.graphed(xyz.detach(), t)


def _time_tensor(time: Union[float, Tensor], like: Tensor) -> Tensor:
    """The time as the [1, 1] tensor a captured graph reads."""
    if isinstance(time, Tensor):
        return time.detach().to(device=like.device, dtype=like.dtype).reshape(1, 1)
    return torch.full((1, 1), float(time), dtype=like.dtype, device=like.device)


class _SplatsCall(nn.Module):
    """A training step's Gaussians as a module of (the six canonical tensors, time [1, 1]): what
    make_graphed_callables captures (the field's parameters are the module's)."""

    def __init__(self, field: nn.Module, scale_offset: ScaleOffset) -> None:
        super().__init__()
        self.field = field
        self.scale_offset = scale_offset

    def forward(self, *args: Tensor) -> Tuple[Tensor, ...]:
        canonical = Canonical(*args[:6])
        return tuple(activate(canonical, compose(self.field, canonical, args[6], self.scale_offset))[:5])


class GraphedSplats:
    """`activate(canonical, compose(field(), canonical, time, scale_offset))`, the Gaussians of a training step; with
    `enabled`, on CUDA and with gradients, through one CUDA graph captured for the parameters' shapes, the field
    object, the scale term and the TF32 setting (the canonical tensors are copied into the graph's inputs)."""

    def __init__(self, field: Callable[[], nn.Module], enabled: bool = False) -> None:
        self.field = field
        self.enabled = bool(enabled)
        self.key: Optional[Tuple[Any, ...]] = None
        self.graphed: Optional[Callable[..., Tuple[Tensor, ...]]] = None
        self.captures = 0

    def __call__(self, canonical: Canonical, time: Union[float, Tensor], scale_offset: ScaleOffset) -> Splats:
        field = self.field()
        means = canonical.means
        if not (self.enabled and means.is_cuda and torch.is_grad_enabled() and field.training):
            return activate(canonical, compose(field, canonical, time, scale_offset))
        t = _time_tensor(time, means)
        shapes = tuple((x.shape, x.dtype, x.requires_grad) for x in canonical)
        key = (shapes, means.device, id(field), scale_offset, torch.backends.cuda.matmul.allow_tf32)
        if key != self.key:
            self.graphed = None  # the old graph's memory first
            samples = tuple(x.detach().clone().requires_grad_(x.requires_grad) for x in canonical) + (t.clone(),)
            self.graphed = torch.cuda.make_graphed_callables(_SplatsCall(field, scale_offset), samples)
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return Splats(*self.graphed(*canonical, t))
