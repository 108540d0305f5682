"""A round's decision, made before anything is removed: which share of the least important Gaussians it
removes, judged by what leaving them out of the render costs on the guard's training views.

`cost(mask)` renders the guard views twice at the same step, with the same field: as they are and with the
Gaussians of `mask` left out (nothing is removed to measure it), and returns each view's PSNR loss in dB.
The worst view decides, so one view's loss is not hidden by a mean over the others. No training state is
copied or rolled back: a removal that costs too much is simply never made.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, List

import torch
from torch import Tensor

from garo_ns.compaction.schedule import Compaction
from garo_ns.redundancy.select import lowest

# (mask [N] of the Gaussians left out of the render) -> PSNR loss of each guard view [V], in dB.
CostFn = Callable[[Tensor], Tensor]


def view_costs(plain: Tensor, without: Tensor) -> Tensor:
    """Each view's PSNR loss in dB: its PSNR as rendered minus its PSNR without the candidates [V]."""
    return plain.double() - without.double()


def decide(scores: Tensor, n: int, compaction: Compaction, spent_db: float, cost: CostFn) -> Dict[str, Any]:
    """The round's removal: tries the shares of `compaction.shares()` (largest first) of the `n` Gaussians
    with the lowest `scores` [N] and keeps the first whose worst view's cost is within the round's bound
    and what is left of the total budget after `spent_db`.

    Returns `mask` (the Gaussians to remove, None when none), `tries` (share, count, mean and worst cost
    of each measured try) and, when nothing is removed, `stop` (a schedule.REASONS key) and `detail`.
    """
    allowed = min(compaction.round_bound_db, max(compaction.budget_db - spent_db, 0.0))
    tries: List[Dict[str, Any]] = []
    last_count = -1
    for share in compaction.shares():
        count = compaction.removal_count(n, share)
        if count == 0 or count == last_count:  # nothing left to try, or the same Gaussians again
            break
        last_count = count
        mask = lowest(scores, count)
        costs = cost(mask)
        worst, mean = _worst_and_mean(costs)
        tries.append({"share": share, "count": count, "cost_mean_db": mean, "cost_worst_db": worst})
        if worst <= allowed:  # NaN never is
            return {"mask": mask, "tries": tries, "stop": None, "detail": None}
    if not tries:
        detail = f"{compaction.fraction} x {n} Gaussians"
        return {"mask": None, "tries": tries, "stop": "nothing_to_remove", "detail": detail}
    last = tries[-1]
    by_budget = last["cost_worst_db"] <= compaction.round_bound_db
    if by_budget:
        limit = f"the {allowed:.3f} dB left of the {compaction.budget_db:g} dB budget"
    else:
        limit = f"the round bound {compaction.round_bound_db:g} dB"
    detail = f"removing {last['count']} Gaussians would cost {last['cost_worst_db']:.3f} dB (worst view), over {limit}"
    return {"mask": None, "tries": tries, "stop": "budget" if by_budget else "round_bound", "detail": detail}


def _worst_and_mean(costs: Tensor) -> tuple[float, float]:
    """The worst and the mean view cost (NaN for no views or a non-finite cost: such a try is never kept)."""
    if costs.numel() == 0 or not bool(torch.isfinite(costs).all()):
        return math.nan, math.nan
    return float(costs.max()), float(costs.mean())


def committed_cost(worst_db: float) -> float:
    """What a kept round adds to the spent budget: its worst view's cost, a gain counting as none."""
    return max(worst_db, 0.0)
