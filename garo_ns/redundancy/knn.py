"""Exact K-nearest neighbours of a few query points among many (no N x N matrix).

Two exact methods share one interface:
* `knn_brute`: every query against every point, in blocks; candidates are ranked by a fused
  matrix product computed in float64 (in float32 its cancellation, about eps * |p|^2, reorders
  neighbours of dense clusters far from the origin) and the survivors re-ranked by exact distances.
* `knn_grid`: points are binned into a uniform grid sorted by cell; each query looks only at
  the 27 cells around it. Whenever the k-th distance found is within one cell size, no point
  outside those cells can be closer, so the answer is exact; the other queries (sparse regions)
  go to `knn_brute`.
`knn` picks the grid for large problems, brute force for small ones.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _check(points: Tensor, k: int) -> None:
    n = points.shape[0]
    if not 1 <= k < n:
        raise ValueError(f"k must be in 1..{n - 1} for {n} points, got {k}")


def _exact_rerank(points: Tensor, query_ids: Tensor, cand: Tensor, k: int, finite: Tensor) -> Tensor:
    """The k candidates [Q, C] closest to each query by exact squared distance.

    Non-finite points count as infinitely far and the query itself comes after them: when fewer
    than k finite others exist, the answer is padded with non-finite points, never with itself.
    """
    d = ((points[cand] - points[query_ids][:, None, :]) ** 2).sum(-1)
    d = torch.where(finite[cand], d, torch.full_like(d, float("inf")))
    # Rank by (is self, distance): a stable sort by distance, then a stable sort by the flag.
    by_dist = torch.argsort(d, dim=1, stable=True)
    is_self = torch.gather(cand == query_ids[:, None], 1, by_dist)
    sel = torch.gather(by_dist, 1, torch.argsort(is_self.to(torch.uint8), dim=1, stable=True)[:, :k])
    return torch.gather(cand, 1, sel)


def knn_brute(points: Tensor, query_ids: Tensor, k: int, query_chunk: int = 4096, point_chunk: int = 1 << 16) -> Tensor:
    """Indices [Q, k] of the k nearest points to each queried point (itself excluded), by blocks."""
    _check(points, k)
    n = points.shape[0]
    finite = torch.isfinite(points).all(-1)
    pts = torch.where(finite[:, None], points, torch.zeros_like(points))
    wide = pts.double()  # the ranking product's precision (see the module docstring)
    sq = torch.where(finite, (wide * wide).sum(-1), torch.full_like(wide[:, 0], float("inf")))
    keep = min(2 * k + 2, n)  # margin for the exact re-rank
    out = []
    for q0 in range(0, query_ids.numel(), query_chunk):
        qid = query_ids[q0 : q0 + query_chunk]
        q = wide[qid]
        rows = torch.arange(qid.numel(), device=points.device)
        best_d = torch.empty((qid.numel(), 0), device=points.device, dtype=wide.dtype)
        best_i = torch.empty((qid.numel(), 0), device=points.device, dtype=torch.long)
        for p0 in range(0, n, point_chunk):
            block = wide[p0 : p0 + point_chunk]
            # |p|^2 - 2 q.p ranks points like |q - p|^2 for a fixed query, as one fused product.
            score = torch.addmm(sq[p0 : p0 + point_chunk][None, :], q, block.T, alpha=-2.0)
            inside = (qid >= p0) & (qid < p0 + block.shape[0])
            score[rows[inside], qid[inside] - p0] = float("inf")
            d, i = torch.topk(score, min(keep, block.shape[0]), dim=1, largest=False)
            best_d = torch.cat([best_d, d], 1)
            best_i = torch.cat([best_i, i + p0], 1)
            if best_d.shape[1] > keep:
                best_d, sel = torch.topk(best_d, keep, dim=1, largest=False)
                best_i = torch.gather(best_i, 1, sel)
        out.append(_exact_rerank(pts, qid, best_i, k, finite))
    if not out:
        return torch.zeros((0, k), dtype=torch.long, device=points.device)
    return torch.cat(out, 0)


def knn_grid(
    points: Tensor,
    query_ids: Tensor,
    k: int,
    cell_quantile: float = 0.9,
    sample_size: int = 256,
    max_candidates: int = 4096,
) -> Tensor:
    """Indices [Q, k] of the k nearest points to each queried point (itself excluded), via a uniform grid.

    The cell size is the `cell_quantile` quantile of the k-th neighbour distance over a sample of
    queries. Queries whose 27-cell neighbourhood holds more than `max_candidates` points, or whose
    k-th neighbour lies beyond one cell, are answered by `knn_brute` (still exact).
    """
    _check(points, k)
    dev = points.device
    finite = torch.isfinite(points).all(-1)
    pts = torch.where(finite[:, None], points, torch.zeros_like(points))
    fid = torch.nonzero(finite).squeeze(1)
    if fid.numel() <= k or query_ids.numel() == 0:
        return knn_brute(points, query_ids, k)
    lo = pts[fid].min(0).values
    extent = (pts[fid].max(0).values - lo).clamp_min(1e-9)
    # Cell size = the typical k-th neighbour distance, measured on a sample of the queries
    # (a bounding-box density would be fooled by outliers and by surfaces).
    sample = query_ids[torch.randperm(query_ids.numel(), device="cpu")[:sample_size].to(dev)]
    sample_nb = knn_brute(points, sample, k)
    kth = ((pts[sample_nb[:, -1]] - pts[sample]) ** 2).sum(-1).sqrt()
    h = float(torch.quantile(kth[torch.isfinite(kth)], cell_quantile)) if torch.isfinite(kth).any() else 0.0
    h = max(h, float(extent.max()) / float(1 << 20), 1e-12)  # grid keys stay well inside int64
    dims = (extent / h).floor().long() + 1
    cells = ((pts[fid] - lo) / h).floor().long().clamp(min=0)
    cells = torch.minimum(cells, dims - 1)
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = torch.argsort(key)
    key_s, pid_s = key[order], fid[order]

    qcell = torch.minimum(((pts[query_ids] - lo) / h).floor().long().clamp(min=0), dims - 1)
    offs = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=dev)] * 3, indexing="ij"), -1).reshape(27, 3)
    nb = qcell[:, None, :] + offs[None]  # [Q, 27, 3]
    valid = ((nb >= 0) & (nb < dims)).all(-1)
    nkey = torch.where(
        valid, (nb[..., 0] * dims[1] + nb[..., 1]) * dims[2] + nb[..., 2], torch.full_like(nb[..., 0], -1)
    )
    start = torch.searchsorted(key_s, nkey.flatten()).reshape(nkey.shape)
    end = torch.searchsorted(key_s, nkey.flatten(), right=True).reshape(nkey.shape)
    cnt = torch.where(valid, end - start, torch.zeros_like(start))
    total = cnt.sum(1)
    fits = (total <= max_candidates) & (total > k) & finite[query_ids]
    result = torch.empty((query_ids.numel(), k), dtype=torch.long, device=dev)
    todo = torch.nonzero(~fits).squeeze(1)
    sel = torch.nonzero(fits).squeeze(1)
    if sel.numel():
        cum = torch.cumsum(cnt[sel], 1)
        m = int(total[sel].max())
        j = torch.arange(m, device=dev).expand(sel.numel(), m).contiguous()
        r = torch.searchsorted(cum, j, right=True)  # which of the 27 ranges slot j falls in
        inrange = r < 27
        r = r.clamp(max=26)
        first = torch.gather(cum - cnt[sel], 1, r)
        pos = torch.gather(start[sel], 1, r) + (j - first)
        cand = pid_s[pos.clamp(max=pid_s.numel() - 1)]
        cand = torch.where(inrange, cand, query_ids[sel][:, None])  # padding = self, excluded below
        qid = query_ids[sel]
        d = ((pts[cand] - pts[qid][:, None, :]) ** 2).sum(-1)
        d = torch.where(cand == qid[:, None], torch.full_like(d, float("inf")), d)
        dk, ik = torch.topk(d, k, dim=1, largest=False)
        exact = dk[:, -1] <= h * h  # nothing outside the 27 cells can be closer than one cell size
        result[sel[exact]] = torch.gather(cand[exact], 1, ik[exact])
        todo = torch.cat([todo, sel[~exact]])
    if todo.numel():
        result[todo] = knn_brute(points, query_ids[todo], k)
    return result


def knn(points: Tensor, query_ids: Tensor, k: int) -> Tensor:
    """Exact k nearest neighbours (Euclidean, itself excluded) of points[query_ids] among `points`."""
    if points.shape[0] * max(query_ids.numel(), 1) > 1 << 26:
        return knn_grid(points, query_ids, k)
    return knn_brute(points, query_ids, k)
