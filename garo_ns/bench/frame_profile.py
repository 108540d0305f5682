"""Where the time of one rendered frame goes: deformation MLP, projection, colour (SH), sorting
(tile intersection and ordering), compositing, and the Python overhead of the whole call.

Each stage is run on its own between CUDA synchronisations, on the same prepared views as the FPS
protocol (garo_ns.tools.fps); the overhead is the end-to-end frame time minus the sum of the stages,
i.e. what the renderer's Python glue costs. The stages run eagerly (the projection outside any
CUDA graph), so with `cuda_graph` and `lean_raster` the frame can take less than their sum; the
overhead is then reported as 0. Same stages on the CUDA kernels and on the pure-torch
reference, so the profile runs (slowly) on a CPU too.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Any, Dict, Iterator

import torch

from garo_ns.ops.alpha_reach import reach_radii
from garo_ns.render import reference
from garo_ns.render.backend import rasterize_lean, resolve_backend
from garo_ns.render.kernels import TILE_SIZE, lean_front
from garo_ns.render.view import RenderView
from garo_ns.tools.fps import model_background, prepare_views, synchronize

STAGES = ("deformation", "projection", "color", "sorting", "compositing")


def tile_pairs(model: Any, views: Any) -> float:
    """Mean (tile, Gaussian) pairs per view that sorting orders, each splat's box cut to its alpha reach: the count
    compositing walks."""
    total = 0
    for view in views:
        means, quats, scales, opacities = model.gaussians_at(view.time)[:4]
        W, H = view.width, view.height
        radii, means2d, _, conics = reference.project(
            means, reference.covariance(quats, scales), view.viewmat, view.K, W, H
        )
        radii = reach_radii(radii, conics, opacities)
        lo, hi = reference.tile_bounds(means2d, radii, TILE_SIZE, math.ceil(W / TILE_SIZE), math.ceil(H / TILE_SIZE))
        total += int((hi - lo).prod(-1).sum())
    return total / max(len(views), 1)


@torch.no_grad()
def profile_frame(model: Any, cameras: Any, warmup: int = 3, repeats: int = 2) -> Dict[str, float]:
    """Mean milliseconds per view of each stage, of the whole frame, and the overhead.

    Returns a dict with `ms_<stage>` for each of STAGES, `ms_frame` (the whole frame, `model.render`),
    `ms_python_overhead` (frame minus the stages, clamped at 0), `tile_pairs` (per view) and `backend`.
    """
    model.eval()
    device = model.device
    backend = resolve_backend(model.config.rasterizer, device)
    views = prepare_views(model, cameras)
    background = model_background(model)
    totals: Dict[str, float] = defaultdict(float)

    @contextmanager
    def stage(name: str, record: bool) -> Iterator[None]:
        synchronize(device)
        t0 = time.perf_counter()
        yield
        synchronize(device)
        if record:
            totals[name] += time.perf_counter() - t0

    count = 0
    for rep in range(repeats + 1):
        for i, view in enumerate(views):
            record = rep > 0 or i >= warmup  # the first views of the first pass warm caches up
            _staged_frame(model, view, backend, lambda name: stage(name, record))
            with stage("frame", record):
                model.render(view, backgrounds=background)
            count += int(record)
    out = {f"ms_{k}": 1000.0 * v / max(count, 1) for k, v in totals.items()}
    out["ms_python_overhead"] = max(0.0, out["ms_frame"] - sum(out[f"ms_{s}"] for s in STAGES))
    out["backend"] = backend  # type: ignore[assignment]
    out["tile_pairs"] = tile_pairs(model, views)
    return out


def _staged_frame(model: Any, view: RenderView, backend: str, stage: Any) -> None:
    """One frame through the stages of the renderer (classic mode, unpacked, RGB): on CUDA the
    kernels of `rendering.rasterize_lean`, elsewhere the reference rasterizer's functions."""
    with stage("deformation"):  # MLP, composition and activations (one graph replay with cuda_graph)
        splats = model.gaussians_at(view.time)
    means, quats, scales, opacities, shs = splats[:5]
    viewmats, Ks, W, H = view.viewmat, view.K, view.width, view.height
    degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    if backend == "cuda":  # the lean path's own steps, timed where they run
        background = model_background(model)
        with stage("projection"):  # as the frame projects: the camera's graph (alpha-reach tile lists) where it has one
            front = model.frame.front(splats, view) if model.render_settings().lean_raster else None
            if front is None:
                front = lean_front(means, quats, scales, viewmats, Ks, W, H, True)
        rasterize_lean(
            means, quats, scales, opacities, shs, viewmats, Ks, W, H, degree, background, stage=stage, front=front
        )
        return
    tw, th = math.ceil(W / TILE_SIZE), math.ceil(H / TILE_SIZE)
    campos = torch.linalg.inv(viewmats)[:, :3, 3]
    from garo_ns.render.sh import eval_sh

    with stage("projection"):
        radii, means2d, depths, conics = reference.project(
            means, reference.covariance(quats, scales), viewmats, Ks, W, H
        )
    with stage("color"):
        colors = torch.clamp_min(eval_sh(degree, means[None] - campos[:, None], shs[None]) + 0.5, 0.0)
    with stage("sorting"):
        radii = reference.reach_radii(radii, conics, opacities[None])  # as the reference rasterizer sorts
        _, tile_ids, flat_ids = reference.intersect_tiles(means2d, radii, depths, TILE_SIZE, tw, th)
    with stage("compositing"):
        reference.composite(means2d, conics, opacities[None], colors, tile_ids, flat_ids, W, H, TILE_SIZE)
