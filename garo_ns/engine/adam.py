"""Adam with torch's fused kernel and little else on the host.

A training step updates eight parameter groups, each through its own optimizer (nerfstudio keeps one per group, and
gsplat's densification edits each one's state by name). torch's `Adam(fused=True).step` spends about 100 us of host
time per call on bookkeeping (hooks, the profiler's marks, grouping tensors by device and dtype, per-parameter
checks) around two kernels; with the GPU waiting on the host for a third of a step, that bookkeeping is worth
removing. `LeanAdam.step` makes the same two calls (`_foreach_add_` on the step counters, `_fused_adam_`) with the
same state, so its updates are bitwise those of `torch.optim.Adam(fused=True)` and checkpoints move between the two.
Whatever the lean path does not cover (AMSGrad, maximize, a closure, a tensor learning rate, parameters of mixed
devices or dtypes) goes through torch's own step.

`install_grouped_step` goes one further for a training run: nerfstudio's loop steps (and zeroes) the eight optimizers
one after another, each through the grad scaler and torch's per-call wrapper; installed on the run's `Optimizers`, a
step is one `_foreach_add_` over every group's counter and one fused update per group, with the same numbers.

`AdamGraph` goes further still once the parameters stop moving (after densification): the grouped step, and the
zeroing of the gradients, replay one CUDA graph. A graph reads fixed addresses, so while it is in use each gradient
lives in a buffer of the graph's own that backward accumulates into (autograd adds into an existing gradient in place;
a gradient that the training step's graph writes at a fixed address stays where it is: `graph_gradients`) and the
graph zeroes after the update, and each group's learning rate is a device scalar written only when the scheduler
changes it. The updates are those of the grouped step, bit for bit, except that on CUDA the fused kernel
reads a device learning rate in fp32 where it takes a Python float in fp64: a rate that is not an fp32 number moves
each step by a relative 6e-8 (tests/test_adam.py).
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garo_ns.ops.collector import collector_paused


class LeanAdam(torch.optim.Adam):
    """`torch.optim.Adam(fused=True)` whose step skips the host bookkeeping (see the module docstring)."""

    def __init__(self, params: Iterable[Any], **kwargs: Any) -> None:
        super().__init__(params, fused=True, **kwargs)

    @staticmethod
    def _lean(group: dict, params: List[Tensor], states: List[dict]) -> bool:
        """Whether the lean path covers this group: what torch's fused step would do is two kernels."""
        if (
            group["amsgrad"]
            or group["maximize"]
            or group["differentiable"]
            or group["capturable"]
            or group.get("decoupled_weight_decay", False)
            or isinstance(group["lr"], Tensor)
        ):
            return False
        device, dtype = params[0].device, params[0].dtype
        for p, state in zip(params, states):
            if p.device != device or p.dtype != dtype or p.grad.is_sparse or torch.is_complex(p):
                return False
            if state and (set(state) != {"step", "exp_avg", "exp_avg_sq"} or state["step"].device != device):
                return False
        return True

    def work(self) -> Optional[List[Work]]:
        """Each group's parameters with a gradient and their states, or None where the lean path does not apply."""
        out = []
        for group in self.param_groups:
            params: List[Tensor] = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = [self.state[p] for p in params]
            if not self._lean(group, params, states):
                return None
            out.append((group, params, states))
        return out

    @torch.no_grad()
    def step(self, closure: Optional[Callable[[], float]] = None) -> Optional[float]:  # type: ignore[override]
        """One Adam update of every parameter with a gradient."""
        work = self.work() if closure is None else None
        if work is None:
            return super().step(closure)  # torch checks and groups these; nothing has been updated yet
        apply(work)
        return None


Work = Tuple[dict, List[Tensor], List[dict]]


@torch.no_grad()
def apply(work: Sequence[Work]) -> None:
    """The Adam updates of `work` (`LeanAdam.work` of one optimizer or several): the step counters of every group in
    one `_foreach_add_`, then one fused update per group (each has its own learning rate)."""
    for _, params, states in work:
        for p, state in zip(params, states):
            if len(state) == 0:  # torch's initial state for a fused Adam
                state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    if not work:
        return
    torch._foreach_add_([s["step"] for _, _, states in work for s in states], 1)
    for group, params, states in work:
        beta1, beta2 = group["betas"]
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states],
            [],
            [s["step"] for s in states],
            amsgrad=False,
            lr=float(group["lr"]),
            beta1=float(beta1),
            beta2=float(beta2),
            weight_decay=float(group["weight_decay"]),
            eps=float(group["eps"]),
            maximize=False,
        )


