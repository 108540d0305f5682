"""`python -m garo_ns.bench.ab`: a recipe change's A/B over scenes, pooled over rounds of runs.

Each side (`--base`, `--arm`) is a list of scored 40k runs: `train_profile` result files, or one row of a
`benchmark` result file (`FILE:VARIANT`). Per scene it keeps every run's test PSNR, LPIPS and final Gaussian
count, each side's mean over its runs, the change of the means, and each side's spread (largest minus smallest
run) where a side has two runs or more. Over the scenes both sides ran, each scene weighs once: the mean PSNR and
LPIPS change, and the two rules issue 45 judges a change by: kept for speed where the mean PSNR change is within
`--within` dB (0.15), adopted for accuracy only where it gains on average (by 0.01 dB at least).

    python -m garo_ns.bench.ab --base R/table40k_mutant_H200.json:deform-splatfacto ... \\
        --arm R/train_profile_linear_deform-splatfacto_mutant_H200.json ... \\
        --note "..." --output benchmarks/results/ab_scale_term.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from statistics import mean
from typing import Any, Dict, List, Optional, Sequence, Tuple

from garo_ns.bench.results import utc_stamp, write_with_table
from garo_ns.bench.train_speed import run_row

WITHIN_DB = 0.15
GAIN_DB = 0.01  # the least change the table shows: a mean of +0.004 dB is no gain


def run_of(spec: str) -> Dict[str, Any]:
    """One run's scores from `FILE` (a train_profile result, read by train_speed.run_row) or `FILE:VARIANT` (a
    benchmark result's row)."""
    path, _, variant = spec.partition(":")
    try:
        if variant:
            data = json.loads(Path(path).read_text())
        else:
            run = run_row(Path(path))
    except (OSError, json.JSONDecodeError) as err:
        raise SystemExit(f"error: cannot read result {path}: {err}") from None
    except KeyError as err:
        raise SystemExit(f"error: {path} is not a train_profile result (it lacks {err})") from None
    if variant:
        rows = data.get("variants") or {}
        if variant not in rows:
            raise SystemExit(f"error: {path} has no variant {variant!r} (it has {', '.join(sorted(rows))})")
        row = rows[variant]
        run = {"scene": data.get("scene"), "gpu": data.get("gpu"), "git_commit": data.get("git_commit")}
        run.update(psnr=row.get("psnr"), lpips=row.get("lpips"), gaussians_final=row.get("num_gaussians"))
    if run["psnr"] is None or not run["scene"]:
        raise SystemExit(f"error: {spec} holds no scored run of a named scene")
    return {
        "file": Path(path).name,
        "variant": variant or None,
        "scene": run["scene"],
        "gpu": run["gpu"],
        "git_commit": run["git_commit"],
        "psnr": run["psnr"],
        "lpips": run["lpips"],
        "gaussians": run["gaussians_final"],
    }


def _spread(values: Sequence[float]) -> Optional[float]:
    return max(values) - min(values) if len(values) > 1 else None


def _side(runs: List[Dict[str, Any]]) -> Dict[str, Any]:
    lpips = [r["lpips"] for r in runs if r["lpips"] is not None]
    gaussians = [r["gaussians"] for r in runs if r["gaussians"] is not None]
    psnr = [r["psnr"] for r in runs]
    return {
        "runs": runs,
        "psnr": mean(psnr),
        "psnr_spread": _spread(psnr),
        "lpips": mean(lpips) if lpips else None,
        "gaussians": mean(gaussians) if gaussians else None,
    }


