"""The rasterizer's (tile, splat) lists at a fixed length, so that a whole frame can be one CUDA graph.

gsplat's `isect_tiles` counts a frame's pairs, reads the count back to size its buffers, then sorts: the frame waits
for the device in its middle, and what follows cannot be captured. Here the lists have a capacity fixed with the
graph: every pair is made and keyed (tile, then depth, in gsplat's order; one Triton kernel on a GPU, `pair_keys` in
torch elsewhere) and sorted in tensors of that length, and the number of pairs needed comes back with the image, so
that a frame that needed more is rendered again with room for them (`FrameGraph` in garo_ns.render.frame_graph).

Two cuts on the way, neither of which changes a pixel: the rasterizer skips a splat wherever its alpha is under
1/255, and a skip leaves the pixel as it was.
- A splat's tile box is the box of its alpha-reach ellipse, in x and in y apart (garo_ns.ops.alpha_reach), inside
  projection's 3-sigma square.
- A pair is kept only where the ellipse reaches the rectangle of the tile's pixel centres (the smallest exponent
  over that rectangle, exact for a convex quadratic form).
What is left is gsplat's list in gsplat's order, less pairs the rasterizer would only have skipped.

The rasterizer reads the last tile's list up to the end of the buffer. So the tile offsets get one more row of tiles
below the image, and the unused tail of the buffer (and the pairs cut) goes to that row's last tile: every pixel of
it lies outside the image, so the compositing kernel closes the tile before it reads a single pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.ops.alpha_reach import ALPHA_MIN, reach_half_widths
from garo_ns.ops.triton_mode import per_mode, runs_on

# The rasterizer computes each exponent in fp32 (fused, fast-math) and its exp() approximately, and so do we: a pair
# is cut only when its smallest exponent passes the threshold by more than this (alpha 0.1% under 1/255), plus a share
# of the exponent's terms' size over the rectangle, where a large thin splat's terms cancel to a small exponent.
SIGMA_MARGIN = 1e-3
SIGMA_MARGIN_REL = 1e-5
INT32_KEYS = 2**31 - 1  # the largest key sorted as int32


@dataclass(frozen=True)
class TileGrid:
    """An image's tiles, plus a row below it (outside the image) that holds the unused pairs."""

    width: int
    height: int
    tile_size: int = 16

    @property
    def tiles_w(self) -> int:
        return math.ceil(self.width / self.tile_size)

    @property
    def tiles_h(self) -> int:
        return math.ceil(self.height / self.tile_size)

    @property
    def n_tiles(self) -> int:
        return self.tiles_w * (self.tiles_h + 1)


def tile_boxes(
    means2d: Tensor, radii: Tensor, grid: TileGrid, half_widths: Optional[Tensor] = None, empty: Optional[Tensor] = None
) -> Tuple[Tensor, Tensor]:
    """Each splat's tiles [lo, hi) in x and y ([N, 2] int64 each), as gsplat's `isect_tiles` bounds a square of
    `radii` (floor and ceil of (centre -/+ radius) / tile, clamped to the image's tiles; none for a radius of 0).
    `half_widths` [N, 2] (x, y), where finite, shrink the square in each axis; `empty` [N] bool empties boxes."""
    r = radii.to(means2d.dtype)[:, None].expand_as(means2d)
    empty = radii <= 0 if empty is None else empty | (radii <= 0)
    if half_widths is not None:
        r = torch.where(torch.isfinite(half_widths), torch.minimum(half_widths, r), r)
    # Clamped axis by axis with Python numbers: a CUDA graph cannot hold a copy of host data.
    lo = torch.floor((means2d - r) / grid.tile_size).clamp_min(0).long()
    hi = torch.ceil((means2d + r) / grid.tile_size).clamp_min(0).long()
    lo = torch.stack([lo[:, 0].clamp_max(grid.tiles_w), lo[:, 1].clamp_max(grid.tiles_h)], -1)
    hi = torch.stack([hi[:, 0].clamp_max(grid.tiles_w), hi[:, 1].clamp_max(grid.tiles_h)], -1)
    return lo, torch.where(empty[:, None], lo, hi)


