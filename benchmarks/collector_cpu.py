"""What Python's garbage collector costs a CPU training run, at CPython's threshold and at the recipe's.

Trains `garo-deform` on a small synthetic scene (garo_ns.tools.scene; the pure-torch rasterizer) for `steps` steps,
once per `gc_threshold` in `--thresholds` (0: CPython's own 700), alternating `--repeats` times, each run a process
of its own (nerfstudio's writers are process-wide), and records per run the wall seconds of training and, from
`gc.callbacks`, each generation's collections and the seconds spent in them.

    python benchmarks/collector_cpu.py --output benchmarks/results/collector_cpu.json
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List


class CollectionClock:
    """Collections per generation and the seconds spent in them, while installed."""

    def __init__(self) -> None:
        self.counts = [0, 0, 0]
        self.seconds = [0.0, 0.0, 0.0]
        self._start = 0.0

    def __call__(self, phase: str, info: Dict[str, Any]) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        else:
            self.counts[info["generation"]] += 1
            self.seconds[info["generation"]] += time.perf_counter() - self._start


def one_run(threshold: int, steps: int, root: Path) -> Dict[str, Any]:
    from garo_ns.tools.scene import SceneSpec, generate_scene
    from garo_ns.tools.train import QuickSchedule, make_config, train

    scene = generate_scene(root / "scene", SceneSpec(resolution=24, n_train=8, n_val=2, n_test=2))
    schedule = QuickSchedule(steps=steps, num_random=600, deform_width=16, deform_depth=2, deform_skip=0)
    config = make_config("garo-deform", scene, root / "runs", schedule=schedule)
    config.pipeline.model.rasterizer = "reference"
    config.pipeline.model.gc_threshold = threshold
    clock = CollectionClock()
    gc.collect()
    gc.callbacks.append(clock)
    start = time.perf_counter()
    try:
        train(config)
    finally:
        gc.callbacks.remove(clock)
    return {
        "gc_threshold": threshold,
        "wall_seconds": time.perf_counter() - start,
        "collections": clock.counts,
        "collection_seconds": clock.seconds,
    }


def main() -> None:
    from garo_ns.bench.benchmark import environment

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--thresholds", type=int, nargs="+", default=[0, 20_000])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # a single run, JSON on stdout
    args = parser.parse_args()
    if args.one is not None:
        with tempfile.TemporaryDirectory() as tmp:
            print("RUN " + json.dumps(one_run(args.one, args.steps, Path(tmp))))
        return
    if args.output is None:
        parser.error("--output is required")
    load_before = list(os.getloadavg())
    runs: List[Dict[str, Any]] = []
    for _ in range(args.repeats):
        for threshold in args.thresholds:
            command = [sys.executable, __file__, "--one", str(threshold), "--steps", str(args.steps)]
            out = subprocess.run(command, capture_output=True, text=True, check=True).stdout
            runs.append(json.loads([line for line in out.splitlines() if line.startswith("RUN ")][-1][4:]))
            print(json.dumps(runs[-1]))
    result = {
        "environment": environment("cpu"),
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": list(os.getloadavg()),
        "steps": args.steps,
        "python_default_threshold": 700,
        "runs": runs,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