_GRAPH_GRADIENT = "_garo_graph_gradient"


def graph_gradients(buffers: Sequence[Tensor]) -> None:
    """Mark `buffers` as gradients that another CUDA graph adds into at fixed addresses (the training step's
    `StepGraph`), and which bumps their autograd version as it does: an `AdamGraph` takes them as they are. Replacing
    one with a buffer of its own would have that graph copy it back each step, and each would drop the other."""
    for b in buffers:
        setattr(b, _GRAPH_GRADIENT, True)


def is_graph_gradient(grad: Optional[Tensor]) -> bool:
    """Whether `grad` is a buffer marked by `graph_gradients`."""
    return grad is not None and getattr(grad, _GRAPH_GRADIENT, False)


class AdamGraph:
    """`apply` as one CUDA graph (on a CPU, the same calls eagerly) for work whose parameters and optimizer states have
    stayed where they are for `stable_steps` steps: captured then, and dropped as soon as any of them moves (a
    densification or compaction step, a loaded checkpoint) or a gradient is replaced (see the module docstring)."""

    def __init__(self, stable_steps: int = 100) -> None:
        self.stable_steps = max(int(stable_steps), 1)
        self.key: Optional[Tuple[Any, ...]] = None
        self.same = 0  # steps the key has held
        self.run: Optional[Callable[[], None]] = None
        self.pairs: List[Tuple[Tensor, Tensor]] = []  # (parameter, the gradient buffer the graph reads)
        self.groups: List[dict] = []
        self.lrs: List[Tensor] = []
        self.lr_values: List[float] = []
        self.versions: List[int] = []  # each buffer's version after the last update: backward's adds bump it
        self.captures = 0
        self.replays = 0

    @staticmethod
    def key_of(work: Sequence[Work]) -> Optional[Tuple[Any, ...]]:
        """Where everything the update reads and writes lives, and the constants it bakes in (None: a state not
        made yet)."""
        key: List[Any] = []
        for group, params, states in work:
            beta1, beta2 = group["betas"]
            key.append((id(group), float(beta1), float(beta2), float(group["eps"]), float(group["weight_decay"])))
            for p, state in zip(params, states):
                if not state:
                    return None
                key.append((p.data_ptr(), p.shape, p.device, p.dtype, state["exp_avg"].data_ptr()))
                key.append((state["exp_avg_sq"].data_ptr(), state["step"].data_ptr()))
        return tuple(key)

    def held(self) -> set:
        """ids of the parameters whose gradient is the graph's buffer (a zero-grad leaves those: the graph zeroes
        them after each update)."""
        return {id(p) for p, buf in self.pairs if p.grad is buf} if self.run is not None else set()

    def settle(self) -> None:
        """Before a step's work is gathered: a parameter whose buffer backward did not add into since the last update
        had no gradient this step, which nerfstudio's loop leaves as None (no update at all, not a zero one), so it
        gets None again and the graph is dropped."""
        if self.run is None:
            return
        untouched = [p for (p, buf), v in zip(self.pairs, self.versions) if p.grad is buf and buf._version == v]
        if untouched:
            for p in untouched:
                p.grad = None
            self.release()
            self.key = None

    def release(self) -> None:
        """Drop the graph and its buffers; gradients go back to nerfstudio's None between steps."""
        self.run, self.pairs, self.groups, self.lrs, self.lr_values, self.versions = None, [], [], [], [], []

    @torch.no_grad()
    def step(self, work: Sequence[Work]) -> bool:
        """Do `apply(work)` here and return True, or return False for the caller to (not yet stable, or moved)."""
        key = self.key_of(work) if work else None
        if key is None or key != self.key:
            self.release()
            self.key, self.same = key, 1
            return False
        if self.run is None:
            self.same += 1
            if self.same < self.stable_steps:
                return False
            self._capture(work)
        elif not all(p.grad is buf for p, buf in self.pairs):  # a gradient replaced: the graph would miss it
            self.release()
            self.key = None
            return False
        for i, group in enumerate(self.groups):
            lr = float(group["lr"])
            if lr != self.lr_values[i]:
                self.lrs[i].fill_(lr)
                self.lr_values[i] = lr
        assert self.run is not None
        self.run()
        self.versions = [buf._version for _, buf in self.pairs]  # a replay bumps none: only backward's adds do
        self.replays += 1
        return True

    def _capture(self, work: Sequence[Work]) -> None:
        device = work[0][1][0].device
        self.pairs = []
        for _, params, _ in work:
            for p in params:
                # The graph's own buffers (a gradient autograd made may alias another graph's output), except a
                # gradient that is already a graph's fixed buffer (`graph_gradients`): that graph writes there.
                buf = p.grad if is_graph_gradient(p.grad) else p.grad.detach().clone()
                p.grad = buf
                self.pairs.append((p, buf))
        self.groups = [group for group, _, _ in work]
        self.lr_values = [float(group["lr"]) for group in self.groups]
        # CUDA's fused kernel reads an fp32 learning rate (a Python float reaches it in fp64): the graph's updates
        # round the rate to fp32, a relative 6e-8 of each step. The CPU kernel reads fp64: its updates are the same.
        dtype = torch.float32 if device.type == "cuda" else torch.float64
        self.lrs = [torch.tensor(lr, dtype=dtype, device=device) for lr in self.lr_values]
        steps = [s["step"] for _, _, states in work for s in states]
        grads = [buf for _, buf in self.pairs]
        calls = []
        for (group, params, states), lr in zip(work, self.lrs):
            beta1, beta2 = group["betas"]
            calls.append(
                (
                    list(params),
                    [p.grad for p in params],
                    [s["exp_avg"] for s in states],
                    [s["exp_avg_sq"] for s in states],
                    [s["step"] for s in states],
                    dict(
                        lr=lr,
                        beta1=float(beta1),
                        beta2=float(beta2),
                        weight_decay=float(group["weight_decay"]),
                        eps=float(group["eps"]),
                    ),
                )
            )

        def body() -> None:
            torch._foreach_add_(steps, 1)
            for params, param_grads, exp_avgs, exp_avg_sqs, group_steps, consts in calls:
                torch._fused_adam_(
                    params, param_grads, exp_avgs, exp_avg_sqs, [], group_steps, amsgrad=False, maximize=False, **consts
                )
            torch._foreach_zero_(grads)

        if device.type == "cuda":
            graph = torch.cuda.CUDAGraph()
            with collector_paused(), torch.cuda.graph(graph):
                body()
            self.run = graph.replay
        else:
            self.run = body
        self.captures += 1


