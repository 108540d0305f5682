"""The time table on finished models: its tolerance against its error, its memory and its frame rate.

For each benchmark export (garo_ns.bench.transfer) and each tolerance, the model renders the split's views
through the network (plain, fp32) and through a table of that tolerance (`time_table_tolerance`: how far a
Gaussian's interpolated trajectory may stray at keyframe midpoints before it stays on the network), and
records the worst view's two-sided change (garo_ns.render.switches.view_change_db), how many Gaussians the
table leaves to the network, the table's size and build time, and the frame rate of both. The table's keys
sit halfway between the training times (garo_ns.render.time_table), so D-NeRF's test views, taken at training
times, are the worst place for it.

    python benchmarks/time_table.py --scene SCENE --exports EXPORT... --output RESULT.json
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import torch

from garo_ns import compat

compat.install()


def main() -> None:
    from garo_ns.bench import transfer
    from garo_ns.bench.benchmark import environment
    from garo_ns.bench.timing import measure_fps
    from garo_ns.data.dnerf import read_split
    from garo_ns.render.switches import view_change_db
    from garo_ns.render.time_table import spec_for
    from garo_ns.tools.eval import load_run, load_split

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--exports", type=Path, nargs="+", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--tolerances", type=float, nargs="+", default=[1e-2, 3e-3, 1e-3, 3e-4, 1e-4])
    parser.add_argument("--precisions", nargs="+", default=["int16"], choices=["int16", "fp16", "fp32"])
    parser.add_argument(
        "--orders", nargs="+", default=["linear"], choices=["linear", "cubic"], help="the order preferred on a tie"
    )
    parser.add_argument("--keys-per-frame", type=int, nargs="+", default=[2])
    parser.add_argument(
        "--budget-mb", type=float, default=None, help="the table's memory budget (default: the model's)"
    )
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/time_table"))
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    result = {**environment(device), "scene": args.scene.name, "split": args.split, "models": {}}
    for export in args.exports:
        record = transfer.import_run(export, args.work_dir, args.scene)
        _, pipeline, _, _ = load_run(Path(record["config"]))
        model = pipeline.model
        model.eval()
        cfg = model.config
        for key in ("static_skip", "cuda_graph", "lean_raster", "time_table"):
            setattr(cfg, key, False)
        cameras, images = load_split(args.scene, args.split, model.background_color)
        gt = torch.stack(images).to(model.device)
        times = torch.unique(torch.as_tensor(read_split(args.scene, "train")[2], dtype=torch.float32))

        @torch.no_grad()
        def renders() -> torch.Tensor:
            views = [cameras[i : i + 1].to(model.device) for i in range(len(images))]
            return torch.stack([model.get_outputs_for_camera(view)["rgb"] for view in views])

        plain = renders()
        rows = {"network": {"fps": measure_fps(model, cameras)["fps"]}}
        cfg.time_table = True
        cfg.time_table_budget_mb = args.budget_mb or cfg.time_table_budget_mb
        for tol, precision, keys, order in [
            (t, p, k, o)
            for t in args.tolerances
            for p in args.precisions
            for k in args.keys_per_frame
            for o in args.orders
        ]:
            name = f"tol={tol:g},{precision},keys={keys}" + (f",{order}" if len(args.orders) > 1 else "")
            spec, why = spec_for(
                times, keys, model.num_points, cfg.time_table_budget_mb, precision, tol, model.scene_extent
            )
            spec = replace(spec, order=order) if spec is not None else None
            model.switches.table_override = spec
            if spec is None:
                rows[name] = {"off": why}
                continue
            tabled = renders()
            change = view_change_db(plain, tabled, gt)
            rows[name] = {
                "tolerance": tol,
                "precision": precision,
                "keys_per_frame": keys,
                "order": model.frame.table_info.get("spec", {}).get("order"),
                "worst_view_change_db": float(change.max()),
                "mean_view_change_db": float(change.mean()),
                "view_change_db": [round(float(c), 5) for c in change],
                "fps": measure_fps(model, cameras)["fps"],
                "table": model.frame.table_info,
            }
            row = rows[name]
            print(
                record["variant"],
                name,
                f"{row['worst_view_change_db']:.4f} dB",
                f"{row['fps']:.0f} fps",
                row["table"].get("network"),
                f"{row['table'].get('mb', 0):.0f} MB",
                flush=True,
            )
        result["models"][record["variant"]] = {"gaussians": model.num_points, "rows": rows}
        torch.cuda.empty_cache() if device == "cuda" else None
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