def smallest_sigma(means2d: Tensor, conics: Tensor, x0: Tensor, x1: Tensor, y0: Tensor, y1: Tensor) -> Tensor:
    """The smallest exponent sigma = 0.5 (a dx^2 + c dy^2) + b dx dy (the rasterizer's, d = point - centre) over each
    rectangle [x0, x1] x [y0, y1]: 0 with the centre inside, else the least of the four edges' minima (a convex
    quadratic form's minimum on a segment is its vertex, clamped to the segment)."""
    a, b, c = conics.unbind(-1)
    dx0, dx1 = x0 - means2d[..., 0], x1 - means2d[..., 0]
    dy0, dy1 = y0 - means2d[..., 1], y1 - means2d[..., 1]

    def sigma(dx: Tensor, dy: Tensor) -> Tensor:
        return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy

    edges = [sigma(dx, torch.clamp(-b * dx / c.clamp_min(1e-30), dy0, dy1)) for dx in (dx0, dx1)]
    edges += [sigma(torch.clamp(-b * dy / a.clamp_min(1e-30), dx0, dx1), dy) for dy in (dy0, dy1)]
    least = torch.minimum(torch.minimum(edges[0], edges[1]), torch.minimum(edges[2], edges[3]))
    inside = (dx0 <= 0) & (dx1 >= 0) & (dy0 <= 0) & (dy1 >= 0)
    return torch.where(inside, torch.zeros_like(least), least)


def sigma_size(means2d: Tensor, conics: Tensor, x0: Tensor, x1: Tensor, y0: Tensor, y1: Tensor) -> Tensor:
    """A bound on the size of the exponent's terms over the rectangle (their absolute values at its farthest
    corner): the scale of the rounding in an exponent computed there."""
    a, b, c = conics.unbind(-1)
    dx = torch.maximum((x0 - means2d[..., 0]).abs(), (x1 - means2d[..., 0]).abs())
    dy = torch.maximum((y0 - means2d[..., 1]).abs(), (y1 - means2d[..., 1]).abs())
    return 0.5 * (a.abs() * dx * dx + c.abs() * dy * dy) + b.abs() * dx * dy


def tile_lists(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    grid: TileGrid,
    capacity: int,
    cut: bool = True,
) -> Tuple[Tensor, Tensor, Tensor]:
    """One camera's sorted tile lists in `capacity` pairs, in fixed-shape tensors (a CUDA graph can hold them).

    Args:
        means2d [N, 2], conics [N, 3], depths [N], radii [N]: projection's outputs; opacities [N].
        grid: the image's tiles. capacity: the lists' length.
        cut: snug boxes and the exact tile test (see the module docstring); False: gsplat's pairs exactly.

    Returns:
        flatten_ids [capacity] int32: the splat of each sorted pair, 0 for unused ones (never read);
        offsets [1, tiles_h + 1, tiles_w] int32: where each tile's pairs start (gsplat's `isect_offset_encode`);
        needed [] int64: the pairs the boxes hold; more than `capacity` means pairs were lost (render again).
    """
    n, device = radii.shape[0], radii.device
    if n == 0:
        blocked = torch.zeros(capacity, dtype=torch.int32, device=device)
        return (
            blocked,
            torch.zeros((1, grid.tiles_h + 1, grid.tiles_w), dtype=torch.int32, device=device),
            blocked[0].long(),
        )
    half, faint = None, None
    reach = torch.full_like(opacities, math.inf)  # the exponent a kept pair's rectangle must reach (inf: any)
    if cut:
        # A NaN box is a splat too faint to reach 1/255 anywhere, or a conic not to be trusted: that one keeps its
        # square and every pair (its exponent need not be convex).
        faint = ~(opacities >= ALPHA_MIN)
        a, b, c = conics.unbind(-1)
        convex = (a > 0) & (c > 0) & (a * c - b * b > 0)
        half = torch.stack(reach_half_widths(conics, opacities, ALPHA_MIN), -1)
        reach = torch.where(convex, torch.log(opacities / ALPHA_MIN) + SIGMA_MARGIN, reach)
    lo, hi = tile_boxes(means2d, radii, grid, half, faint)
    span = hi - lo
    counts = span[:, 0] * span[:, 1]
    ends = torch.cumsum(counts, 0)
    # gsplat keys a pair by (tile, the fp32 depth's bits) and sorts stably, so equal depths keep splat order. The
    # splats' ranks in that order (one sort of N) give the same order in keys tile * (N + 1) + rank: unique, and in
    # 32 bits for most frames, which a radix sort reads in half the passes of 64.
    rank = torch.empty(n, dtype=torch.long, device=device)
    rank[torch.sort(depths.contiguous().view(torch.int32), stable=True).indices] = torch.arange(n, device=device)
    per_splat = (ends, counts, lo, span, means2d, conics, reach, rank)
    if runs_on(device):  # one Triton kernel: a CUDA device, or the interpreter (the CPU tests)
        keys, values = _pairs_kernel(per_splat, grid, capacity, cut)
    else:
        keys, values = pair_keys(per_splat, grid, capacity, cut)
    if grid.n_tiles * (n + 1) <= INT32_KEYS:
        keys = keys.int()
    keys, order = torch.sort(keys, stable=True)
    starts = torch.arange(grid.n_tiles, device=device, dtype=keys.dtype) * (n + 1)
    offsets = torch.searchsorted(keys, starts).int().reshape(1, grid.tiles_h + 1, grid.tiles_w)
    return values[order].int(), offsets, ends[-1]


