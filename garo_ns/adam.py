"""Adam with torch's fused kernel and little else on the host.

A training step updates eight parameter groups, each through its own optimizer (nerfstudio keeps one per group, and
gsplat's densification edits each one's state by name). torch's `Adam(fused=True).step` spends about 100 us of host
time per call on bookkeeping (hooks, the profiler's marks, grouping tensors by device and dtype, per-parameter
checks) around two kernels; with the GPU waiting on the host for a third of a step, that bookkeeping is worth
removing. `LeanAdam.step` makes the same two calls (`_foreach_add_` on the step counters, `_fused_adam_`) with the
same state, so its updates are bitwise those of `torch.optim.Adam(fused=True)` and checkpoints move between the two.
Whatever the lean path does not cover (AMSGrad, maximize, a closure, a tensor learning rate, parameters of mixed
devices or dtypes) goes through torch's own step.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, List, Optional

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

    @torch.no_grad()
    def step(self, closure: Optional[Callable[[], float]] = None) -> Optional[float]:  # type: ignore[override]
        """One Adam update of every parameter with a gradient."""
        if closure is not None:
            return super().step(closure)
        work = []
        for group in self.param_groups:
            params: List[Tensor] = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = [self.state[p] for p in params]
            if not self._lean(group, params, states):
                return super().step()  # torch checks and groups these; nothing has been updated yet
            work.append((group, params, states))
        for group, params, states in work:
            for p, state in zip(params, states):
                if len(state) == 0:  # torch's initial state for a fused Adam
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            steps = [s["step"] for s in states]
            torch._foreach_add_(steps, 1)
            beta1, beta2 = group["betas"]
            torch._fused_adam_(
                params,
                [p.grad for p in params],
                [s["exp_avg"] for s in states],
                [s["exp_avg_sq"] for s in states],
                [],
                steps,
                amsgrad=False,
                lr=float(group["lr"]),
                beta1=float(beta1),
                beta2=float(beta2),
                weight_decay=float(group["weight_decay"]),
                eps=float(group["eps"]),
                maximize=False,
            )
        return None