def install_grouped_step(optimizers: Any, graph: Optional[AdamGraph] = None) -> bool:
    """Give a nerfstudio `Optimizers` a step and a zero-grad over all its groups at once where every optimizer is a
    `LeanAdam` without gradient clipping: the counters of all groups in one kernel and none of the per-optimizer
    calls around the updates (nerfstudio steps each group's optimizer through the grad scaler in turn). Anything
    the lean path does not cover at a step (a scaler that scales, an optimizer `work` refuses) takes nerfstudio's
    own path for that step. With `graph` (an `AdamGraph`), a stable step replays its graph. Returns whether it was
    installed."""
    named = optimizers.optimizers
    if getattr(optimizers, "_grouped_step", False) or not named:
        return False
    if not all(isinstance(o, LeanAdam) for o in named.values()):
        return False
    if any(optimizers.config[name]["optimizer"].max_norm is not None for name in named):
        return False
    own_step = optimizers.optimizer_scaler_step_some

    def optimizer_scaler_step_some(grad_scaler: Any, param_groups: List[str]) -> None:
        if graph is not None:
            graph.settle()
        work: List[Work] = []
        for name in param_groups:
            items = None if grad_scaler.is_enabled() else named[name].work()
            if items is None:
                if graph is not None:
                    graph.release()
                return own_step(grad_scaler, param_groups)
            work.extend(items)
        if graph is None or not graph.step(work):
            apply(work)

    def zero_grad_some(param_groups: List[str]) -> None:
        held = graph.held() if graph is not None else set()
        for name in param_groups:  # torch's zero_grad(set_to_none=True), without its per-call profiler mark
            for group in named[name].param_groups:
                for p in group["params"]:
                    if id(p) not in held:  # the graph's buffers were zeroed by its last update
                        p.grad = None

    optimizers.optimizer_scaler_step_some = optimizer_scaler_step_some
    optimizers.zero_grad_some = zero_grad_some
    optimizers._grouped_step = True
    optimizers.adam_graph = graph
    return True