PerSplat = Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]


def pair_keys(per_splat: PerSplat, grid: TileGrid, capacity: int, cut: bool) -> Tuple[Tensor, Tensor]:
    """Each of `capacity` pairs' key (int64) and splat (N for an unused pair), from the splats' (box ends, counts,
    box lows, spans, means2d, conics, exponent reach, depth rank): the torch path of `tile_lists`."""
    ends, counts, lo, span, means2d, conics, reach, rank = per_splat
    n = ends.shape[0]
    pair = torch.arange(capacity, device=ends.device)
    splat = torch.searchsorted(ends, pair, right=True).clamp_max(n - 1)
    local = pair - (ends[splat] - counts[splat])
    width = span[splat, 0].clamp_min(1)
    tx, ty = lo[splat, 0] + local % width, lo[splat, 1] + local // width
    used = pair < ends[-1]
    if cut:
        s = grid.tile_size
        x0, y0 = (tx * s).to(means2d.dtype) + 0.5, (ty * s).to(means2d.dtype) + 0.5
        x1 = torch.clamp_max(x0 + (s - 1), grid.width - 0.5)
        y1 = torch.clamp_max(y0 + (s - 1), grid.height - 0.5)
        m, q = means2d[splat], conics[splat]
        margin = SIGMA_MARGIN_REL * sigma_size(m, q, x0, x1, y0, y1)
        used = used & (smallest_sigma(m, q, x0, x1, y0, y1) <= reach[splat] + margin)
    tile = torch.where(used, ty * grid.tiles_w + tx, grid.n_tiles - 1)
    keys = tile * (n + 1) + torch.where(used, rank[splat], torch.full_like(splat, n))
    return keys, torch.where(used, splat, torch.zeros_like(splat))


BLOCK = 1024  # pairs per program of the Triton kernel


