"""The host's side of a training step: the CUDA host synchronisations a window causes and the lines they come from
(torch's sync debug mode), and per step the CUDA runtime calls and the costliest host operations (from the profiler)."""

from __future__ import annotations

import re
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch


class SyncCounter:
    """Counts CUDA host synchronisations while active (torch's sync debug mode) and where they come from."""

    def __init__(self) -> None:
        self.count = 0
        self.sources: Counter = Counter()
        self._catch: Optional[Any] = None
        self._log: List[Any] = []

    def start(self) -> None:
        self._catch = warnings.catch_warnings(record=True)
        self._log = self._catch.__enter__()
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")

    def stop(self) -> None:
        torch.cuda.set_sync_debug_mode("default")
        if self._catch is not None:
            self._catch.__exit__(None, None, None)
        for w in self._log:
            if "synchronizing" in str(w.message):
                self.count += 1
                self.sources[f"{Path(w.filename).name}:{w.lineno}"] += 1


# CUDA runtime and driver calls as the profiler names them on the host (cudaLaunchKernel, cuLaunchKernelEx,
# cudaGraphLaunch, cudaMemcpyAsync, cudaStreamSynchronize ...).
RUNTIME_CALL = re.compile(r"^cu(da)?[A-Z]")


def host_op_summary(prof: Any, steps: int, top: int = 12) -> Dict[str, Any]:
    """Per step, from a finished torch profiler that recorded the host: `launches_per_step` (kernel and graph
    launches), `runtime_calls_per_step` (every CUDA runtime call by name) and `top_host_ops` (the `top` host
    operations by their own time: name, calls and milliseconds per step)."""
    runtime: Dict[str, float] = {}
    ops: List[Tuple[float, str, int]] = []
    for e in prof.key_averages():
        if getattr(e, "device_type", None) not in (None, torch.autograd.DeviceType.CPU):
            continue  # the kernels themselves: the GPU's side
        if RUNTIME_CALL.match(e.key):
            runtime[e.key] = e.count / steps
        else:
            ops.append((float(e.self_cpu_time_total), e.key, int(e.count)))
    ops.sort(key=lambda o: -o[0])
    return {
        "launches_per_step": sum(v for k, v in runtime.items() if "Launch" in k),
        "runtime_calls_per_step": dict(sorted(runtime.items(), key=lambda kv: -kv[1])),
        "top_host_ops": [
            {"name": name, "calls_per_step": count / steps, "self_ms_per_step": us / 1e3 / steps}
            for us, name, count in ops[:top]
        ],
    }
