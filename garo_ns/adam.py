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
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, List, Optional, Sequence, Tuple

import torch
from torch import Tensor


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


def install_grouped_step(optimizers: Any) -> bool:
    """Give a nerfstudio `Optimizers` a step and a zero-grad over all its groups at once where every optimizer is a
    `LeanAdam` without gradient clipping: the counters of all groups in one kernel and none of the per-optimizer
    calls around the updates (nerfstudio steps each group's optimizer through the grad scaler in turn). Anything
    the lean path does not cover at a step (a scaler that scales, an optimizer `work` refuses) takes nerfstudio's
    own path for that step. Returns whether it was installed."""
    named = optimizers.optimizers
    if getattr(optimizers, "_grouped_step", False) or not named:
        return False
    if not all(isinstance(o, LeanAdam) for o in named.values()):
        return False
    if any(optimizers.config[name]["optimizer"].max_norm is not None for name in named):
        return False
    own_step = optimizers.optimizer_scaler_step_some

    def optimizer_scaler_step_some(grad_scaler: Any, param_groups: List[str]) -> None:
        work: List[Work] = []
        for name in param_groups:
            items = None if grad_scaler.is_enabled() else named[name].work()
            if items is None:
                return own_step(grad_scaler, param_groups)
            work.extend(items)
        apply(work)

    def zero_grad_some(param_groups: List[str]) -> None:
        for name in param_groups:  # torch's zero_grad(set_to_none=True), without its per-call profiler mark
            for group in named[name].param_groups:
                for p in group["params"]:
                    p.grad = None

    optimizers.optimizer_scaler_step_some = optimizer_scaler_step_some
    optimizers.zero_grad_some = zero_grad_some
    optimizers._grouped_step = True
    return True