def _pairs_kernel(per_splat: PerSplat, grid: TileGrid, capacity: int, cut: bool) -> Tuple[Tensor, Tensor]:
    """`pair_keys` in one Triton kernel: each pair finds its splat by a binary search of the box ends."""
    ends, counts, lo, span, means2d, conics, reach, rank = per_splat
    n, device = ends.shape[0], ends.device
    keys = torch.empty(capacity, dtype=torch.long, device=device)
    values = torch.empty(capacity, dtype=torch.long, device=device)
    f32 = [x.float().contiguous() for x in (means2d[:, 0], means2d[:, 1], *conics.unbind(-1), reach)]
    i64 = [x.long().contiguous() for x in (ends, counts, lo[:, 0], lo[:, 1], span[:, 0], rank)]
    _kernel()[(-(-capacity // BLOCK),)](
        *i64,
        *f32,
        keys,
        values,
        n,
        capacity,
        grid.tiles_w,
        grid.n_tiles,
        float(grid.width),
        float(grid.height),
        REL=SIGMA_MARGIN_REL,
        TILE=grid.tile_size,
        CUT=cut,
        BLOCK=BLOCK,
        # The binary search's steps as a constant: one kernel per bit length of N, which a model keeps; a loop
        # bound passed at run time is a one-element array to Triton's interpreter, which newer NumPy refuses.
        STEPS=max(1, n.bit_length() + 1),
    )
    return keys, values


@per_mode
def _kernel() -> Any:
    """The Triton kernel, made once per interpreter setting (garo_ns.ops.triton_mode)."""
    import triton
    import triton.language as tl

    @triton.jit
    def pairs(
        ends_ptr,
        counts_ptr,
        lox_ptr,
        loy_ptr,
        spanx_ptr,
        rank_ptr,
        mx_ptr,
        my_ptr,
        ca_ptr,
        cb_ptr,
        cc_ptr,
        reach_ptr,
        keys_ptr,
        values_ptr,
        n,
        capacity,
        tiles_w,
        n_tiles,
        width,
        height,
        REL: tl.constexpr,
        TILE: tl.constexpr,
        CUT: tl.constexpr,
        BLOCK: tl.constexpr,
        STEPS: tl.constexpr,
    ):
        p = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        inside = p < capacity
        # The splat: the first whose box ends (a running sum of box sizes) pass p (searchsorted, right).
        lo = p * 0
        hi = p * 0 + n
        for _ in range(STEPS):
            mid = (lo + hi) // 2
            right = (tl.load(ends_ptr + mid, mask=mid < n, other=0) <= p) & (lo < hi)
            lo = tl.where(right, mid + 1, lo)
            hi = tl.where(right, hi, mid)
        g = tl.minimum(lo, n - 1)
        local = p - (tl.load(ends_ptr + g) - tl.load(counts_ptr + g))
        w = tl.maximum(tl.load(spanx_ptr + g), 1)
        tx = tl.load(lox_ptr + g) + local % w
        ty = tl.load(loy_ptr + g) + local // w
        used = inside & (p < tl.load(ends_ptr + n - 1))
        if CUT:  # smallest_sigma over the tile's rectangle of pixel centres, edge by edge
            x0 = (tx * TILE).to(tl.float32) + 0.5
            y0 = (ty * TILE).to(tl.float32) + 0.5
            x1 = tl.minimum(x0 + (TILE - 1), width - 0.5)
            y1 = tl.minimum(y0 + (TILE - 1), height - 0.5)
            a = tl.load(ca_ptr + g)
            b = tl.load(cb_ptr + g)
            c = tl.load(cc_ptr + g)
            mx = tl.load(mx_ptr + g)
            my = tl.load(my_ptr + g)
            dx0, dx1, dy0, dy1 = x0 - mx, x1 - mx, y0 - my, y1 - my
            dy = tl.minimum(tl.maximum(-b * dx0 / tl.maximum(c, 1e-30), dy0), dy1)
            s0 = 0.5 * (a * dx0 * dx0 + c * dy * dy) + b * dx0 * dy
            dy = tl.minimum(tl.maximum(-b * dx1 / tl.maximum(c, 1e-30), dy0), dy1)
            s1 = 0.5 * (a * dx1 * dx1 + c * dy * dy) + b * dx1 * dy
            dx = tl.minimum(tl.maximum(-b * dy0 / tl.maximum(a, 1e-30), dx0), dx1)
            s2 = 0.5 * (a * dx * dx + c * dy0 * dy0) + b * dx * dy0
            dx = tl.minimum(tl.maximum(-b * dy1 / tl.maximum(a, 1e-30), dx0), dx1)
            s3 = 0.5 * (a * dx * dx + c * dy1 * dy1) + b * dx * dy1
            least = tl.minimum(tl.minimum(s0, s1), tl.minimum(s2, s3))
            least = tl.where((dx0 <= 0) & (dx1 >= 0) & (dy0 <= 0) & (dy1 >= 0), 0.0, least)
            fx = tl.maximum(tl.abs(dx0), tl.abs(dx1))
            fy = tl.maximum(tl.abs(dy0), tl.abs(dy1))
            size = 0.5 * (tl.abs(a) * fx * fx + tl.abs(c) * fy * fy) + tl.abs(b) * fx * fy
            used = used & (least <= tl.load(reach_ptr + g) + REL * size)
        tile = tl.where(used, ty * tiles_w + tx, n_tiles - 1)
        key = tile * (n + 1) + tl.where(used, tl.load(rank_ptr + g), n)
        tl.store(keys_ptr + p, key, mask=inside)
        tl.store(values_ptr + p, tl.where(used, g, 0), mask=inside)

    return pairs
