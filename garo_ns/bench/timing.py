"""The benchmark's timing beyond the FPS protocol of `garo_ns.tools.fps`: several trained variants timed in
alternating passes (`paired_fps`), each pass a model's whole view set (`frame_pass`).
"""

from __future__ import annotations

import statistics
import time
from typing import Any, Callable, Dict, List

import torch

from garo_ns.tools.fps import model_background, prepare_views, synchronize


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
    background = model_background(model)
    device = model.device

    def run() -> int:
        for view in views:
            model.render(view, backgrounds=background)
            synchronize(device)
        return len(views)

    return run
