"""How well a linear time table's keys, as laid out today, give the frame at the ends of the time range.

    python benchmarks/table_edge.py EXPORT SCENE INTERVALS OUT.json

Keys sit at the centres of the range's cells (garo_ns.render.time_table.TableSpec.key_times), so a frame at the
range's first or last time is the midpoint of an inside key and a key half a cell outside the range, sampled from the
field at a time no frame was trained at. For a trained model (a benchmark export laid out under /tmp/table_edge by
garo_ns.bench.transfer) this compares, at a few times, the field's means with the linear interpolation between the
two keys around that time, in fp32 on the CPU (no table is built: its rounding of keys comes on top). INTERVALS: the
model's table spec (its record's `time_table.spec.intervals`).
"""

import json
import sys
from pathlib import Path

import torch

from garo_ns.bench.transfer import import_run
from garo_ns.render.frame import compose
from garo_ns.render.time_table import PAD, TableSpec
from garo_ns.tools.eval import load_run


def main() -> None:
    export, scene, intervals, out = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
    record = import_run(export, Path("/tmp/table_edge"), scene)
    _, pipeline, _, _ = load_run(Path(record["config"]), settings={"time_table": False})
    model = pipeline.model
    canonical = model.canonical()
    spec = TableSpec(t_lo=0.0, t_hi=1.0, intervals=intervals)
    key_t = spec.key_times().double()

    def means(t: float) -> torch.Tensor:
        with torch.no_grad():
            return compose(model.deformation, canonical, t, model.config.deform_scale_offset)[0].double()

    rows = []
    for t in (0.0, 0.25, 0.5, 0.75, 1.0):
        i, f = spec.segment(t)
        lo, hi = float(key_t[i]), float(key_t[i + 1])
        error = (means(lo) * (1 - f) + means(hi) * f - means(t)).norm(dim=-1)
        rows.append(
            {
                "time": t,
                "keys": [lo, hi],
                "fraction": f,
                "key_outside_range": not (0.0 <= lo and hi <= 1.0),
                "max": error.max().item(),
                "p99": error.quantile(0.99).item(),
                "mean": error.mean().item(),
            }
        )
        print(json.dumps(rows[-1]))
    result = {"export": str(export), "variant": record["variant"], "intervals": intervals, "pad": PAD, "rows": rows}
    out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
