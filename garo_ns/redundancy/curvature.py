"""Geometric complexity (GARO's GCA): how much normals vary around a Gaussian."""

from __future__ import annotations

import torch
from torch import Tensor

from garo_ns.redundancy.knn import knn


def curvature(points: Tensor, normals: Tensor, query_ids: Tensor, k: int) -> Tensor:
    """c_i = mean over the k nearest neighbours j of (1 - |n_i . n_j|), for the queried Gaussians.

    0 on a flat patch (parallel normals, either orientation), up to 1 where neighbours are
    orthogonal. k is reduced to N - 1 when there are fewer Gaussians; with a single Gaussian
    nothing can be measured and the result is +inf (never redundant).

    Returns:
        [Q] curvature of each queried Gaussian.
    """
    n = points.shape[0]
    if query_ids.numel() == 0:
        return torch.zeros(0, device=points.device, dtype=points.dtype)
    if n < 2:
        return torch.full((query_ids.numel(),), float("inf"), device=points.device, dtype=points.dtype)
    nbrs = knn(points, query_ids, min(k, n - 1))
    cos = (normals[query_ids][:, None, :] * normals[nbrs]).sum(-1).abs().clamp(max=1.0)
    c = (1.0 - cos).mean(-1)
    return torch.where(torch.isfinite(c), c, torch.full_like(c, float("inf")))
