"""Exact K-nearest neighbours of a few query points among many, chunked (no N x N matrix)."""

from __future__ import annotations

import torch
from torch import Tensor


def knn(
    points: Tensor,
    query_ids: Tensor,
    k: int,
    query_chunk: int = 4096,
    point_chunk: int = 1 << 17,
    segment: int = 0,
) -> Tensor:
    """Indices [Q, k] of the k nearest points (Euclidean) to each queried point, itself excluded.

    Runs on the points' device. Memory is bounded by query_chunk x point_chunk scores. Non-finite
    points are never neighbours. Requires 1 <= k < len(points).

    Ranking uses |p|^2 - 2 q.p, which orders points like |q - p|^2 for a fixed query (|q|^2 is
    constant per row), computed as one fused matrix product per block.

    Args:
        points: [N, 3].
        query_ids: [Q] indices into points.
        k: neighbours per query.
        segment: if > 0, select within segments of this many columns first, then among the
            segment winners (two small selections instead of one over a long row).
    """
    n = points.shape[0]
    if not 1 <= k < n:
        raise ValueError(f"k must be in 1..{n - 1} for {n} points, got {k}")
    finite = torch.isfinite(points).all(-1)
    pts = torch.where(finite[:, None], points, torch.zeros_like(points))
    sq = torch.where(finite, (pts * pts).sum(-1), torch.full_like(pts[:, 0], float("inf")))
    out = []
    for q0 in range(0, query_ids.numel(), query_chunk):
        qid = query_ids[q0 : q0 + query_chunk]
        q = pts[qid]
        rows = torch.arange(qid.numel(), device=points.device)
        best_d = torch.empty((qid.numel(), 0), device=points.device, dtype=points.dtype)
        best_i = torch.empty((qid.numel(), 0), device=points.device, dtype=torch.long)
        for p0 in range(0, n, point_chunk):
            block = pts[p0 : p0 + point_chunk]
            score = torch.addmm(sq[p0 : p0 + point_chunk][None, :], q, block.T, alpha=-2.0)
            inside = (qid >= p0) & (qid < p0 + block.shape[0])
            score[rows[inside], qid[inside] - p0] = float("inf")  # a point is not its own neighbour
            kk = min(k, block.shape[0])
            if segment and block.shape[0] % segment == 0 and segment > kk:
                seg = score.view(score.shape[0], -1, segment)
                d, i = torch.topk(seg, kk, dim=2, largest=False)
                i = i + torch.arange(0, block.shape[0], segment, device=points.device)[None, :, None]
                d, j = torch.topk(d.flatten(1), kk, dim=1, largest=False)
                i = torch.gather(i.flatten(1), 1, j)
            else:
                d, i = torch.topk(score, kk, dim=1, largest=False)
            best_d = torch.cat([best_d, d], 1)
            best_i = torch.cat([best_i, i + p0], 1)
            if best_d.shape[1] > k:
                best_d, sel = torch.topk(best_d, k, dim=1, largest=False)
                best_i = torch.gather(best_i, 1, sel)
        out.append(best_i)
    if not out:
        return torch.zeros((0, k), dtype=torch.long, device=points.device)
    return torch.cat(out, 0)
