"""Which Gaussians to remove: GARO's joint measurement, and the least contributing ones."""

from __future__ import annotations

import math
from typing import Any, Dict, Literal

import torch
from torch import Tensor

from garo_ns.redundancy.activity import activity_candidates
from garo_ns.redundancy.curvature import curvature


def select_redundant(
    activity: Tensor,
    counts: Tensor,
    points: Tensor,
    unit_normals: Tensor,
    mode: Literal["oaa", "gca", "full"],
    tau_activity: float,
    n_max: int,
    tau_curvature: float,
    rho_max: float,
    k: int,
) -> Dict[str, Any]:
    """GARO's joint measurement: which Gaussians to prune now.

    Modes: "full" (the paper: activity candidates, then curvature), "oaa" (activity only, least
    active first), "gca" (curvature only: every visible Gaussian is a candidate, flattest first).

    Returns a dict with `prune` (indices, at most floor(rho_max * N)), and the counts
    `candidates` and `redundant` for logging.
    """
    n = points.shape[0]
    cap = int(math.floor(max(0.0, min(1.0, rho_max)) * n))
    if mode == "gca":
        cand = torch.nonzero(counts > 0).squeeze(1)
    else:
        cand = activity_candidates(activity, tau_activity, n_max)
    if mode == "oaa":
        # Lowest activity first (activity_candidates returns them in that order).
        return {"prune": cand[:cap], "candidates": cand.numel(), "redundant": cand.numel()}
    curv = curvature(points, unit_normals, cand, k)
    flat = curv < tau_curvature
    red, red_curv = cand[flat], curv[flat]
    order = torch.argsort(red_curv, stable=True)
    return {"prune": red[order[:cap]], "candidates": cand.numel(), "redundant": red.numel()}


def least_contributing(contribution: Tensor, ratio: float) -> Tensor:
    """Boolean mask of the floor(ratio * N) Gaussians with the smallest contribution (ties: lower index)."""
    if not 0.0 <= ratio < 1.0:
        raise ValueError(f"prune ratio must be in [0, 1), got {ratio}")
    n = contribution.shape[0]
    k = math.floor(ratio * n)
    mask = torch.zeros(n, dtype=torch.bool, device=contribution.device)
    if k == 0:
        return mask
    order = torch.sort(contribution, stable=True).indices
    mask[order[:k]] = True
    return mask


def lowest(score: Tensor, count: int) -> Tensor:
    """Boolean mask of the `count` Gaussians with the smallest score (ties: lower index)."""
    n = score.shape[0]
    if not 0 <= count <= n:
        raise ValueError(f"cannot mark {count} of {n} Gaussians")
    mask = torch.zeros(n, dtype=torch.bool, device=score.device)
    if count > 0:
        mask[torch.sort(score, stable=True).indices[:count]] = True
    return mask
