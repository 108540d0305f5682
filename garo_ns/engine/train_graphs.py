"""A training step's deformed Gaussians, forward and backward, replayed from a CUDA graph.

A training step runs the field's MLP on every Gaussian and back, then the D-3DGS composition (offsets added,
quaternions normalised, the scale term) and the activations (exp, sigmoid, the SH concatenation): a few dozen small
kernels each way whose launches, and the autograd nodes around them, cost the host more time than the GPU spends on
them (benchmarks/results/train_profile_fast_*). For fixed shapes the whole of it is captured once
(`StepGraph`, the field's parameters read in place through stand-ins: `functional_splats`) and replayed with the
step's canonical parameters and time copied in, as one autograd node whose backward also adds the field parameters'
gradients into their `.grad` inside the graph; a new count of Gaussians (densification, pruning, compaction)
captures anew, on the same stream and into the same memory pool. With `deform_graph_grads` off the capture is
torch's make_graphed_callables (the earlier path). Off the GPU, without gradients, or with `deform_cuda_graph` off, it
runs eagerly.

`deform_train_bf16` runs the field's matrix products in bf16 (`Bf16Field`), graphed or eager, on CUDA only.
"""

from __future__ import annotations

from time import perf_counter
from typing import Any, Callable, List, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor, nn
from torch.autograd.graph import increment_version

from garo_ns.deformation import ScaleOffset
from garo_ns.engine.adam import graph_gradients
from garo_ns.ops.collector import collector_paused
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

    What `StepGraph` captures, with stand-ins for the parameters: leaf tensors on their storage
    (`p.detach().requires_grad_()`), so that the graph reads the optimizer's updates in place. Nothing of the capture
    then holds on to the parameters' own gradient accumulators. torch's make_graphed_callables, given the module,
    captured with the parameters themselves on its side stream, and the autograd graph of the captured outputs,
    which it keeps, kept their accumulators as made there: every backward handed each parameter's gradient to that
    stream and back, an event recorded and waited on per parameter (27 of each a step in `garo-deform`'s host pass,
    benchmarks/results/train_profile_hx2_*)."""
    names = [name for name, _ in call.named_parameters()]
    params = [p for _, p in call.named_parameters()]
    count = len(names)

    def run(*args: Tensor) -> Tuple[Tensor, ...]:
        inputs, values = args[: len(args) - count], args[len(args) - count :]
        return torch.func.functional_call(call, dict(zip(names, values)), inputs)

    return run, params


def stand_ins(params: Sequence[Tensor]) -> Tuple[Tensor, ...]:
    """Leaf tensors on the parameters' storage, for a capture (`functional_splats`)."""
    return tuple(p.detach().requires_grad_(p.requires_grad) for p in params)


def attach_gradients(params: Sequence[Tensor], buffers: Sequence[Tensor]) -> None:
    """Make each buffer its parameter's `.grad`, holding what `.grad` held: zero where it was None (an optimizer's
    zero_grad), a copy where it was another tensor, untouched where it already is the buffer. A graph that adds
    into the buffers then accumulates as autograd would."""
    fresh, copies = [], []
    for p, b in zip(params, buffers):
        if p.grad is b:
            continue
        if p.grad is None:
            fresh.append(b)
        else:
            copies.append((b, p.grad))
        p.grad = b
    if fresh:
        torch._foreach_zero_(fresh)
    for b, g in copies:
        b.copy_(g)


