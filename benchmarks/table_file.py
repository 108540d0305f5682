"""A model's loads with its time table's file (garo_ns.render.table_cache): the first (table built and written), the
second (read), and one under a 1 GB window (each window cut from the file), each with its load seconds, first frame
and FPS through the test views in time order (garo_ns.tools.fps).

    python benchmarks/table_file.py EXPORT SCENE WORK_DIR OUT.json

EXPORT: a benchmark export of a trained variant (`garo_ns.bench.benchmark --export-dir`), laid out under WORK_DIR as
its run (garo_ns.bench.transfer); OUT.json: one row per load. Run on the GPU machine without CUDA MPS.
"""

import json
import os
import sys
import time
from pathlib import Path

import torch

from garo_ns.bench.transfer import import_run
from garo_ns.tools.eval import load_run, split_views
from garo_ns.tools.fps import measure_fps, synchronize

export, scene, work, out = map(Path, sys.argv[1:5])
record = import_run(export, work, scene)
rows = []
for name, settings in (("first load", {}), ("second load", {}), ("window 1024 MB", {"time_table_window_mb": 1024.0})):
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    _, pipeline, _, _ = load_run(Path(record["config"]), settings=settings)
    model = pipeline.model
    synchronize(model.device)
    load_s = time.perf_counter() - t0
    cameras = split_views(pipeline, scene, "test")[0]
    t1 = time.perf_counter()
    model.render(
        model.camera_view(cameras[0:1].to(model.device)), backgrounds=model.background_color.to(model.device)[None]
    )
    synchronize(model.device)
    first = time.perf_counter() - t1
    timing = measure_fps(model, cameras)
    info = {
        k: v
        for k, v in (model.frame.table_info or {}).items()
        if k in ("mb", "build_s", "file", "window", "keys", "error")
    }
    rows.append(
        {
            "load": name,
            "load_s": load_s,
            "first_frame_s": first,
            "fps": timing["fps"],
            "table": info,
            "render_peak_memory_mb": timing["render_peak_memory_mb"],
            "line": model.switches.line(model.config, False, model.device),
        }
    )
    print(json.dumps(rows[-1]), flush=True)
    del model, pipeline
# What the rows are of, so that a reader (benchmarks/table_cost.py) needs no file name to tell.
head = {"scene": scene.name, "variant": record["variant"], "git_commit": os.environ.get("GARO_GIT_COMMIT")}
head["cuda_mps"] = os.environ.get("GARO_MPS_ON") == "1"
out.write_text(json.dumps({**head, "gpu": torch.cuda.get_device_name(0), "rows": rows}, indent=2))
