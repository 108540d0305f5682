"""Render-time measurement with the FPS protocol of the benchmarks.

Per view: deformation MLP + rasterization only (what a viewer pays per frame), timed with CUDA
synchronisation on both sides, no metric computation, no disk writes; the first `warmup` views
are rendered but dropped; the figure is the mean over the remaining views at the dataset's full
resolution, reported as FPS = 1 / mean seconds. Each view's camera matrices (world-to-camera,
intrinsics) are prepared on the device before timing, as the official D-3DGS code prepares them
when it loads its cameras: they belong to the dataset, not to the frame. The MLP and the
rasterization are also timed apart (separate synchronised runs) to show where the time goes.
"""

from __future__ import annotations

import statistics
import time
from typing import Any, Callable, Dict, List

import torch

from garo_ns.render.view import RenderView
from garo_ns.tools.eval import synchronize


def prepare_views(model: Any, cameras: Any) -> List[RenderView]:
    """Every camera of `cameras` as `model.render` takes it, on the model's device."""
    return [model.camera_view(cameras[i : i + 1].to(model.device)) for i in range(len(cameras))]


def _background(model: Any) -> torch.Tensor:
    return model.background_color.to(model.device)[None]


@torch.no_grad()
def render_view(model: Any, camera: Any) -> torch.Tensor:
    """Deform and rasterize one camera's view, nothing else; returns the RGB render [1, H, W, 3]."""
    return model.render(model.camera_view(camera.to(model.device)), backgrounds=_background(model))[0]


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


@torch.no_grad()
def paired_fps(
    frames: Dict[str, Callable[[], Any]], device: torch.device, passes: int = 6, warmup: int = 1
) -> Dict[str, Dict[str, Any]]:
    """Time several renderers in alternating passes: pass p runs every renderer once, in the given order
    when p is even and reversed when odd (A B, B A, ...), so a drift of the machine (clocks, other load)
    falls on all of them alike; each renderer's figure is the median of its pass times, so one stalled
    pass does not move it. `frames[name]()` renders that renderer's whole view set once, frame by frame
    (synchronising after each frame, as the FPS protocol does); returns per renderer the mean ms per frame
    of each pass, their median and FPS from it."""
    device = torch.device(device)
    names = list(frames)
    for _ in range(warmup):
        for name in names:
            frames[name]()
    synchronize(device)
    pass_ms: Dict[str, List[float]] = {name: [] for name in names}
    for p in range(passes):
        for name in names if p % 2 == 0 else names[::-1]:
            synchronize(device)
            t0 = time.perf_counter()
            count = frames[name]()
            synchronize(device)
            pass_ms[name].append(1000.0 * (time.perf_counter() - t0) / max(int(count), 1))
    out = {}
    for name, ms in pass_ms.items():
        median = statistics.median(ms)
        out[name] = {"fps": 1000.0 / median, "ms_per_view_median_pass": median, "pass_ms_per_view": ms}
    return out


def frame_pass(model: Any, cameras: Any) -> Callable[[], int]:
    """One pass of `model` over `cameras` as `paired_fps` takes it: every view rendered and synchronised
    in turn (camera matrices prepared beforehand, as in the FPS protocol); returns the number of views."""
    views = prepare_views(model, cameras)
    background = _background(model)
    device = model.device

    def run() -> int:
        for view in views:
            model.render(view, backgrounds=background)
            synchronize(device)
        return len(views)

    return run


def measure_fps(model: Any, cameras: Any, warmup: int = 5, repeats: int = 3) -> Dict[str, Any]:
    """FPS of `model` over `cameras` (see the module docstring), plus the MLP/raster split in ms."""
    model.eval()
    background = _background(model)
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
    background = _background(model)
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
