"""A training rasterization's tile lists without a host read.

gsplat's `isect_tiles` counts each Gaussian's tiles on the GPU and then reads the total on the host to allocate the
lists: every training step waits there for the GPU to finish everything queued before it (the deformation field's
forward and the projection), and the host's launches for the rest of the step only start then. Here the lists are
built at a `capacity` the host chose beforehand, so nothing waits:

* each Gaussian's tile rectangle is gsplat's (the same fp32 arithmetic), its entries are numbered by a cumulative
  sum, and entry e of the capacity finds its Gaussian by a search in that sum;
* keys are gsplat's (tile id above the depth's bits) and are sorted stably, so the lists equal gsplat's, entry for
  entry, whenever the total fits;
* the unused tail of the capacity goes to an extra row of tiles below the image, one tile per column: the
  rasterizer's kernels skip tiles whose pixels are all outside the image (a forward never reads their entries; a
  backward reads each dummy tile's share without using it), so the image, its gradients and the real tiles'
  lists are unchanged by the padding;
* the total is copied to the host without waiting and read a step or more later (`TileCapacity`): the capacity
  grows before it is needed, and a step whose total exceeded it (its last entries dropped) is counted and said.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import torch
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

CAPACITY_STEP = 1 << 16  # capacities are multiples of this: a new size, and so new allocations, only now and then


@dataclass
class TileLists:
    """A rasterization's tile lists (one camera): `isect_ids` [capacity] (sorted keys), `flatten_ids` [capacity]
    (int32 Gaussian index of each entry), `offsets` [1, tiles_h + 1, tiles_w] (int32: each tile's first entry; the
    last row holds the padding), `counts` [1, N] (int32 tiles per Gaussian) and `total` [1] (int64, on the device:
    the entries the Gaussians need)."""

    isect_ids: Tensor
    flatten_ids: Tensor
    offsets: Tensor
    counts: Tensor
    total: Tensor


def tile_rectangles(
    means2d: Tensor, radii: Tensor, tile_size: int, tiles_w: int, tiles_h: int
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each Gaussian's tile rectangle [x0, x1) x [y0, y1) (int64 [N] each), as gsplat's `isect_tiles` computes it: in
    fp32, the centre and radius in tiles, floor and ceil, cast to unsigned (negative to 0) and clamped to the grid.
    Gaussians with radius <= 0 get an empty rectangle."""
    r = radii.to(torch.float32) / float(tile_size)
    x = means2d[..., 0].to(torch.float32) / float(tile_size)
    y = means2d[..., 1].to(torch.float32) / float(tile_size)

    def cell(v: Tensor, limit: int) -> Tensor:
        # A float cast to uint32 on the GPU saturates: negatives (and NaN) become 0.
        return torch.nan_to_num(v, nan=0.0).clamp(0.0, float(limit)).to(torch.int64)

    x0, x1 = cell(torch.floor(x - r), tiles_w), cell(torch.ceil(x + r), tiles_w)
    y0, y1 = cell(torch.floor(y - r), tiles_h), cell(torch.ceil(y + r), tiles_h)
    empty = radii <= 0
    x1 = torch.where(empty, x0, x1)
    y1 = torch.where(empty, y0, y1)
    return x0, x1, y0, y1


