"""Training speed of a recipe against another, from `train_profile` result files (each a whole run alone on its
GPU): steps per second, minutes per 40k steps and test PSNR of every run, and per method the mean of each side
and their ratio. Writes `benchmarks/results/train_speed_<GPU>.json` and its markdown table.

    python -m garo_ns.bench.train_speed --before garo-deform=OLD.json --after garo-deform=NEW1.json \\
        garo-deform=NEW2.json --output benchmarks/results/train_speed_H200.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from statistics import mean
from typing import Any, Dict, List, Optional, Sequence, Tuple

STEPS_40K = 40_000


def run_row(path: Path) -> Dict[str, Any]:
    """One run's figures from its `train_profile` result file."""
    r = json.loads(Path(path).read_text())
    env = r.get("environment", {})
    score = r.get("score") or {}
    return {
        "file": Path(path).name,
        "scene": r.get("scene"),
        "gpu": env.get("gpu"),
        "git_commit": env.get("git_commit"),
        "steps": r["steps"],
        "train_seconds": r["train_seconds"],
        "steps_per_second": r["steps_per_second"],
        "minutes_per_40k": r["train_seconds"] / r["steps"] * STEPS_40K / 60.0,
        "psnr": score.get("psnr"),
        "lpips": score.get("lpips"),
        "gaussians_final": r.get("gaussians_final"),
    }


def _side(rows: List[Dict[str, Any]]) -> Dict[str, Any]:
    psnrs = [r["psnr"] for r in rows if r["psnr"] is not None]
    return {
        "runs": rows,
        "minutes_per_40k": mean(r["minutes_per_40k"] for r in rows),
        "steps_per_second": mean(r["steps_per_second"] for r in rows),
        "psnr": mean(psnrs) if psnrs else None,
    }


def summary(before: Dict[str, List[Path]], after: Dict[str, List[Path]]) -> Dict[str, Any]:
    """Per method: both sides' runs and means, the speed-up (mean minutes before / after) and the PSNR change."""
    out: Dict[str, Any] = {}
    for method in sorted(set(before) | set(after)):
        entry: Dict[str, Any] = {}
        for name, side in (("before", before), ("after", after)):
            if side.get(method):
                entry[name] = _side([run_row(p) for p in side[method]])
        if "before" in entry and "after" in entry:
            entry["speedup"] = entry["before"]["minutes_per_40k"] / entry["after"]["minutes_per_40k"]
            b, a = entry["before"]["psnr"], entry["after"]["psnr"]
            entry["psnr_change_db"] = a - b if a is not None and b is not None else None
        out[method] = entry
    gpus = sorted({r["gpu"] for e in out.values() for s in ("before", "after") if s in e for r in e[s]["runs"]})
    return {"gpus": gpus, "methods": out}


def markdown(result: Dict[str, Any]) -> str:
    """One row per method and side: runs, mean minutes per 40k, steps/s, test PSNR; then the ratio."""
    lines = ["| method | recipe | runs | minutes per 40k | steps/s | test PSNR |", "|---|---|---|---|---|---|"]
    for method, e in result["methods"].items():
        for side in ("before", "after"):
            if side in e:
                s = e[side]
                each = ", ".join(f"{r['minutes_per_40k']:.1f}" for r in s["runs"])
                psnr = f"{s['psnr']:.2f}" if s["psnr"] is not None else "-"
                lines.append(
                    f"| {method} | {side} | {len(s['runs'])} | {s['minutes_per_40k']:.1f} ({each}) | "
                    f"{s['steps_per_second']:.1f} | {psnr} |"
                )
        if "speedup" in e:
            change = f", PSNR {e['psnr_change_db']:+.2f} dB" if e.get("psnr_change_db") is not None else ""
            lines.append(f"| {method} | after / before | | {e['speedup']:.2f}x faster{change} | | |")
    return "\n".join(lines) + "\n"


def _pairs(values: Sequence[str]) -> Dict[str, List[Path]]:
    out: Dict[str, List[Path]] = {}
    for v in values:
        method, sep, path = v.partition("=")
        if not sep or not method or not path:
            raise SystemExit(f"expected METHOD=FILE, got {v!r}")
        out.setdefault(method, []).append(Path(path))
    return out


def main(argv: Optional[Sequence[str]] = None) -> Tuple[Dict[str, Any], str]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", nargs="+", default=[], metavar="METHOD=FILE")
    parser.add_argument("--after", nargs="+", default=[], metavar="METHOD=FILE")
    parser.add_argument("--note", default="", help="what the two recipes are, recorded with the result")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    result = {"note": args.note, **summary(_pairs(args.before), _pairs(args.after))}
    table = markdown(result)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    args.output.with_suffix(".md").write_text(table)
    print(table)
    return result, table


if __name__ == "__main__":
    main()
