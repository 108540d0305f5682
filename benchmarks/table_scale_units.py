"""How many Gaussians a time table leaves to the network for a model trained with `deform-scale-offset linear`: as
the table holds them now (the field's own scale offsets, scale errors in scene units) and as it held them up to
2788b35 (the offsets made log-scale offsets, errors in log-scales). The second arm is the same build fed a view of
the field whose scale offsets are made log-scale offsets first.

    bash scripts/demo.sh --methods garo-deform --deform-scale-offset linear --output-dir runs/demo_linear
    python benchmarks/table_scale_units.py --config runs/demo_linear/garo-deform/garo-deform/config.yml \
        --output benchmarks/results/table_scale_units_cpu.json
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def log_scale_view(field: Any, log_scales: torch.Tensor) -> Callable[[torch.Tensor, float], Tuple[torch.Tensor, ...]]:
    """The field with its `linear` scale offsets made log-scale offsets, one time per call over every Gaussian."""
    from garo_ns.deformation import as_log_offsets

    def view(xyz: torch.Tensor, t: float) -> Tuple[torch.Tensor, ...]:
        if xyz.shape[0] != log_scales.shape[0]:
            raise ValueError("the log-scale view takes every Gaussian in one call")
        d = as_log_offsets(torch.cat(field(xyz, t), dim=-1), log_scales, "linear")
        return d[:, :3], d[:, 3:7], d[:, 7:]

    return view


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, required=True, help="a trained run's config.yml (linear offsets)")
    parser.add_argument("--frames", type=int, default=60, help="training times, evenly spaced (the demo's 60)")
    parser.add_argument("--keys-per-frame", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()

    from garo_ns.render.time_table import TimeTable, spec_for
    from garo_ns.tools.eval import load_run

    _, pipeline, _, step = load_run(args.config)
    model = pipeline.model
    cfg = model.config
    if cfg.deform_scale_offset != "linear":
        raise SystemExit(f"{args.config} composes its scales with {cfg.deform_scale_offset!r}, not linear")
    field = model.deformation.eval()
    xyz, log_scales = model.means.detach(), model.scales.detach()
    times = torch.linspace(0.0, 1.0, args.frames)
    rows: List[Dict[str, Any]] = []
    with torch.no_grad():
        for keys in args.keys_per_frame:
            spec, reason = spec_for(
                times, keys, model.num_points, cfg.time_table_budget_mb, cfg.time_table_precision,
                cfg.time_table_tolerance, model.scene_extent,
            )  # fmt: skip
            if spec is None:
                rows.append({"keys_per_frame": keys, "refused": reason})
                continue
            row: Dict[str, Any] = {"keys_per_frame": keys, "intervals": spec.intervals, "precision": spec.precision}
            for arm, table_field, offset in (
                ("scene_units", field, "linear"),
                ("log_scales", log_scale_view(field, log_scales), "log"),
            ):
                start = time.perf_counter()
                table = TimeTable.build(spec, table_field, xyz, scale_offset=offset)
                row[arm] = {
                    "network": int(table.network.numel()),
                    "order": table.spec.order,
                    "build_s": round(time.perf_counter() - start, 2),
                }
            rows.append(row)
            print(json.dumps(row))
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    result = {
        "run": str(args.config),
        "step": int(step),
        "gaussians": int(model.num_points),
        "tolerance": cfg.time_table_tolerance,
        "scene_extent": float(model.scene_extent),
        "frames": args.frames,
        "rows": rows,
        "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__},
        "commit": commit,
        "note": "network: Gaussians the table leaves to the MLP. scene_units: the table as built now; log_scales: "
        "the same build on the field's offsets made log-scale offsets, as tables were built up to 2788b35.",
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
