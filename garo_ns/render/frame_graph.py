"""A frame's camera half as one CUDA graph: projection, colours, tile lists and compositing.

The lean path (garo_ns.render.backend.rasterize_lean) replays the projection as a graph, then launches the colours
(gsplat's SH kernel runs on the legacy stream, which no graph can hold), the tile intersection (which reads its pair
count back to the host in the middle of the frame) and the compositing, each from Python. Here all of it is one
replay: the colours in one Triton kernel (garo_ns.render.sh.rendered_colors), the tile lists at a fixed capacity
(garo_ns.render.tile_lists, which also cuts the pairs that only hold skipped pixels) and gsplat's compositing kernel.
The pairs needed come back with the image; a frame that needed more than the capacity is captured again with room
for them and rendered again, so no frame loses a pair.

Same pixels as the lean path, but for the colours' float rounding (our SH sums against gsplat's kernel).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, Hashable, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.render.graphs import InputGraph
from garo_ns.render.kernels import TILE_SIZE, gsplat_kernels, lean_front
from garo_ns.render.sh import rendered_colors
from garo_ns.render.tile_lists import TileGrid, tile_lists

HEADROOM = 1.25  # capacity over the pairs the first frame needed: a moving camera's next frames need about as many
GRANULE = 1 << 16  # capacities are whole multiples: a capture is kept while the need stays under it


def capacity_for(needed: int) -> int:
    """The lists' length for a frame that needs `needed` pairs: with headroom, rounded up to a granule. A RuntimeError
    past int32 (the rasterizer's tile offsets): such a frame takes the lean path."""
    capacity = max(GRANULE, math.ceil(needed * HEADROOM / GRANULE) * GRANULE)
    if capacity >= 2**31:
        raise RuntimeError(f"a frame of {needed} tile pairs: more than the rasterizer's int32 offsets hold")
    return capacity


def capture_errors() -> Tuple[type, ...]:
    """What a refused capture raises: CUDA's RuntimeError, or Triton's compile and resource errors."""
    try:
        from triton.runtime.errors import TritonError
    except ImportError:
        return (RuntimeError,)
    return (RuntimeError, TritonError)


def frame_fn(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    sh_degree: Optional[int],
    grid: TileGrid,
    capacity: int,
    with_depth: bool,
) -> Callable[[Tensor, Tensor, Tensor], Tuple[Tensor, ...]]:
    """The camera half of a frame of these splats as a function of (viewmat [1, 4, 4], K [1, 3, 3], background
    [1, 3]): render [1, H, W, 3 (+1: expected depth)], alpha [1, H, W, 1], radii, means2d, depths, pairs needed."""

    def fn(viewmat: Tensor, K: Tensor, background: Tensor) -> Tuple[Tensor, ...]:
        radii, means2d, depths, conics, dirs, _, _ = lean_front(
            means, quats, scales, viewmat, K, grid.width, grid.height, sh_degree is not None
        )
        rgb = colors[None] if sh_degree is None else rendered_colors(sh_degree, dirs, colors)
        bg = background
        if with_depth:
            rgb = torch.cat([rgb, depths[..., None]], dim=-1)
            bg = torch.cat([background, background.new_zeros(1, 1)], dim=-1)
        ids, offsets, needed = tile_lists(means2d[0], conics[0], opacities, depths[0], radii[0], grid, capacity)
        render, alpha, _ = gsplat_kernels().rasterize_to_pixels_fwd(
            means2d.contiguous(),
            conics.contiguous(),
            rgb.contiguous(),
            opacities[None].contiguous(),
            bg.contiguous(),
            None,
            grid.width,
            grid.height,  # the offsets' extra tile row lies below it: its pixels are outside, its tile closed at once
            TILE_SIZE,
            offsets,
            ids,
        )
        if with_depth:  # expected depth, as gsplat's RGB+ED
            render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
        return render, alpha, radii, means2d, depths, needed

    return fn


class FrameGraph:
    """The camera half of a frame by one graph replay per frame, for one set of splats (the key says which)."""

    def __init__(self) -> None:
        self._graph = InputGraph()
        self.capacity = 0  # the lists' length of the graph held (0: none yet)
        self.regrown = 0  # frames rendered again because they needed more pairs than the capacity

    def __call__(
        self,
        key: Hashable,
        splats: Tuple[Tensor, Tensor, Tensor, Tensor, Tensor],
        sh_degree: Optional[int],
        viewmat: Tensor,
        K: Tensor,
        width: int,
        height: int,
        background: Tensor,
        with_depth: bool,
    ) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
        """render, alpha and the rasterizer's info (radii, means2d, depths), as `rasterize_lean` returns them. The
        image is a copy (a caller may keep it); the info's tensors are the graph's buffers, overwritten next call."""
        grid = TileGrid(width, height, TILE_SIZE)
        while True:
            if self.capacity == 0:
                self.capacity = capacity_for(0)
            fn = frame_fn(*splats, sh_degree, grid, self.capacity, with_depth)
            out = self._graph((key, width, height, sh_degree, with_depth, self.capacity), fn, viewmat, K, background)
            needed = int(out[-1])  # the one read-back of the frame, after its last kernel
            if needed <= self.capacity:
                break
            self.capacity = capacity_for(needed)
            self.regrown += 1
        render, alpha, radii, means2d, depths, _ = out
        info = {"radii": radii, "means2d": means2d, "depths": depths, "width": width, "height": height, "n_cameras": 1}
        return render.clone(), alpha.clone(), info

    def release(self) -> None:
        """Drop the graph and its buffers."""
        self._graph.release()
        self.capacity = 0