class StepGraph:
    """`function(*inputs, *params)` and its backward, captured once as two CUDA graphs for fixed shapes.

    The inputs are copied into static tensors at each call (unless they are those tensors); the parameters are read
    where they are, through stand-ins on their storage (`functional_splats`). The backward graph adds the
    parameters' gradients into `grads` (each parameter's `.grad` at every backward, `attach_gradients`), so autograd
    sees neither the parameters nor their accumulators: torch's make_graphed_callables returned one gradient per
    parameter, for autograd to accumulate (a node, an allocation and a copy each, 26 a step for the field). The
    capture's own autograd graph is dropped after the capture. Built inside the caller's memory pool, on the caller's
    capture stream: the caching allocator reuses a freed block only on the stream it was allocated on, so captures on
    a new stream each could not reuse their dropped predecessors' memory (a run held 43,697 MiB so
    3.5 minutes in)."""

    def __init__(
        self,
        function: Callable[..., Tuple[Tensor, ...]],
        inputs: Tuple[Tensor, ...],
        params: Sequence[Tensor],
        grads: Sequence[Tensor],
        warmup: int,
        pool: Any,
        stream: "torch.cuda.Stream",
    ) -> None:
        leaves = stand_ins(params)
        # Only the trained parameters get a `.grad`, as autograd would give them.
        trained = [(p, b) for p, b in zip(params, grads) if p.requires_grad]
        self.params, self.grads = tuple(p for p, _ in trained), tuple(b for _, b in trained)
        self.needs_grad = tuple(x.requires_grad for x in inputs)
        wrt = [x for x in inputs if x.requires_grad] + [s for s in leaves if s.requires_grad]
        # Warm-up runs before the capture initialise what it needs (libraries' handles and workspaces), on the
        # stream the capture will use, as torch advises.
        torch.cuda.synchronize()
        with torch.cuda.stream(stream):
            for _ in range(warmup):
                differentiable = [o for o in function(*inputs, *leaves) if o.requires_grad]
                torch.autograd.grad(
                    differentiable, wrt, [torch.empty_like(o) for o in differentiable], allow_unused=True
                )
            del differentiable
        torch.cuda.synchronize()
        self.forward_graph, self.backward_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.forward_graph, pool=pool, stream=stream):
            outs = function(*inputs, *leaves)
        # An output that needs no gradient gets none (its incoming gradient is not copied in).
        self.grad_outputs: Tuple[Optional[Tensor], ...] = tuple(
            torch.empty_like(o) if o.requires_grad else None for o in outs
        )
        differentiable = [(o, g) for o, g in zip(outs, self.grad_outputs) if g is not None]
        n_inputs = sum(self.needs_grad)
        with torch.cuda.graph(self.backward_graph, pool=pool, stream=stream):
            got = torch.autograd.grad(
                [o for o, _ in differentiable], wrt, [g for _, g in differentiable], allow_unused=True
            )
            for buffer, g in zip(self.grads, got[n_inputs:]):
                if g is not None:
                    buffer.add_(g)
        # A replay's adds bump no version counter: `_StepReplay` bumps these, as an eager add would, for whatever
        # tells a step's gradients by their versions (AdamGraph.settle).
        self.written = tuple(b for b, g in zip(self.grads, got[n_inputs:]) if g is not None)
        graph_gradients(self.grads)
        self.inputs = inputs
        self.outputs = tuple(o.detach() for o in outs)  # the capture's autograd graph goes with `outs`
        grads_of_inputs = iter(got[:n_inputs])
        self.input_grads = tuple(next(grads_of_inputs) if needed else None for needed in self.needs_grad)

    def __call__(self, *inputs: Tensor) -> Tuple[Tensor, ...]:
        """The outputs for `inputs` (same shapes as at the capture), as one autograd node."""
        return _StepReplay.apply(self, *inputs)


class _StepReplay(torch.autograd.Function):
    """A `StepGraph`'s replays as an autograd node of its inputs (the parameters' gradients bypass autograd)."""

    @staticmethod
    def forward(ctx: Any, graph: StepGraph, *inputs: Tensor) -> Tuple[Tensor, ...]:  # type: ignore[override]
        for static, x in zip(graph.inputs, inputs):
            if static.data_ptr() != x.data_ptr():
                static.copy_(x)
        graph.forward_graph.replay()
        ctx.graph = graph
        return tuple(o.detach() for o in graph.outputs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, *grads: Tensor) -> Tuple[Optional[Tensor], ...]:  # type: ignore[override]
        graph: StepGraph = ctx.graph
        for static, g in zip(graph.grad_outputs, grads):
            if static is not None and static.data_ptr() != g.data_ptr():
                static.copy_(g)
        attach_gradients(graph.params, graph.grads)
        graph.backward_graph.replay()
        increment_version(graph.written)
        # Copies, not the fixed buffers: autograd adopts a returned tensor as a leaf's `.grad`, and the next replay
        # would rewrite that `.grad` in place before adding to it (g2 + g2 where g1 + g2 is right).
        return (None, *(None if g is None else g.clone() for g in graph.input_grads))


