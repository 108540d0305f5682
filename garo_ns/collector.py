"""Python's garbage collector while a model trains: its youngest generation collected every `threshold` net
allocations of containers instead of CPython's 700.

A training step allocates a few thousand Python containers (autograd nodes, tensor wrappers, the loop's dicts),
most freed by reference counting within the step. At the default threshold the collector runs two or three times a
step and scans what the step still holds each time: on the CPU demo scene (600 steps, a 2-core machine) 0.75 s of a
59 s run went to 1,398 young and 127 middle collections, and 0.03 s to 7 collections at a threshold of 20,000. On a
GPU the loop's host time is what a step waits on after densification (docs/benchmarks.md), so the same scans cost
wall time there. What only the collector frees (reference cycles) waits a few steps longer.
"""

from __future__ import annotations

import gc
from typing import Optional, Tuple

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
