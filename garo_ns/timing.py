"""Render-time measurement with the FPS protocol of the benchmarks.

Per view: deformation MLP + rasterization only (what a viewer pays per frame), timed with CUDA
synchronisation on both sides, no metric computation, no disk writes; the first `warmup` views
are rendered but dropped; the figure is the mean over the remaining views at the dataset's full
resolution, reported as FPS = 1 / mean seconds. The MLP and the rasterization are also timed
apart (separate synchronised runs) to show where the time goes.
"""

from __future__ import annotations

import time
from typing import Any, Dict, Tuple

import torch

from garo_ns.garo_model import viewmat_from_c2w
from garo_ns.rendering import rasterize


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def render_view(model: Any, camera: Any) -> torch.Tensor:
    """Deform and rasterize one view, nothing else; returns the RGB render."""
    return _rasterize(model, camera, model.splat_inputs(model.camera_time(camera)))


def _rasterize(model: Any, camera: Any, inputs: Tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Rasterize the output of `model.splat_inputs` for one camera."""
    means, quats, scales, opacities, colors = inputs
    render, _, _ = rasterize(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmat_from_c2w(camera.camera_to_worlds.to(model.device)),
        Ks=camera.get_intrinsics_matrices().to(model.device),
        width=int(camera.width.item()),
        height=int(camera.height.item()),
        sh_degree=model.config.sh_degree,
        backgrounds=model.background_color.to(model.device)[None],
        backend=model.config.rasterizer,
        lean=model.config.lean_raster,
    )
    return render


@torch.no_grad()
def measure_fps(model: Any, cameras: Any, warmup: int = 5, repeats: int = 3) -> Dict[str, Any]:
    """FPS of `model` over `cameras` (see the module docstring), plus the MLP/raster split in ms."""
    model.eval()
    device = model.device
    cams = [cameras[i : i + 1].to(device) for i in range(len(cameras))]
    for i in range(warmup):
        render_view(model, cams[i % len(cams)])
    _sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    totals, mlps, rasters = [], [], []
    for _ in range(repeats):
        for cam in cams:
            _sync(device)
            t0 = time.perf_counter()
            render_view(model, cam)
            _sync(device)
            totals.append(time.perf_counter() - t0)
    for cam in cams:
        _sync(device)
        t0 = time.perf_counter()
        g = model.splat_inputs(model.camera_time(cam))
        _sync(device)
        t1 = time.perf_counter()
        _rasterize(model, cam, g)
        _sync(device)
        mlps.append(t1 - t0)
        rasters.append(time.perf_counter() - t1)
    mean = sum(totals) / len(totals)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return {
        "fps": 1.0 / mean,
        "ms_per_view": 1000.0 * mean,
        "ms_deformation": 1000.0 * sum(mlps) / len(mlps),
        "ms_rasterization": 1000.0 * sum(rasters) / len(rasters),
        "views": len(cams),
        "repeats": repeats,
        "render_peak_memory_mb": peak,
    }


@torch.no_grad()
def measure_same_time(model: Any, cameras: Any) -> float:
    """Mean ms per view when the view's time was rendered just before (what the viewer pays while
    the user moves the camera at a fixed time): the deformation cache, then rasterization."""
    model.eval()
    device = model.device
    times = []
    for i in range(len(cameras)):
        cam = cameras[i : i + 1].to(device)
        t = model.camera_time(cam)
        model.splat_inputs(t, cache=model.config.cache_deformation)
        _sync(device)
        t0 = time.perf_counter()
        _rasterize(model, cam, model.splat_inputs(t, cache=model.config.cache_deformation))
        _sync(device)
        times.append(time.perf_counter() - t0)
    return 1000.0 * sum(times) / len(times)


def model_size_mb(model: Any) -> float:
    """Bytes of what a trained model must store to render (Gaussians + deformation MLP), in MiB."""
    tensors = list(model.gauss_params.values()) + list(model.deformation.parameters())
    return sum(t.numel() * t.element_size() for t in tensors) / 2**20
