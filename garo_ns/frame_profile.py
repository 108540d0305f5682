"""Where the time of one rendered frame goes: deformation MLP, projection, colour (SH), sorting
(tile intersection and ordering), compositing, and the Python overhead of the whole call.

Each stage is run on its own between CUDA synchronisations, on the same views as the FPS
protocol (garo_ns.timing); the overhead is the end-to-end frame time minus the sum of the stages,
i.e. what the renderer's Python glue costs. Same stages on the CUDA kernels and on the pure-torch
reference, so the profile runs (slowly) on a CPU too.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Any, Dict, Iterator

import torch

from garo_ns.garo_model import viewmat_from_c2w
from garo_ns.rendering import TILE_SIZE, rasterize_lean, resolve_backend
from garo_ns.timing import render_view

STAGES = ("deformation", "projection", "color", "sorting", "compositing")


@torch.no_grad()
def profile_frame(model: Any, cameras: Any, warmup: int = 3, repeats: int = 2) -> Dict[str, float]:
    """Mean milliseconds per view of each stage, of the whole frame, and the overhead.

    Returns a dict with `ms_<stage>` for each of STAGES, `ms_frame` (the timed render_view call),
    `ms_python_overhead` (frame minus the stages, clamped at 0) and `backend`.
    """
    model.eval()
    device = model.device
    backend = resolve_backend(model.config.rasterizer, device)
    cams = [cameras[i : i + 1].to(device) for i in range(len(cameras))]
    totals: Dict[str, float] = defaultdict(float)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    @contextmanager
    def stage(name: str, record: bool) -> Iterator[None]:
        sync()
        t0 = time.perf_counter()
        yield
        sync()
        if record:
            totals[name] += time.perf_counter() - t0

    count = 0
    for rep in range(repeats + 1):
        for i, cam in enumerate(cams):
            record = rep > 0 or i >= warmup  # the first views of the first pass warm caches up
            _staged_frame(model, cam, backend, lambda name: stage(name, record))
            with stage("frame", record):
                render_view(model, cam)
            count += int(record)
    out = {f"ms_{k}": 1000.0 * v / max(count, 1) for k, v in totals.items()}
    out["ms_python_overhead"] = max(0.0, out["ms_frame"] - sum(out[f"ms_{s}"] for s in STAGES))
    out["backend"] = backend  # type: ignore[assignment]
    return out


def _staged_frame(model: Any, cam: Any, backend: str, stage: Any) -> None:
    """One frame through the stages of the renderer (classic mode, unpacked, RGB): on CUDA the
    kernels of `rendering.rasterize_lean`, elsewhere the reference rasterizer's functions."""
    with stage("deformation"):  # MLP, composition and activations (one graph replay with cuda_graph)
        means, quats, scales, opacities, shs = model.splat_inputs(model.camera_time(cam))
    viewmats = viewmat_from_c2w(cam.camera_to_worlds)
    Ks = cam.get_intrinsics_matrices().to(means.device)
    W, H = int(cam.width.item()), int(cam.height.item())
    degree = model.config.sh_degree
    if backend == "cuda":  # the lean path's own steps, timed where they run
        background = model.background_color.to(means.device)[None]
        rasterize_lean(means, quats, scales, opacities, shs, viewmats, Ks, W, H, degree, background, stage=stage)
        return
    tw, th = math.ceil(W / TILE_SIZE), math.ceil(H / TILE_SIZE)
    campos = torch.linalg.inv(viewmats)[:, :3, 3]
    from garo_ns import rasterizer
    from garo_ns.sh import eval_sh

    with stage("projection"):
        radii, means2d, depths, conics = rasterizer.project(
            means, rasterizer.covariance(quats, scales), viewmats, Ks, W, H
        )
    with stage("color"):
        colors = torch.clamp_min(eval_sh(degree, means[None] - campos[:, None], shs[None]) + 0.5, 0.0)
    with stage("sorting"):
        _, tile_ids, flat_ids = rasterizer.intersect_tiles(means2d, radii, depths, TILE_SIZE, tw, th)
    with stage("compositing"):
        rasterizer.composite(means2d, conics, opacities[None], colors, tile_ids, flat_ids, W, H, TILE_SIZE)
