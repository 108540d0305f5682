"""Python's garbage collector while a model trains: its youngest generation collected every `threshold` net
allocations of containers instead of CPython's 700.

A training step allocates a few thousand Python containers (autograd nodes, tensor wrappers, the loop's dicts),
most freed by reference counting within the step. At the default threshold the collector runs two or three times a
step and scans what the step still holds each time. A small effect, measured: 600 CPU steps on a synthetic scene
spent 0.53 and 0.58 s of their 51 and 56 s in 1,519 collections at CPython's threshold, 0.03 s in 211 at 20,000
(benchmarks/results/collector_cpu.json, `benchmarks/collector_cpu.py` at 7997206); the three 40k runs alone on an H100
with it moved by no more than two runs' spread (docs/benchmarks.md). What only the collector frees (reference
cycles) waits a few steps longer.

`collector_paused` keeps the collector out of a CUDA graph's capture: a dropped graph lives in reference cycles
(torch's graphed callables are autograd Function classes holding their graphs), so only a collection frees it, and
a graph freed while another is being captured invalidates that capture (a `deform-splatfacto` run crashed so at a
new count of Gaussians, with a dozen dropped graphs collected at once).
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from typing import Iterator, Optional, Tuple

DEFAULT_THRESHOLD = 20_000


class TrainingCollector:
    """Sets the collector's youngest threshold while training (`start`) and gives the previous thresholds back
    (`stop`); a threshold of 0 leaves the collector as it is. Starting twice keeps the first saved thresholds."""

    def __init__(self, threshold: int = DEFAULT_THRESHOLD) -> None:
        if threshold < 0:
            raise ValueError(f"the collector's threshold must be >= 0 (0: Python's own), got {threshold}")
        self.threshold = int(threshold)
        self.saved: Optional[Tuple[int, ...]] = None

    def start(self) -> None:
        if self.threshold == 0 or self.saved is not None:
            return
        self.saved = gc.get_threshold()
        gc.set_threshold(self.threshold, *self.saved[1:])

    def stop(self) -> None:
        if self.saved is not None:
            gc.set_threshold(*self.saved)
            self.saved = None


@contextmanager
def collector_paused() -> Iterator[None]:
    """No collection while the body runs (a CUDA graph's capture: see the module docstring); the collector is
    enabled afterwards only if it was before."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
