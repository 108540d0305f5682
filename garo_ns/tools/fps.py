"""The FPS protocol: how `garo-eval`, `garo-demo` and the benchmark time a trained model's renders.

Per view: deformation MLP + rasterization only (what a viewer pays per frame), timed with CUDA
synchronisation on both sides, no metric computation, no disk writes; the first `warmup` views
are rendered but dropped; the figure is the mean over the remaining views at the dataset's full
resolution, reported as FPS = 1 / mean seconds. Each view's camera matrices (world-to-camera,
intrinsics) are prepared on the device before timing, as the official D-3DGS code prepares them
when it loads its cameras: they belong to the dataset, not to the frame. The MLP and the
rasterization are also timed apart (separate synchronised runs) to show where the time goes.
A frame rate says little without the machine that measured it: `machine` names it.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import torch

from garo_ns.render.view import RenderView


def synchronize(device: Any) -> None:
    """Wait for the GPU's queued work, so a wall-clock time includes it (nothing to wait for on a CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def protocol(warmup: int = 5, repeats: int = 3) -> str:
    """The protocol in one line, as a result file records it beside its frame rates."""
    return (
        "mean over views of synchronised (deformation MLP + rasterization) time, "
        f"{warmup} warm-up views dropped, {repeats} passes, full resolution, "
        "camera matrices prepared on the device before timing"
    )


def prepare_views(model: Any, cameras: Any) -> List[RenderView]:
    """Every camera of `cameras` as `model.render` takes it, on the model's device."""
    return [model.camera_view(cameras[i : i + 1].to(model.device)) for i in range(len(cameras))]


def model_background(model: Any) -> torch.Tensor:
    """The model's background colour as `model.render` takes it, on the model's device."""
    return model.background_color.to(model.device)[None]


@torch.no_grad()
def fps_protocol(
    views: List[Any],
    frame: Callable[[Any], Any],
    deform: Callable[[Any], Any],
    raster: Callable[[Any, Any], Any],
    device: torch.device,
    warmup: int = 5,
    repeats: int = 3,
) -> Dict[str, Any]:
    """The FPS protocol (module docstring) for any renderer: `frame(view)` renders a view,
    `deform(view)` computes its deformed Gaussians and `raster(view, deformed)` rasterizes them (the
    MLP/raster split, timed in a separate pass). Also used for the official D-3DGS code."""
    device = torch.device(device)
    for i in range(warmup):
        frame(views[i % len(views)])
    synchronize(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    totals, mlps, rasters = [], [], []
    for _ in range(repeats):
        for view in views:
            synchronize(device)
            t0 = time.perf_counter()
            frame(view)
            synchronize(device)
            totals.append(time.perf_counter() - t0)
    for view in views:
        synchronize(device)
        t0 = time.perf_counter()
        deformed = deform(view)
        synchronize(device)
        t1 = time.perf_counter()
        raster(view, deformed)
        synchronize(device)
        mlps.append(t1 - t0)
        rasters.append(time.perf_counter() - t1)
    mean = sum(totals) / len(totals)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return {
        "fps": 1.0 / mean,
        "ms_per_view": 1000.0 * mean,
        "ms_deformation": 1000.0 * sum(mlps) / len(mlps),
        "ms_rasterization": 1000.0 * sum(rasters) / len(rasters),
        "views": len(views),
        "repeats": repeats,
        "render_peak_memory_mb": peak,
    }


def measure_fps(model: Any, cameras: Any, warmup: int = 5, repeats: int = 3) -> Dict[str, Any]:
    """FPS of `model` over `cameras` (see the module docstring), plus the MLP/raster split in ms."""
    model.eval()
    background = model_background(model)
    return fps_protocol(
        prepare_views(model, cameras),
        lambda view: model.render(view, backgrounds=background),
        lambda view: model.gaussians_at(view.time),
        lambda view, splats: model.render(view, backgrounds=background, splats=splats),
        model.device,
        warmup,
        repeats,
    )


@torch.no_grad()
def measure_same_time(model: Any, cameras: Any) -> float:
    """Mean ms per view when the view's time was rendered just before (what the viewer pays while
    the user moves the camera at a fixed time): the deformation cache, then rasterization."""
    model.eval()
    device = model.device
    background = model_background(model)
    times = []
    for view in prepare_views(model, cameras):
        model.gaussians_at(view.time)
        synchronize(device)
        t0 = time.perf_counter()
        model.render(view, backgrounds=background, splats=model.gaussians_at(view.time))
        synchronize(device)
        times.append(time.perf_counter() - t0)
    return 1000.0 * sum(times) / len(times)


def model_size_mb(model: Any) -> float:
    """Bytes of what a trained model must store to render (Gaussians + deformation MLP), in MiB."""
    tensors = list(model.gauss_params.values()) + list(model.deformation.parameters())
    return sum(t.numel() * t.element_size() for t in tensors) / 2**20


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> Optional[str]:
    """The CPU's model name as Linux reports it in `cpuinfo` (None where there is none)."""
    try:
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine(device: Any) -> Dict[str, Any]:
    """The machine a frame rate was measured on: its GPU (None on a CPU), CPU, torch and the rasterizer in use."""
    from garo_ns.render.backend import rasterizer_in_use

    device = torch.device(device).type
    return {
        "gpu": torch.cuda.get_device_name(0) if device == "cuda" and torch.cuda.is_available() else None,
        "cpu": platform.processor() or platform.machine(),
        # Training after densification waits on the host: runs on two machines with the same GPU model differ by
        # their CPUs (benchmarks/results/train_profile_tf32_*_H100.json against train_profile_gcpreview_*).
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        # A GPU run whose gsplat failed to load renders through the reference: its times say nothing of gsplat's.
        "rasterizer": rasterizer_in_use(device),
    }
