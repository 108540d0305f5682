"""Optimization activity (GARO's OAA): how much each Gaussian is still being moved by training.

The per-iteration input is what densification already computes: the norm of each visible Gaussian's
view-space gradient in NDC units, summed over the cameras that see it, and how many cameras saw it
(the strategy reads both from gsplat's own accumulation, so the normalisation exists once).
"""

from __future__ import annotations

import torch
from torch import Tensor


def record(sums: Tensor, counts: Tensor, step_sums: Tensor, step_counts: Tensor) -> None:
    """Add one iteration's per-Gaussian gradient-norm sums and visibility counts (in place).

    A Gaussian whose sum is not finite this iteration is left out of it (sum and count), so a NaN
    on some Gaussians neither poisons their record nor spreads to the others.
    """
    ok = torch.isfinite(step_sums) & (step_counts > 0)
    sums.add_(torch.where(ok, step_sums, torch.zeros_like(step_sums)).to(sums.dtype))
    counts.add_(torch.where(ok, step_counts, torch.zeros_like(step_counts)).to(counts.dtype))


def mean_activity(sums: Tensor, counts: Tensor) -> Tensor:
    """g_i = sum / count over visible iterations; NaN for Gaussians never seen (no estimate)."""
    g = sums / counts.clamp_min(1)
    return torch.where(counts > 0, g, torch.full_like(g, float("nan")))


def activity_candidates(activity: Tensor, tau: float, n_max: int) -> Tensor:
    """Indices of Gaussians with g_i < tau (never-seen ones excluded), the n_max lowest, lowest first."""
    ok = torch.isfinite(activity) & (activity < tau)
    idx = torch.nonzero(ok).squeeze(1)
    order = torch.argsort(activity[idx], stable=True)
    return idx[order[: max(int(n_max), 0)]]
