"""Re-evaluate runs a benchmark already trained, under more render settings and more timing passes.

Used on the GPU machine right after a benchmark, while its checkpoints exist:
    python benchmarks/retime.py --work-dir /tmp/garo-work/lego_speed --scene /tmp/lego --split val \
        --trained garo-prune0.7 garo-prune0.5 garo-deform deform-splatfacto --rows "" +half +static \
        --repeats 5 --output lego_speed_retime.json
(`benchmarks/results/lego_speed_retime_H200.json` was produced by such calls with the rows `+tf32
+static+tf32` (a path since deleted, benchmarks/HISTORY.md), typed inline in the hold of
`lego_speed_H200.json` before this script was committed, so it lacks the environment fields.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal

import tyro

from garo_ns.bench.benchmark import BenchArgs, environment, evaluate_variant


@dataclass
class RetimeArgs:
    work_dir: Path
    """The benchmark's work directory (holds <variant>.record.json)."""
    scene: Path
    split: Literal["train", "val", "test"] = "val"
    trained: List[str] = field(default_factory=lambda: ["deform-splatfacto", "garo-deform"])
    rows: List[str] = field(default_factory=lambda: ["", "+half", "+static"])
    """Render-time suffixes evaluated for every trained variant, besides the plain row that is always measured."""
    repeats: int = 5
    output: Path = Path("retime.json")


def main(args: RetimeArgs) -> None:
    bench = BenchArgs(scene=args.scene, split=args.split, warmup_views=5, timing_repeats=args.repeats)
    out = {**environment("cuda"), "scene": args.scene.name, "split": args.split, "variants": {}}
    for name in args.trained:
        record = json.loads((args.work_dir / f"{name}.record.json").read_text())
        # The plain row always: every other row is compared with it view by view (psnr_vs_plain).
        rows = [name] + [name + row for row in args.rows if row]
        out["variants"].update(evaluate_variant(bench, record, rows))
        args.output.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(tyro.cli(RetimeArgs))
