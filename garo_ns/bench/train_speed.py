"""Training speed of a recipe against another, from `train_profile` result files (each a whole run alone on its
GPU): per run the minutes per 40k steps, the part of them the finished model's render choice took (it runs after
the last step: time tables built and training views rendered, garo_ns.render.switches; as `train_profile` measured
it, unknown in its files from before it did), steps per second and test
PSNR; per method the mean of each side and their ratio over the scenes both sides ran. Writes
`benchmarks/results/train_speed_<GPU>.json` and its markdown table.

The ratio over steps 1k to 3k comes with it: the deformation field's warm-up (the recipe's first 3000 steps train
the Gaussians alone), where two recipes that differ only in the field run the same steps. There it measures the
machines, not the recipes: two GPUs of one host differed by 2 to 8% on those steps, as much as an arm measured.

    python -m garo_ns.bench.train_speed --before garo-deform=OLD.json --after garo-deform=NEW1.json \\
        garo-deform=NEW2.json --output benchmarks/results/train_speed_H200.json

A FILE may also be a benchmark result (garo_ns.bench.benchmark) trained with `--arms-per-gpu 1`, each arm alone on
its GPU: METHOD names the arm, and its whole training is the run's time.
"""

from __future__ import annotations

import argparse
import datetime
import json
from pathlib import Path
from statistics import mean
from typing import Any, Dict, List, Optional, Sequence, Tuple

from garo_ns.bench.results import cell

STEPS_40K = 40_000
WARMUP_SPAN = (1000, 3000)  # inside the field's warm-up, past the start-up's first steps


def warmup_ms_per_step(r: Dict[str, Any]) -> Optional[float]:
    """Milliseconds per step over `WARMUP_SPAN` from the run's timeline (None where it lacks either step)."""
    at = {row["step"]: row["seconds"] for row in r.get("timeline") or []}
    first, last = WARMUP_SPAN
    if first not in at or last not in at:
        return None
    return (at[last] - at[first]) / (last - first) * 1000.0


def run_row(path: Path, method: Optional[str] = None) -> Dict[str, Any]:
    """One run's figures from its `train_profile` result file, or `method`'s arm of a benchmark result file
    (garo_ns.bench.benchmark) whose arms each trained alone on a GPU (`--arms-per-gpu 1`)."""
    r = json.loads(Path(path).read_text())
    if "variants" in r:
        r = benchmark_run(Path(path), r, method)
    env = r.get("environment", {})
    score = r.get("score") or {}
    choice = r.get("render_choice_seconds")  # measured by train_profile (None in files from before it was)
    steps_seconds = r["train_seconds"] - choice if choice is not None else None
    return {
        "file": Path(path).name,
        "scene": r.get("scene"),
        "gpu": env.get("gpu"),
        "git_commit": env.get("git_commit"),
        "model_settings": r.get("model_settings") or {},
        "steps": r["steps"],
        "train_seconds": r["train_seconds"],
        "steps_per_second": r["steps_per_second"],
        "minutes_per_40k": r["train_seconds"] / r["steps"] * STEPS_40K / 60.0,
        "render_choice_seconds": choice,
        "render_choice_source": None if choice is None else "measured",
        "minutes_per_40k_steps": None if steps_seconds is None else steps_seconds / r["steps"] * STEPS_40K / 60.0,
        "warmup_ms_per_step": warmup_ms_per_step(r),
        "psnr": score.get("psnr"),
        "lpips": score.get("lpips"),
        "gaussians_final": r.get("gaussians_final"),
    }


def benchmark_run(path: Path, r: Dict[str, Any], method: Optional[str]) -> Dict[str, Any]:
    """One arm of a benchmark result as a `train_profile` result holds a run: its whole training as the worker
    timed it (the render choice after the last step included, not apart: the benchmark does not time it alone;
    no timeline)."""
    if r.get("arms_per_gpu") != 1:
        raise SystemExit(
            f"{path.name}: its arms trained {r.get('arms_per_gpu', 'several')} to a GPU at once, so their times are "
            "not lone runs' (train with --arms-per-gpu 1)"
        )
    v = (r.get("variants") or {}).get(method or "")
    if v is None or v.get("trained_in", "this run") != "this run":
        raise SystemExit(f"{path.name}: no arm {method!r} trained in that run")
    return {
        "scene": r.get("scene"),
        "environment": {"gpu": r.get("gpu"), "git_commit": r.get("git_commit")},
        "model_settings": dict(s.split("=", 1) for s in r.get("model_settings") or []),
        "steps": v["iterations"],
        "train_seconds": v["train_seconds"],
        "steps_per_second": v["train_steps_per_second"],
        "score": {"psnr": v.get("psnr"), "lpips": v.get("lpips")},
        "gaussians_final": v.get("num_gaussians"),
    }


def _mean_or_none(values: Sequence[Optional[float]]) -> Optional[float]:
    """The mean, or None where any value is unknown (a partial mean would compare other runs)."""
    return mean(values) if values and all(v is not None for v in values) else None  # type: ignore[arg-type]


