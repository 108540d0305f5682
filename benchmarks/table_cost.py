"""What each trained model's time table costs: memory, load to first frame, lookup and frame, before and after the
table's file (garo_ns.render.table_cache), from committed result files.

    python benchmarks/table_cost.py OUT.json SCENE:VARIANT:TABLE_FILE[:FRAME_FILE] ...

TABLE_FILE: benchmarks/table_file.py's rows for that model (its first load built the table and wrote its file, as
every load did before the file existed; its second read the file; its third cut a 1 GB window from it). FRAME_FILE:
the benchmark run that trained the model (garo_ns.bench.benchmark), whose `VARIANT+auto` row gives the lookup's and
the frame's milliseconds (garo_ns.bench.frame_profile: `ms_deformation` is the lookup where the table serves the
frame). A VARIANT whose table was refused has a FRAME_FILE only (write `-` for TABLE_FILE). Names are relative to
benchmarks/results/.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

RESULTS = Path(__file__).parent / "results"
LOADS = {"first load": "built", "second load": "read", "window 1024 MB": "window"}


def frame_row(frame_file: Optional[str], variant: str) -> Dict[str, Any]:
    """The `VARIANT+auto` row of a benchmark file, or {}."""
    if not frame_file:
        return {}
    return json.loads((RESULTS / frame_file).read_text())["variants"].get(f"{variant}+auto", {})


def rows_of(scene: str, variant: str, table_file: Optional[str], frame_file: Optional[str]) -> List[Dict[str, Any]]:
    """One row per load of one model."""
    frame = frame_row(frame_file, variant)
    profile = frame.get("profile") or {}
    tabled = bool((frame.get("render_switches_used") or {}).get("time_table", table_file is not None))
    common = {
        "scene": scene,
        "variant": variant,
        "lookup_ms": profile.get("ms_deformation") if tabled else None,
        "frame_ms": profile.get("ms_frame"),
        "frame_file": frame_file,
    }
    if table_file is None:  # the table was refused: the field serves the frame, nothing is held or loaded
        change = ((frame.get("switch_record") or {}).get("tried") or {}).get("time_table")
        load_s = frame.get("load_seconds", 0.0) + frame.get("first_frame_seconds", 0.0)
        return [{**common, "load": "refused", "table_mb": 0.0, "load_s": load_s, "refused_change_db": change}]
    data = json.loads((RESULTS / table_file).read_text())
    out = []
    for row in data["rows"]:
        table = row.get("table") or {}
        out.append(
            {
                **common,
                "load": LOADS.get(row["load"], row["load"]),
                "table_mb": table.get("mb"),
                # Load to first frame, as the target counts it: the load (table included) and the first render.
                "load_s": row["load_s"] + row["first_frame_s"],
                "fps_in_time_order": row["fps"],
                "table_file": table_file,
                "cuda_mps": data.get("cuda_mps"),
                "git_commit": data.get("git_commit"),
            }
        )
    return out


def main(argv: List[str]) -> None:
    out, specs = Path(argv[0]), argv[1:]
    rows: List[Dict[str, Any]] = []
    for spec in specs:
        scene, variant, table_file, *frame = spec.split(":")
        rows += rows_of(scene, variant, None if table_file == "-" else table_file, frame[0] if frame else None)
    targets = {"table_mb": 1024.0, "load_s": 5.0, "lookup_ms": 0.05}
    result = {"command": "python benchmarks/table_cost.py " + " ".join(argv), "targets": targets, "rows": rows}
    out.write_text(json.dumps(result, indent=1) + "\n")
    for r in rows:
        print(r["scene"], r["variant"], r["load"], r["table_mb"], r["load_s"], r["lookup_ms"], r["frame_ms"])


if __name__ == "__main__":
    main(sys.argv[1:])
