"""The GPU's side of a profiled window: the share of its wall time the GPU spends in kernels and copies, and the
costliest GPU events per step, read from a finished torch profiler's table."""

from __future__ import annotations

from typing import Any, Dict, List, Optional

import torch


def _device_events(prof: Any) -> List[Any]:
    """The GPU's own events of a finished torch profiler (kernels, copies, sets), as torch's table totals them: a
    CPU event's device time is that of the kernels it launched, which appear again here, and a user annotation's
    GPU range spans kernels counted already."""
    cpu = torch.autograd.DeviceType.CPU
    return [
        e
        for e in prof.key_averages()
        if getattr(e, "device_type", None) not in (None, cpu) and not getattr(e, "is_user_annotation", False)
    ]


def kernel_share(prof: Any, wall_ms: float) -> Optional[float]:
    """Share of `wall_ms` the GPU spent in kernels and copies (their summed time), from a finished torch profiler.
    The GPU's own events only: a profiler that also records the CPU holds a launched kernel's time again under the
    op that launched it (tests/test_train_profile.py)."""
    total_us = sum(float(e.self_device_time_total or 0.0) for e in _device_events(prof))
    return total_us / 1e3 / wall_ms if wall_ms > 0 else None


def top_kernels(prof: Any, steps: int, top: int = 15) -> List[Dict[str, Any]]:
    """The `top` GPU events by their time: name (cut at 100 characters), calls and milliseconds per step."""
    events = sorted(_device_events(prof), key=lambda e: -float(e.self_device_time_total or 0.0))
    return [
        {
            "name": e.key[:100],
            "calls_per_step": e.count / steps,
            "ms_per_step": float(e.self_device_time_total) / 1e3 / steps,
        }
        for e in events[:top]
    ]
