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
from typing import Any, Callable, List, Optional, Tuple, Union

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


class _SplatsCall(nn.Module):
    """A training step's Gaussians as a module of (the six canonical tensors, time [1, 1]) (`functional_splats`
    makes the field's parameters arguments too)."""

    def __init__(self, field: nn.Module, scale_offset: ScaleOffset) -> None:
        super().__init__()
        self.field = field
        self.scale_offset = scale_offset

    def forward(self, *args: Tensor) -> Tuple[Tensor, ...]:
        canonical = Canonical(*args[:6])
        return tuple(activate(canonical, compose(self.field, canonical, args[6], self.scale_offset))[:5])


def functional_splats(call: nn.Module) -> Tuple[Callable[..., Tuple[Tensor, ...]], List[Tensor]]:
    """`call` as a function of (its arguments..., then every parameter of it), and those parameters in that order.

    What make_graphed_callables captures, with stand-ins for the parameters: leaf tensors on their storage
    (`p.detach().requires_grad_()`). A capture runs on a side stream, and the autograd graph of the captured
    outputs, which the graphed callable keeps, keeps each leaf's gradient accumulator as made there, on that stream;
    a module's own parameters would then hand their gradient from the step's stream to the side stream and back in
    every backward, an event recorded and waited on per parameter (27 of each a step in `garo-deform`'s host pass,
    benchmarks/results/train_profile_hx2_*). The stand-ins keep those accumulators; each step passes the real
    parameters, whose accumulators are made in the step, on its stream. Sharing their storage, the stand-ins are not
    copied into at replay, and they read the optimizer's updates."""
    names = [name for name, _ in call.named_parameters()]
    params = [p for _, p in call.named_parameters()]
    count = len(names)

    def run(*args: Tensor) -> Tuple[Tensor, ...]:
        inputs, values = args[: len(args) - count], args[len(args) - count :]
        return torch.func.functional_call(call, dict(zip(names, values)), inputs)

    return run, params


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
        self._params: Tuple[Tensor, ...] = ()  # the field's parameters, passed to the graph (`functional_splats`)

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
            function, params = functional_splats(_SplatsCall(run, scale_offset))
            stand_ins = tuple(p.detach().requires_grad_(p.requires_grad) for p in params)
            start = perf_counter()
            with collector_paused():
                graphed = torch.cuda.make_graphed_callables(
                    function, samples + stand_ins, num_warmup_iters=warmup, pool=self._pool
                )
            self.graphed, self._params = graphed, tuple(params)
            self.capture_s += perf_counter() - start
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return Splats(*self.graphed(*canonical, t, *self._params))
