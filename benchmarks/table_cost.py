"""What each trained model's time table costs: memory, load to first frame, lookup and frame, before and after the
table's file (garo_ns.render.table_cache), from committed result files.

    python benchmarks/table_cost.py OUT.json SCENE:VARIANT:TABLE_FILE:FRAME_FILE ...

TABLE_FILE: benchmarks/table_file.py's rows for that model (its first load built the table and wrote its file, as
every load did before the file existed; its second read the file; its third cut a 1 GB window from it). FRAME_FILE:
the benchmark run that trained the model, whose `VARIANT+auto` row garo_ns.bench.summary.table_cost reads (the
lookup, the frame). For a VARIANT whose table was refused, write `-` for TABLE_FILE. Names are relative to
benchmarks/results/.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

from garo_ns.bench.summary import table_cost

RESULTS = Path(__file__).parent / "results"
LOADS = {"first load": "built", "second load": "read", "window 1024 MB": "window"}


def rows_of(scene: str, variant: str, table_file: Optional[str], frame_file: str) -> List[Dict[str, Any]]:
    """One row per load of one model: the benchmark's own row for it (garo_ns.bench.summary.table_cost), its table
    and load replaced by each load of TABLE_FILE."""
    data = json.loads((RESULTS / frame_file).read_text())
    tabled = [r for r in table_cost([(frame_file, data)]) if r["variant"] == f"{variant}+auto"]
    if table_file is None or not tabled:  # the table was refused: the field serves the frame, nothing is held
        row = data["variants"][f"{variant}+auto"]
        change = ((row.get("switch_record") or {}).get("tried") or {}).get("time_table")
        return [{"scene": scene, "variant": variant, "load": "refused", "table_mb": 0.0, "refused_change_db": change}]
    loads = json.loads((RESULTS / table_file).read_text())
    out = []
    for load in loads["rows"]:
        out.append(
            {
                **tabled[0],
                "scene": scene,
                "variant": variant,
                "load": LOADS.get(load["load"], load["load"]),
                "table_mb": (load.get("table") or {}).get("mb"),
                "build_s": (load.get("table") or {}).get("build_s"),  # this load's: a read where the file was there
                "load_s": load["load_s"] + load["first_frame_s"],  # load to first frame, as the target counts it
                "fps_in_time_order": load["fps"],
                "table_file": table_file,
                "table_file_cuda_mps": loads.get("cuda_mps"),
            }
        )
    return out


def main(argv: List[str]) -> None:
    out, specs = Path(argv[0]), argv[1:]
    rows: List[Dict[str, Any]] = []
    for spec in specs:
        scene, variant, table_file, *frame = spec.split(":")
        rows += rows_of(scene, variant, None if table_file == "-" else table_file, frame[0])
    targets = {"table_mb": 1024.0, "load_s": 5.0, "lookup_ms": 0.05}
    result = {"command": "python benchmarks/table_cost.py " + " ".join(argv), "targets": targets, "rows": rows}
    out.write_text(json.dumps(result, indent=1) + "\n")
    for r in rows:
        print(*(r.get(k) for k in ("scene", "variant", "load", "table_mb", "load_s", "lookup_ms", "frame_ms")))


if __name__ == "__main__":
    main(sys.argv[1:])