def compare(base: List[Dict[str, Any]], arm: List[Dict[str, Any]], within: float = WITHIN_DB) -> Dict[str, Any]:
    """Per scene both sides ran: each side's runs and means and the change; over those scenes (each weighing
    once) the mean changes and the two verdicts."""
    scenes = sorted({r["scene"] for r in base} & {r["scene"] for r in arm})
    if not scenes:
        raise SystemExit("error: no scene has runs on both sides")
    per_scene: Dict[str, Any] = {}
    for scene in scenes:
        b = _side([r for r in base if r["scene"] == scene])
        a = _side([r for r in arm if r["scene"] == scene])
        entry = {"base": b, "arm": a, "psnr_change_db": a["psnr"] - b["psnr"]}
        if a["lpips"] is not None and b["lpips"] is not None:
            entry["lpips_change"] = a["lpips"] - b["lpips"]
        if a["gaussians"] and b["gaussians"]:
            entry["gaussian_ratio"] = a["gaussians"] / b["gaussians"]
        per_scene[scene] = entry
    change = mean(e["psnr_change_db"] for e in per_scene.values())
    lpips = [e["lpips_change"] for e in per_scene.values() if "lpips_change" in e]
    spreads = [s for e in per_scene.values() for s in (e["base"]["psnr_spread"], e["arm"]["psnr_spread"]) if s]
    return {
        "scenes": per_scene,
        "psnr_change_db": change,
        "lpips_change": mean(lpips) if len(lpips) == len(scenes) else None,
        "largest_spread_db": max(spreads) if spreads else None,
        "within_db": within,
        "within": abs(change) <= within,
        "gains": change >= GAIN_DB,
        "skipped_scenes": sorted(({r["scene"] for r in base} | {r["scene"] for r in arm}) - set(scenes)),
    }


def markdown(result: Dict[str, Any]) -> str:
    """The A/B as a table: per scene each side's runs and mean, the change; then the mean and the verdicts."""
    lines = [
        f"{result['note']}\n" if result.get("note") else "",
        "| scene | base PSNR (runs) | arm PSNR (runs) | change dB | LPIPS base / arm | Gaussians arm / base |",
        "|---|---|---|---|---|---|",
    ]
    for scene, e in result["scenes"].items():
        cells = []
        for side in ("base", "arm"):
            s = e[side]
            runs = ", ".join(f"{r['psnr']:.2f}" for r in s["runs"])
            cells.append(f"{s['psnr']:.2f} ({runs})" if len(s["runs"]) > 1 else f"{s['psnr']:.2f}")
        lp = "-"
        if e["base"]["lpips"] is not None and e["arm"]["lpips"] is not None:
            lp = f"{e['base']['lpips']:.4f} / {e['arm']['lpips']:.4f}"
        ratio = f"{e['gaussian_ratio']:.3f}" if "gaussian_ratio" in e else "-"
        lines.append(f"| {scene} | {cells[0]} | {cells[1]} | {e['psnr_change_db']:+.2f} | {lp} | {ratio} |")
    spread = result["largest_spread_db"]
    spread_text = f"; the largest spread of one side's runs of a scene {spread:.2f} dB" if spread else ""
    lines.append(
        f"\nMean PSNR change over {len(result['scenes'])} scene(s), each weighing once: "
        f"{result['psnr_change_db']:+.2f} dB ({'within' if result['within'] else 'outside'} "
        f"{result['within_db']:.2f} dB; {'gains' if result['gains'] else 'no gain'} on average){spread_text}."
    )
    return "\n".join(line for line in lines if line != "") + "\n"


def main(argv: Optional[Sequence[str]] = None) -> Tuple[Dict[str, Any], str]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", nargs="+", required=True, metavar="FILE[:VARIANT]")
    parser.add_argument("--arm", nargs="+", required=True, metavar="FILE[:VARIANT]")
    parser.add_argument("--within", type=float, default=WITHIN_DB, help="dB a change may cost and be kept")
    parser.add_argument("--note", default="", help="what the two sides are, recorded with the result")
    parser.add_argument("--date", default=None, help="when the result was written (default: now, UTC)")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    date = args.date or utc_stamp()
    result = {
        "note": args.note,
        "date": date,
        "base": list(args.base),
        "arm": list(args.arm),
        **compare([run_of(s) for s in args.base], [run_of(s) for s in args.arm], args.within),
    }
    return result, write_with_table(result, markdown, args.output)


if __name__ == "__main__":
    main()
