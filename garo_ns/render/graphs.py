"""Replay of a fixed-shape, time-dependent GPU computation as one CUDA graph.

Rendering a dynamic scene runs the same few dozen small kernels every frame (positional
encoding, eight MLP layers, heads, composition, activations) on tensors whose shapes only change
when the Gaussians do. Launching them one by one from Python costs more than computing them once
the model is small (the frame profile of a pruned lego model: about 1 ms of launches for 0.1 ms of
work). Captured once as a CUDA graph, the whole step is a single launch; the time is written into
a device scalar the graph reads.
"""

from __future__ import annotations

import weakref
from typing import Any, Callable, Hashable, Optional, Tuple

import torch
from torch import Tensor, nn

from garo_ns.ops.collector import collector_paused


class TimeGraph:
    """A CUDA graph of `fn(time)` for one `key`; captured again whenever the key changes.

    The key must change whenever anything `fn` reads changes shape, storage or meaning (the
    caller passes the parameters' identities, storages and versions). The returned tensors are the
    graph's own buffers: the next call overwrites them, so use them before calling again.
    """

    def __init__(self, warmup: int = 2):
        self.warmup = warmup
        self.key: Optional[Hashable] = None
        self.graph: Optional[torch.cuda.CUDAGraph] = None
        self.time: Optional[Tensor] = None
        self.outputs: Any = None
        self.last_time: Optional[float] = None
        self.captures = 0

    def __call__(
        self,
        key: Hashable,
        fn: Callable[[Tensor], Tuple[Tensor, ...]],
        time: float,
        device: torch.device,
        reuse: bool = False,
    ) -> Tuple[Tensor, ...]:
        """`fn` at `time` by graph replay (capturing it first for a new key). With `reuse`, the
        buffers are returned as they are when the last replay was at the same time (exact: only a
        replay writes them)."""
        if torch.is_grad_enabled():
            raise RuntimeError("TimeGraph replays inference only; call it under torch.no_grad()")
        time = float(time)
        if self.key != key or self.graph is None:
            self.release()
            self._capture(fn, time, device)
            self.key = key
        elif reuse and self.last_time == time:
            return self.outputs
        self.time.fill_(time)
        self.graph.replay()
        self.last_time = time
        return self.outputs

    def _capture(self, fn: Callable[[Tensor], Tuple[Tensor, ...]], time: float, device: torch.device) -> None:
        self.time = torch.full((), float(time), device=device)
        self.graph, self.outputs = capture(fn, (self.time,), device, self.warmup)
        self.captures += 1

    def release(self) -> None:
        """Drop the graph and its memory pool (e.g. when the Gaussians change)."""
        self.key, self.graph, self.outputs, self.time, self.last_time = None, None, None, None, None


class InputGraph:
    """A CUDA graph of `fn(*inputs)` for one key, the inputs being small tensors (a camera's
    matrices) copied into the graph's own buffers before each replay; captured again whenever the
    key or the inputs' shapes change. As with TimeGraph, the key must change whenever anything
    else `fn` reads changes, and the returned tensors are overwritten by the next call."""

    def __init__(self, warmup: int = 2):
        self.warmup = warmup
        self.key: Optional[Hashable] = None
        self.graph: Optional[torch.cuda.CUDAGraph] = None
        self.inputs: Tuple[Tensor, ...] = ()
        self.outputs: Any = None
        self.captures = 0

    def __call__(self, key: Hashable, fn: Callable[..., Any], *inputs: Tensor) -> Any:
        """`fn(*inputs)` by graph replay, capturing it first for a new key or new input shapes."""
        if torch.is_grad_enabled():
            raise RuntimeError("InputGraph replays inference only; call it under torch.no_grad()")
        key = (key, tuple((x.shape, x.dtype, x.device) for x in inputs))
        if self.key != key or self.graph is None:
            self.release()
            self.inputs = tuple(x.detach().clone() for x in inputs)
            self.graph, self.outputs = capture(fn, self.inputs, self.inputs[0].device, self.warmup)
            self.key = key
            self.captures += 1
        else:
            for buffer, x in zip(self.inputs, inputs):
                buffer.copy_(x)
        self.graph.replay()
        return self.outputs

    def release(self) -> None:
        """Drop the graph, its buffers and its memory pool."""
        self.key, self.graph, self.inputs, self.outputs = None, None, (), None


def capture(
    fn: Callable[..., Any], args: Tuple[Tensor, ...], device: torch.device, warmup: int
) -> Tuple[torch.cuda.CUDAGraph, Any]:
    """Capture `fn(*args)` as a CUDA graph (after `warmup` eager runs on a side stream, so that
    lazy cuBLAS and allocator set-up does not happen during capture); returns the graph and the
    outputs it writes on each replay. The capture itself computes nothing: replay to get values."""
    stream = torch.cuda.Stream(device=device)
    stream.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(stream):
        for _ in range(warmup):
            fn(*args)
    torch.cuda.current_stream(device).wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with collector_paused(), torch.cuda.graph(graph):
        outputs = fn(*args)
    return graph, outputs


def graphs_available(device: torch.device) -> bool:
    """CUDA graphs need a CUDA device; elsewhere the same function runs eagerly."""
    return torch.device(device).type == "cuda" and torch.cuda.is_available()


_LISTED: "weakref.WeakKeyDictionary[nn.Module, Tuple[Tensor, ...]]" = weakref.WeakKeyDictionary()


def parameter_list(module: nn.Module) -> Tuple[Tensor, ...]:
    """`module`'s parameters, listed once per module. A frame keys its caches on their `versions`, and walking the
    module tree for them (several times a frame) cost more host time than a tabled frame's kernels. Loading, moving
    or rounding parameters keeps each Parameter object, and no module here registers one after it is built."""
    listed = _LISTED.get(module)
    if listed is None:
        listed = _LISTED[module] = tuple(module.parameters())
    return listed


def versions(tensors: Any) -> Tuple[Any, ...]:
    """Identity, in-place version and storage of each tensor: changes whenever any of them does
    (the storage pointer too, since assigning `.data` on checkpoint loading keeps the other two).
    The key of every render-time cache and graph."""
    return tuple((id(t), t._version, t.data_ptr()) for t in tensors)