class GraphedSplats:
    """`activate(canonical, compose(field(), canonical, time, scale_offset))`, the Gaussians of a training step; with
    `enabled`, on CUDA and with gradients, through one CUDA graph captured for the parameters' shapes, the field
    object, the scale term and the TF32 setting (the canonical tensors are copied into the graph's inputs). With
    `bf16`, on CUDA the field runs under bf16 autocast (`Bf16Field`), graphed or not; a CPU stays fp32."""

    def __init__(
        self, field: Callable[[], nn.Module], enabled: bool = False, bf16: bool = False, own_grads: bool = True
    ) -> None:
        self.field = field
        self.enabled = bool(enabled)
        self.bf16 = bool(bf16)
        self.own_grads = bool(own_grads)  # a `StepGraph` (deform_graph_grads), else torch's make_graphed_callables
        self._bf16_field: Optional[Bf16Field] = None  # kept: a module built per step would cost the host every step
        self.key: Optional[Tuple[Any, ...]] = None
        self.graphed: Optional[Callable[..., Tuple[Tensor, ...]]] = None
        self._params: Tuple[Tensor, ...] = ()  # what make_graphed_callables' graph takes after the canonical tensors
        self.captures = 0
        self.capture_s = 0.0  # wall seconds in captures, warm-up runs included (a capture synchronises)
        # One memory pool for every capture: a new count of Gaussians (every refinement while densifying) captures
        # into the memory its dropped predecessors held, once Python's collector has freed them (a dropped graph
        # lives in a reference cycle: garo_ns.ops.collector), instead of allocating a pool of its own each time.
        self._pool: Optional[Any] = None
        self._stream: Optional[torch.cuda.Stream] = None  # one capture stream, for the same reason (StepGraph)
        # The field parameters' gradient buffers: each is its parameter's `.grad` after a graphed backward, kept
        # across captures while the parameters are the same tensors.
        self._grads: Tuple[Tuple[int, ...], Tuple[Tensor, ...]] = ((), ())

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
            # Our reference to the old graph. A StepGraph goes once no step's autograd graph holds it; torch's
            # graphed callables live in a reference cycle, which the collector frees (never inside a capture).
            self.graphed = None
            samples = tuple(x.detach().clone().requires_grad_(x.requires_grad) for x in canonical) + (t.clone(),)
            if self._pool is None:
                self._pool, self._stream = torch.cuda.graph_pool_handle(), torch.cuda.Stream()
            # Warm-up runs before a capture initialise what the first capture needs (libraries' handles and
            # workspaces): three before the first, as torch advises; later captures of the same code need one.
            warmup = 3 if self.captures == 0 else 1
            function, params = functional_splats(_SplatsCall(run, scale_offset))
            ids = tuple(id(p) for p in params)
            if self.own_grads and self._grads[0] != ids:
                self._grads = (ids, tuple(torch.zeros_like(p) for p in params))
            start = perf_counter()
            with collector_paused():
                if self.own_grads:
                    self.graphed = StepGraph(
                        function, samples, params, self._grads[1], warmup, self._pool, self._stream
                    )
                    self._params = ()
                else:
                    self.graphed = torch.cuda.make_graphed_callables(
                        function, samples + stand_ins(params), num_warmup_iters=warmup, pool=self._pool
                    )
                    self._params = tuple(params)
            self.capture_s += perf_counter() - start
            self.key = key
            self.captures += 1
        assert self.graphed is not None
        return Splats(*self.graphed(*canonical, t, *self._params))