def tile_lists(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tiles_w: int, tiles_h: int, capacity: int
) -> TileLists:
    """The tile lists of one camera's Gaussians (`means2d` [1, N, 2], `radii` [1, N], `depths` [1, N]) in `capacity`
    entries, built on the device without a host read (see the module docstring)."""
    if means2d.shape[0] != 1:
        raise ValueError(f"tile lists are built for one camera, got {means2d.shape[0]}")
    if capacity < 1:
        raise ValueError(f"the tile lists' capacity must be >= 1, got {capacity}")
    device = means2d.device
    entry = torch.arange(capacity, device=device)
    # Padding: one dummy tile per column below the image, spread so that no tile reads more than its share.
    key = torch.bitwise_left_shift(tiles_h * tiles_w + torch.remainder(entry, tiles_w), 32)
    flatten = torch.zeros(capacity, dtype=torch.int64, device=device)
    n = means2d.shape[1]
    counts = torch.zeros(n, dtype=torch.int64, device=device)
    total = torch.zeros(1, dtype=torch.int64, device=device)
    if n:
        x0, x1, y0, y1 = tile_rectangles(means2d[0], radii[0], tile_size, tiles_w, tiles_h)
        width = x1 - x0
        counts = width * (y1 - y0)
        ends = torch.cumsum(counts, 0)
        total = ends[-1:]
        # Entry e belongs to the first Gaussian whose cumulative count exceeds it; past the total, to none.
        owner = torch.searchsorted(ends, entry, right=True)
        used = owner < n
        g = owner.clamp_max(n - 1)
        local = entry - (ends[g] - counts[g])
        w = width[g].clamp_min(1)
        tile = (y0[g] + torch.div(local, w, rounding_mode="floor")) * tiles_w + x0[g] + torch.remainder(local, w)
        # The depth's fp32 bits below the tile id, as gsplat packs them.
        depth_bits = torch.bitwise_and(depths[0].contiguous().view(torch.int32).to(torch.int64)[g], 0xFFFFFFFF)
        key = torch.where(used, torch.bitwise_or(torch.bitwise_left_shift(tile, 32), depth_bits), key)
        flatten = torch.where(used, g, flatten)
    keys, order = torch.sort(key, stable=True)
    tiles = torch.arange((tiles_h + 1) * tiles_w, device=device)
    offsets = torch.searchsorted(torch.bitwise_right_shift(keys, 32), tiles).to(torch.int32)
    return TileLists(
        keys, flatten[order].to(torch.int32), offsets.view(1, tiles_h + 1, tiles_w), counts.to(torch.int32)[None], total
    )


class TileCapacity:
    """The capacity of a training run's tile lists: chosen on the host, never read from the GPU in the step.

    Each step's total is copied to pinned host memory without waiting and read once its copy has landed (a step or
    more later). The capacity is `margin` times the largest total seen, rounded up to `step`; it is measured
    again, with one wait, when the count of Gaussians changes (refinements, pruning). A total over the capacity
    means that step's lists lost their last entries: counted in `overflows` and told once."""

    def __init__(self, margin: float = 1.5, step: int = CAPACITY_STEP) -> None:
        if not margin >= 1.0 or step < 1:
            raise ValueError(f"the tile lists' margin must be >= 1 and their step >= 1, got {margin} and {step}")
        self.margin = float(margin)
        self.step = int(step)
        self.capacity = 0
        self.gaussians = -1
        self.largest = 0
        self.overflows = 0
        self.pending: List[Tuple[Tensor, int, Optional[torch.cuda.Event]]] = []

    def _fit(self, total: int) -> None:
        want = int(math.ceil(self.margin * max(total, 1) / self.step)) * self.step
        self.capacity = max(self.capacity, want)

    def _settle(self) -> None:
        """Read the totals whose copies have landed."""
        still: List[Tuple[Tensor, int, Optional[torch.cuda.Event]]] = []
        for host, capacity, done in self.pending:
            if done is not None and not done.query():
                still.append((host, capacity, done))
                continue
            total = int(host[0])
            self.largest = max(self.largest, total)
            if total > capacity:
                self.overflows += 1
                if self.overflows == 1:
                    CONSOLE.print(
                        f"[yellow]Tile lists: a step needed {total} entries of its {capacity}; its farthest tiles of "
                        "the last Gaussians were left out. The capacity grows now.[/yellow]"
                    )
            self._fit(total)
        self.pending = still

    def __call__(
        self, means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tiles_w: int, tiles_h: int
    ) -> TileLists:
        """The step's `TileLists`."""
        n = means2d.shape[1]
        self._settle()
        if n != self.gaussians:  # a new count: one wait for the true total
            self.gaussians = n
            x0, x1, y0, y1 = tile_rectangles(means2d[0], radii[0], tile_size, tiles_w, tiles_h)
            need = int(((x1 - x0) * (y1 - y0)).sum())
            self.largest = need
            self.capacity = 0
            self._fit(need)
        lists = tile_lists(means2d, radii, depths, tile_size, tiles_w, tiles_h, self.capacity)
        cuda = lists.total.is_cuda
        host = torch.empty(1, dtype=torch.int64, pin_memory=cuda)
        host.copy_(lists.total, non_blocking=cuda)
        done = None
        if cuda:
            done = torch.cuda.Event()
            done.record()
        self.pending.append((host, self.capacity, done))
        return lists
