"""Optimization activity (GARO's OAA): how much each Gaussian is still being moved by training."""

from __future__ import annotations

from typing import Any, Dict, Tuple

import torch
from torch import Tensor


def visible_gradient_norms(info: Dict[str, Any], packed: bool = False) -> Tuple[Tensor, Tensor]:
    """Norms of the plain view-space gradient of visible Gaussians, in DefaultStrategy's units.

    The means2d gradient is scaled by width/2 and height/2 (times the number of cameras), which
    makes it the NDC gradient 3DGS thresholds. Entries that are not finite are dropped, so a
    NaN on some Gaussians does not poison the others.

    Returns:
        (gaussian ids [M], gradient norms [M]) of the visible (radius > 0) entries.
    """
    grad = info["means2d"].grad
    if grad is None:
        raise ValueError("info['means2d'] has no gradient: call retain_grad() before backward")
    grad = grad.detach().clone()
    grad[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
    grad[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
    if packed:
        ids, grad = info["gaussian_ids"], grad
    else:
        sel = info["radii"] > 0
        ids = torch.where(sel)[1]
        grad = grad[sel]
    norms = grad.norm(dim=-1)
    ok = torch.isfinite(norms)
    return ids[ok], norms[ok]


def accumulate(sums: Tensor, counts: Tensor, ids: Tensor, norms: Tensor) -> None:
    """Add one iteration's norms to the running sums and visibility counts (in place)."""
    sums.index_add_(0, ids, norms.to(sums.dtype))
    counts.index_add_(0, ids, torch.ones_like(norms, dtype=counts.dtype))


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