def _side(rows: List[Dict[str, Any]]) -> Dict[str, Any]:
    """One side's runs and means. Each mean weighs every scene once (the mean of its runs): a scene run twice
    would otherwise count twice. `slowest_minutes_per_40k` is its slowest run, which a per-scene target reads."""
    scenes = sorted({r["scene"] for r in rows})
    scored = [s for s in scenes if any(r["psnr"] is not None for r in rows if r["scene"] == s)]
    psnr = [mean(r["psnr"] for r in rows if r["scene"] == s and r["psnr"] is not None) for s in scored]
    return {
        "runs": rows,
        "minutes_per_40k": _by_scene(rows, "minutes_per_40k", scenes),
        "minutes_per_40k_steps": _by_scene(rows, "minutes_per_40k_steps", scenes),
        "steps_per_second": _by_scene(rows, "steps_per_second", scenes),
        "slowest_minutes_per_40k": max(r["minutes_per_40k"] for r in rows),
        "psnr": mean(psnr) if psnr else None,
    }


def _by_scene(rows: List[Dict[str, Any]], key: str, scenes: Sequence[str]) -> Optional[float]:
    """The mean over `scenes` of each scene's mean `key` over its runs (None where one is unknown)."""
    per_scene = [_mean_or_none([r[key] for r in rows if r["scene"] == s]) for s in scenes]
    return _mean_or_none(per_scene)


def summary(before: Dict[str, List[Path]], after: Dict[str, List[Path]]) -> Dict[str, Any]:
    """Per method: both sides' runs and means; over the scenes both sides ran (each scene its runs' mean), the
    speed-up of the whole run, that of the steps alone (without the render choice, where both sides know it) and
    the PSNR change; and the speed-up over the field's warm-up (`WARMUP_SPAN`)."""
    out: Dict[str, Any] = {}
    for method in sorted(set(before) | set(after)):
        entry: Dict[str, Any] = {}
        for name, side in (("before", before), ("after", after)):
            if side.get(method):
                entry[name] = _side([run_row(p, method) for p in side[method]])
        if "before" in entry and "after" in entry:
            b, a = entry["before"]["runs"], entry["after"]["runs"]
            scenes = sorted({r["scene"] for r in b} & {r["scene"] for r in a})
            entry["scenes_compared"] = scenes
            if scenes:
                entry["speedup"] = _by_scene(b, "minutes_per_40k", scenes) / _by_scene(a, "minutes_per_40k", scenes)
                steps_b, steps_a = (_by_scene(x, "minutes_per_40k_steps", scenes) for x in (b, a))
                entry["speedup_steps"] = steps_b / steps_a if steps_b and steps_a else None
                warm_b, warm_a = (_by_scene(x, "warmup_ms_per_step", scenes) for x in (b, a))
                entry["speedup_warmup"] = warm_b / warm_a if warm_b and warm_a else None
                pb, pa = (_by_scene(x, "psnr", scenes) for x in (b, a))
                entry["psnr_change_db"] = pa - pb if pa is not None and pb is not None else None
        out[method] = entry
    gpus = sorted({r["gpu"] for e in out.values() for s in ("before", "after") if s in e for r in e[s]["runs"]})
    return {"gpus": gpus, "methods": out}


def markdown(result: Dict[str, Any]) -> str:
    """One row per run (method, side, scene, commit, settings): minutes per 40k, of which the render choice,
    steps/s, test PSNR; then each method's ratio over the scenes both sides ran."""
    lines = [
        "| method | recipe | scene | commit | settings | minutes per 40k | render choice (s) | steps/s | test PSNR |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for method, e in result["methods"].items():
        for side in ("before", "after"):
            for r in e.get(side, {}).get("runs", []):
                settings = ", ".join(f"{k}={v}" for k, v in sorted(r.get("model_settings", {}).items())) or "-"
                choice = cell(r.get("render_choice_seconds"), ".0f")
                lines.append(
                    f"| {method} | {side} | {r['scene']} | {(r['git_commit'] or '')[:7]} | {settings} | "
                    f"{r['minutes_per_40k']:.2f} | {choice} | {r['steps_per_second']:.1f} | {cell(r['psnr'], '.2f')} |"
                )
        if "speedup" in e:
            change = f", PSNR {e['psnr_change_db']:+.2f} dB" if e.get("psnr_change_db") is not None else ""
            if e.get("speedup_warmup"):
                change += f"; {e['speedup_warmup']:.2f}x over steps 1k to 3k (the field's warm-up)"
            steps = f" ({e['speedup_steps']:.2f}x the steps alone)" if e.get("speedup_steps") else ""
            scenes = ", ".join(e["scenes_compared"])
            lines.append(
                f"| {method} | after / before | {scenes} | | | {e['speedup']:.2f}x faster{steps}{change} | | | |"
            )
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
    parser.add_argument("--date", help="when the result was written (default: now, UTC, as 2026-01-31T12:00Z)")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    # The README shows the newest file of a kind, by this date.
    date = args.date or datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%MZ")
    result = {"note": args.note, "date": date, **summary(_pairs(args.before), _pairs(args.after))}
    table = markdown(result)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    args.output.with_suffix(".md").write_text(table)
    print(table)
    return result, table


if __name__ == "__main__":
    main()
