"""A training step's deformed Gaussians, forward and backward, replayed from a CUDA graph.

A training step runs the field's MLP on every Gaussian and back, then the D-3DGS composition (offsets added,
quaternions normalised, the scale term) and the activations (exp, sigmoid, the SH concatenation): a few dozen small
kernels each way whose launches, and the autograd nodes around them, cost the host more time than the GPU spends on
them (benchmarks/results/train_profile_fast_*). For fixed shapes the whole of it is captured once
(torch.cuda.make_graphed_callables) and replayed with the step's canonical parameters and time copied in, as one
autograd node; a new count of Gaussians (densification, pruning, compaction) captures anew. Off the GPU, without
gradients, or when the setting is off, it runs eagerly.

`deform_train_bf16` runs the field's matrix products in bf16 (`Bf16Field`), graphed or eager, on CUDA only.
"""

from __future__ import annotations

from time import perf_counter
from typing import Any, Callable, Iterable, List, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from garo_ns.collector import collector_paused
from garo_ns.deformation import ScaleOffset
from garo_ns.render.frame import Canonical, Splats, activate, compose


def _time_tensor(time: Union[float, Tensor], like: Tensor) -> Tensor:
    """The time as the [1, 1] tensor a captured graph reads."""
    if isinstance(time, Tensor):
        return time.detach().to(device=like.device, dtype=like.dtype).reshape(1, 1)
    return torch.full((1, 1), float(time), dtype=like.dtype, device=like.device)


class Bf16Field(nn.Module):
    """`field`'s forward under bf16 autocast: its matrix products on bf16 tensor cores, the weights kept in fp32
    (autocast casts a copy per call, so the optimizer's master weights stay fp32) and the offsets returned in the
    positions' dtype. A thin wrapper: its parameters are the field's."""

    def __init__(self, field: nn.Module) -> None:
        super().__init__()
        self.field = field

    def forward(self, xyz: Tensor, time: Union[float, Tensor]) -> Tuple[Tensor, Tensor, Tensor]:
        # No weight cache: a captured CUDA graph must recast the weights the optimizer has just updated.
        with torch.autocast(xyz.device.type, dtype=torch.bfloat16, cache_enabled=False):
            return self.field(xyz, time)


def step_stream_accumulators(params: Iterable[Tensor]) -> List[Any]:
    """Each parameter's gradient accumulator (the autograd node that adds into `.grad`), made now on the current
    stream; hold them across a capture. make_graphed_callables captures on a side stream, and the autograd graph its
    captured outputs keep alive would keep accumulators made there: every later backward would then hand each
    parameter's gradient from the step's stream to that side stream and back, an event recorded and waited on per
    parameter (27 of each a step in `garo-deform`'s host pass, benchmarks/results/train_profile_hx2_*). Made here and
    held, they are the ones the capture and every step use, on the step's stream."""
    return [p.view_as(p).grad_fn.next_functions[0][0] for p in params if p.requires_grad]


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
    object, the scale term and the TF32 setting (the canonical tensors are copied into the graph's inputs). With
    `bf16`, on CUDA the field runs under bf16 autocast (`Bf16Field`), graphed or not; a CPU stays fp32."""

    def __init__(self, field: Callable[[], nn.Module], enabled: bool = False, bf16: bool = False) -> None:
        self.field = field
        self.enabled = bool(enabled)
        self.bf16 = bool(bf16)
        self._bf16_field: Optional[Bf16Field] = None  # kept: a module built per step would cost the host every step
        self.key: Optional[Tuple[Any, ...]] = None
        self.graphed: Optional[Callable[..., Tuple[Tensor, ...]]] = None
        self.captures = 0
        self.capture_s = 0.0  # wall seconds in captures, warm-up runs included (make_graphed_callables synchronises)
        # One memory pool for every capture: a new count of Gaussians (every refinement while densifying) captures
        # into the memory its dropped predecessors held, once Python's collector has freed them (a dropped graph
        # lives in a reference cycle: garo_ns.collector), instead of allocating a pool of its own each time.
        self._pool: Optional[Any] = None
        # The field parameters' gradient accumulators, made on the training step's stream before each capture and
        # held while its graph lives (`step_stream_accumulators`).
        self._accumulators: List[Any] = []

    def __call__(self, canonical: Canonical, time: Union[float, Tensor], scale_offset: ScaleOffset) -> Splats:
        field = self.field()
        means = canonical.means
        run: nn.Module = field
        if self.bf16 and means.is_cuda:
            if self._bf16_field is None or self._bf16_field.field is not field:
                self._bf16_field = Bf16Field(field)
            run = self._bf16_field
        if not (self.enabled and means.is_cuda and torch.is_grad_enabled() and field.training):
            return activate(canonical, compose(run, canonical, time, scale_offset))
        t = _time_tensor(time, means)
        shapes = tuple((x.shape, x.dtype, x.requires_grad) for x in canonical)
        key = (shapes, means.device, id(field), scale_offset, torch.backends.cuda.matmul.allow_tf32)
        if key != self.key:
            self.graphed = None  # our reference to the old graph: the collector frees it (never inside a capture)
            samples = tuple(x.detach().clone().requires_grad_(x.requires_grad) for x in canonical) + (t.clone(),)
            if self._pool is None:
                self._pool = torch.cuda.graph_pool_handle()
            # Warm-up runs before a capture initialise what the first capture needs (libraries' handles and
            # workspaces): three before the first, as torch advises; later captures of the same code need one.
            warmup = 3 if self.captures == 0 else 1
            call = _SplatsCall(run, scale_offset)
            start = perf_counter()
            self._accumulators = step_stream_accumulators(call.parameters())
            with collector_paused():
                graphed = torch.cuda.make_graphed_callables(call, samples, num_warmup_iters=warmup, pool=self._pool)
            self.graphed = graphed
            self.capture_s += perf_counter() - start
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return Splats(*self.graphed(*canonical, t))
