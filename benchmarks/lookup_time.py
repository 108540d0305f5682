"""Where the time table's lookup stage goes, for a tabled model (a benchmark export laid out under WORK_DIR):

    python benchmarks/lookup_time.py EXPORT SCENE WORK_DIR OUT.json

In ms per frame at the test views' times: `stage_ms` as garo_ns.bench.frame_profile times it (synchronise,
`gaussians_at`, synchronise), `sync_ms` the two synchronisations alone, `host_ms` `gaussians_at` called back to back
without synchronising (the host's share), `device_ms` the lookup kernel replayed 100 times from one CUDA graph (the
device's share, no launches), `host_parts_ms` some of the host's steps alone.
"""

import json
import os
import sys
import time
from pathlib import Path

import torch

from garo_ns.bench.transfer import import_run
from garo_ns.render.graphs import parameter_list, versions
from garo_ns.render.table_lookup import fused_available, table_splats
from garo_ns.tools.eval import load_run, split_views
from garo_ns.tools.fps import synchronize


def per_call(fn, times, repeats: int = 5) -> float:
    """Milliseconds per call of fn(t) over `times`, `repeats` passes, without synchronising between calls."""
    fn(times[0])
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for t in times:
            fn(t)
        best = min(best, (time.perf_counter() - t0) / len(times))
    return 1000.0 * best


def main() -> None:
    export, scene, work, out = map(Path, sys.argv[1:5])
    record = import_run(export, work, scene)
    _, pipeline, _, _ = load_run(Path(record["config"]))
    model = pipeline.model
    device = model.device
    cameras = split_views(pipeline, scene, "test")[0]
    times = [float(cameras.times[i]) for i in range(len(cameras))] * 10
    with torch.no_grad():
        model.gaussians_at(times[0])
        synchronize(device)
        table = model.frame.table
        rows = model.frame._table_rows
        result = {"scene": scene.name, "variant": record["variant"], "device": str(device)}
        result["git_commit"] = os.environ.get("GARO_GIT_COMMIT")  # device_run.sh sets it
        result["gpu"] = torch.cuda.get_device_name(0) if device.type == "cuda" else None
        result["tabled"] = table is not None and rows is not None
        result["gaussians"] = int(model.canonical().means.shape[0])

        def stage(t: float) -> None:
            synchronize(device)
            model.gaussians_at(t)
            synchronize(device)

        result["stage_ms"] = per_call(stage, times)
        result["sync_ms"] = per_call(lambda t: (synchronize(device), synchronize(device)), times)
        result["host_ms"] = per_call(model.gaussians_at, times)
        synchronize(device)
        canonical, field, spec = model.canonical(), model.deformation, model.switches.table_spec()
        parts = {
            "canonical": lambda t: model.canonical(),
            "render_settings": lambda t: model.render_settings(),
            "table_spec": lambda t: model.switches.table_spec(),
            "versions": lambda t: versions([*canonical, *parameter_list(field)]),
            "time_table": lambda t: model.frame.time_table(field, canonical, spec, t),
            "time_to_device": lambda t: torch.tensor(t, device=device),
        }
        result["host_parts_ms"] = {name: per_call(fn, times) for name, fn in parts.items()}
        if result["tabled"] and device.type == "cuda" and fused_available(table, rows[0]):
            t = torch.tensor(times[0], device=device)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                for _ in range(100):
                    table_splats(table, rows[0], t)
            graph.replay()
            synchronize(device)
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            for _ in range(10):
                graph.replay()
            end.record()
            synchronize(device)
            result["device_ms"] = start.elapsed_time(end) / 1000.0
    print(json.dumps(result, indent=1))
    out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
