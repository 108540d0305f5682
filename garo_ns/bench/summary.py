"""`python -m garo_ns.bench.summary`: one table across scenes from per-scene benchmark results.

Reads the JSON files `garo_ns.bench.benchmark` wrote (one per scene), and writes a summary JSON, a
Markdown table (per scene and the average, as the paper's Table 1) and a PNG plot next to it.
Each compared variant is set against the baseline trained and timed in the same file, so ratios
never mix GPUs or runs. A scene run more than once (several files of one scene, same GPU model) counts
once: each value of its row is the mean over its runs, with the runs kept beside it (one run of a
40k schedule is noise-level evidence at the paper's margins).
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import tyro

from garo_ns.bench.results import cell, publish, read_results, save_figure
from garo_ns.bench.targets import TARGETS, check_target, target_lines
from garo_ns.bench.transfer import trained_elsewhere

BASELINE = "deform-splatfacto"
METRICS = ("psnr", "ssim", "lpips", "fps", "num_gaussians", "model_size_mb")
# The paper's claim for GARO against D-3DGS: this speed-up at no more than this PSNR loss.
CLAIM_FPS_RATIO = 2.0
CLAIM_PSNR_DROP_DB = 0.5


@dataclass
class SummaryArgs:
    """Summarise per-scene benchmark results."""

    results: tyro.conf.Positional[List[Path]]
    """Per-scene result JSONs of garo_ns.bench.benchmark."""
    output: Path = Path("benchmarks/results/summary.json")
    """Summary JSON; the .md table and .png plot go next to it."""
    variants: List[str] = field(default_factory=lambda: ["garo-deform"])
    """Variants set against the baseline (each must be in every file)."""
    target: Optional[Literal["compaction", "time-table", "frame"]] = None
    """Also judge a speed and quality target (garo_ns.bench.targets) for `--target-variant`."""
    target_variant: Optional[str] = None
    """The variant the target is judged for (one of --variants), e.g. garo-compact+auto."""
    size_variant: Optional[str] = None
    """The row whose model size is the half-precision file (one of --variants), e.g. garo-compact+auto+fp16."""
    official: List[Path] = field(default_factory=list)
    """Results of the official D-3DGS code (benchmarks/official_score.py, e.g. official_real_<GPU>.json): each
    scene's official arm goes under `official` in that scene's row, beside the baseline."""
    note: str = ""
    """How the runs were made (machine, sharing, what was cut short), recorded before the summary's own note."""
    table_cost: Optional[Path] = None
    """Also write here, as JSON, what each tabled row's time table costs (issue 70, `table_cost`)."""


def _mean(values: List[Optional[float]]) -> Optional[float]:
    kept = [v for v in values if v is not None]
    return sum(kept) / len(kept) if kept and len(kept) == len(values) else None


def scene_rows(result: Dict[str, Any], variants: List[str], source: str) -> Dict[str, Any]:
    """Baseline and compared variants of one scene, with speed-up and PSNR drop per variant."""
    found = result.get("variants", {})
    missing = [v for v in [BASELINE, *variants] if v not in found]
    if missing:
        raise ValueError(f"{source}: no result for {missing} (has {sorted(found)})")
    base = found[BASELINE]
    row: Dict[str, Any] = {
        "scene": result["scene"],
        "split": result["split"],
        "gpu": result.get("gpu"),
        "git_commit": result.get("git_commit"),
        "source": source,
        BASELINE: {k: base.get(k) for k in (*METRICS, "iterations", "shortened", "trained_in")},
    }
    for name in variants:
        v = found[name]
        row[name] = {
            **{k: v.get(k) for k in (*METRICS, "iterations", "shortened", "trained_in")},
            "fps_ratio": v["fps"] / base["fps"],
            "psnr_drop_db": base["psnr"] - v["psnr"],
            "gaussian_ratio": v["num_gaussians"] / max(base["num_gaussians"], 1),
        }
        if "psnr_vs_plain" in v:  # an approximate render path's largest per-view change from the plain render
            row[name]["worst_view_db"] = v["psnr_vs_plain"]["max_abs_db"]
        if "fps_paired" in v and "fps_paired" in base:  # the benchmark's alternating re-timing
            row[name]["fps_ratio_paired"] = v["fps_paired"]["fps"] / base["fps_paired"]["fps"]
    return row


def combine_runs(runs: List[Dict[str, Any]], variants: List[str]) -> Dict[str, Any]:
    """One scene's row from its runs (`scene_rows` of each file): every metric and ratio is the mean over
    the runs, each ratio having been taken within its own run; `runs` keeps the runs' rows and
    `<ratio>_range` their spread. A single run is returned as it is."""
    if len(runs) == 1:
        return runs[0]
    first = runs[0]
    for key in ("split", "gpu"):
        values = sorted({str(r[key]) for r in runs})
        if len(values) > 1:
            raise ValueError(
                f"runs of scene {first['scene']} differ in {key} ({', '.join(values)}): not repeats of one scene"
            )
    row: Dict[str, Any] = {
        "scene": first["scene"],
        "split": first["split"],
        "gpu": first["gpu"],
        "git_commit": [r["git_commit"] for r in runs],
        "source": " + ".join(r["source"] for r in runs),
        "runs": runs,
    }
    for name in [BASELINE, *variants]:
        arms = [r[name] for r in runs]
        ratios = () if name == BASELINE else ("fps_ratio", "psnr_drop_db", "gaussian_ratio")
        row[name] = {k: _mean([a[k] for a in arms]) for k in (*METRICS, *ratios)}
        if name != BASELINE and all("worst_view_db" in a for a in arms):  # the worst of the runs, not their mean
            row[name]["worst_view_db"] = max(a["worst_view_db"] for a in arms)
        iterations = {a.get("iterations") for a in arms}
        row[name]["iterations"] = iterations.pop() if len(iterations) == 1 else None
        row[name]["shortened"] = any(a.get("shortened") for a in arms)
        for k in ratios:
            row[name][f"{k}_range"] = [min(a[k] for a in arms), max(a[k] for a in arms)]
    return row


def summarise(results: List[Tuple[str, Dict[str, Any]]], variants: List[str]) -> Dict[str, Any]:
    """Per-scene rows and their average (the average of per-scene ratios, as papers report it)."""
    if not results:
        raise ValueError("no result files given")
    sources = [src for src, _ in results]
    if len(set(sources)) != len(sources):
        raise ValueError(f"a result file is given twice: {sources}")
    by_scene: Dict[str, List[Dict[str, Any]]] = {}
    for src, r in results:
        row = scene_rows(r, variants, src)
        by_scene.setdefault(row["scene"], []).append(row)
    rows = [combine_runs(runs, variants) for runs in by_scene.values()]
    scenes = [r["scene"] for r in rows]
    average: Dict[str, Any] = {BASELINE: {k: _mean([r[BASELINE][k] for r in rows]) for k in METRICS}}
    for name in variants:
        keys = (*METRICS, "fps_ratio", "psnr_drop_db", "gaussian_ratio")
        average[name] = {k: _mean([r[name][k] for r in rows]) for k in keys}
    shortened = sorted({r["scene"] for r in rows for n in [BASELINE, *variants] if r[n].get("shortened")})

    def meets(v: Dict[str, Any]) -> bool:
        return v["fps_ratio"] >= CLAIM_FPS_RATIO and v["psnr_drop_db"] <= CLAIM_PSNR_DROP_DB

    claim: Dict[str, Any] = {"fps_ratio_min": CLAIM_FPS_RATIO, "psnr_drop_max_db": CLAIM_PSNR_DROP_DB}
    for name in variants:
        claim[name] = {
            "scenes_meeting": [r["scene"] for r in rows if meets(r[name])],
            "average_meets": meets(average[name]),
        }
    return {
        "baseline": BASELINE,
        "scenes": scenes,
        "gpus": sorted({str(r["gpu"]) if r["gpu"] else "a CPU" for r in rows}),  # a CPU run records no GPU
        "variants": variants,
        "rows": rows,
        "average": average,
        "shortened_scenes": shortened,
        "paper_claim": claim,
        "note": "each ratio is taken within one scene's file (same run, same GPU); the average is the "
        "mean over scenes of per-scene values",
    }


def attach_official(summary: Dict[str, Any], official: List[Tuple[str, Dict[str, Any]]]) -> None:
    """Put each official run's arm (official_score.py's row) under `official` in the row of its scene, with the
    baseline's PSNR minus the official one (`psnr_gap_db`) and the GPU it was scored on."""
    rows = {r["scene"]: r for r in summary["rows"]}
    for source, result in official:
        for orow in result.get("rows", []):
            row, arm = rows.get(orow.get("scene")), orow.get("official")
            if row is None or arm is None:
                continue
            if "official" in row:
                raise ValueError(f"{row['scene']}: an official run in {row['official']['source']} and in {source}")
            if arm.get("split") != row["split"]:
                raise ValueError(f"{source}: {row['scene']} scored on {arm.get('split')}, ours on {row['split']}")
            row["official"] = {
                **{k: arm.get(k) for k in (*METRICS, "iterations", "train_args")},
                "shortened": orow.get("shortened"),
                "gpu": result.get("gpu"),
                "source": source,
                "psnr_gap_db": row[BASELINE]["psnr"] - arm["psnr"],
            }


def claim_sentence(summary: Dict[str, Any], variants: List[str]) -> str:
    """One sentence: the paper's claim (its speed-up at its PSNR loss, on average over the scenes) for each of
    `variants`, from the `paper_claim` that `summarise` judged (the summary's table and the README say it so)."""
    claim = summary["paper_claim"]
    parts = []
    for name in dict.fromkeys(variants):
        avg = summary["average"][name]
        parts.append(
            f"`{name}` {'meets' if claim[name]['average_meets'] else 'misses'} it ({avg['fps_ratio']:.2f}x at "
            f"{avg['psnr_drop_db']:+.2f} dB; {len(claim[name]['scenes_meeting'])} of {len(summary['rows'])} scenes)"
        )
    return (
        f"The paper's claim ({claim['fps_ratio_min']:.1f}x at <= {claim['psnr_drop_max_db']} dB, on average): "
        + ", ".join(parts)
        + "."
    )


def write_report(summary: Dict[str, Any], output: Path) -> Tuple[Path, Path]:
    """Markdown table and a plot (per scene, an arrow from the baseline to each variant)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [f"# Baseline ({BASELINE}) against {', '.join(summary['variants'])} on {', '.join(summary['gpus'])}", ""]
    head = "| scene | split | variant | steps | PSNR | SSIM | LPIPS | FPS | speed-up | PSNR drop | Gaussians | MB |"
    lines += [head, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    entries = []
    for r in summary["rows"]:
        for i, run in enumerate(r.get("runs", []), 1):
            entries.append((f"{r['scene']} run {i}", r["split"], run))
        label = f"{r['scene']} (mean of {len(r['runs'])} runs)" if "runs" in r else r["scene"]
        entries.append((label, r["split"], r))
    entries.append(("average", "", summary["average"]))
    for scene, split, row in entries:
        for name in [BASELINE, *summary["variants"]]:
            v = row[name]
            lines.append(
                f"| {scene} | {split} | {name} | {v.get('iterations', '') or ''} | {cell(v['psnr'], '.2f')} | "
                f"{cell(v['ssim'], '.4f')} | {cell(v['lpips'], '.4f')} | {cell(v['fps'], '.1f')} | "
                f"{cell(v.get('fps_ratio'), '.2f') + 'x' if v.get('fps_ratio') else '-'} | "
                f"{cell(v.get('psnr_drop_db'), '+.2f')} | {cell(v['num_gaussians'], '.0f')} | "
                f"{cell(v['model_size_mb'], '.1f')} |"
            )
    lines += ["", claim_sentence(summary, summary["variants"])]
    if summary["shortened_scenes"]:
        lines += ["", f"Shortened schedules in: {', '.join(summary['shortened_scenes'])}."]
    for r in summary["rows"]:
        if "official" in r:
            o = r["official"]
            lines += [
                "",
                f"{r['scene']}: the official D-3DGS code ({o['iterations']} it, {o['gpu']}, {o['source']}): PSNR "
                f"{cell(o['psnr'], '.2f')}, SSIM {cell(o['ssim'], '.4f')}, LPIPS {cell(o['lpips'], '.4f')}; "
                f"{BASELINE} minus official: {o['psnr_gap_db']:+.2f} dB.",
            ]
    if "target_check" in summary:
        lines += ["", *target_lines(summary["target_check"])]
    for r in summary["rows"]:
        for name in summary["variants"] if "runs" in r else []:
            lo, hi = r[name]["fps_ratio_range"]
            drop_lo, drop_hi = r[name]["psnr_drop_db_range"]
            lines += [
                "",
                f"{r['scene']}: {len(r['runs'])} runs ({', '.join(run['source'] for run in r['runs'])}); {name} "
                f"{lo:.2f}x to {hi:.2f}x at {drop_lo:+.2f} to {drop_hi:+.2f} dB; their mean counts once in the "
                "average.",
            ]
    for row in [run for r in summary["rows"] for run in r.get("runs", [r])]:
        for variant in summary["variants"]:
            if "fps_ratio_paired" in row[variant]:
                lines += [
                    "",
                    f"{row['scene']}: {variant} timed again in alternating passes beside the baseline: "
                    f"{row[variant]['fps_ratio_paired']:.2f}x (`fps_paired` in {row['source']}).",
                ]
        for variant in [BASELINE, *summary["variants"]]:
            where = trained_elsewhere(row[variant].get("trained_in"))
            if where is not None:
                lines += [
                    "",
                    f"{row['scene']}: {variant} trained in an earlier machine hold ({where}) and was evaluated "
                    f"and timed in {row['source']} with the other arm.",
                ]
    md = output.with_suffix(".md")
    md.write_text("\n".join(lines) + "\n")

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    # Colour names the scene, the marker the variant: several variants of one scene stay apart.
    markers = dict(zip(summary["variants"], itertools.cycle("*^sDvP<>")))
    for i, row in enumerate(summary["rows"]):
        color = f"C{i}"
        base = row[BASELINE]
        ax.scatter(base["fps"], base["psnr"], color=color, marker="o", s=50, label=f"{row['scene']} ({BASELINE})")
        for name in summary["variants"]:
            v = row[name]
            ax.annotate("", (v["fps"], v["psnr"]), (base["fps"], base["psnr"]), arrowprops={"arrowstyle": "->"})
            ax.scatter(v["fps"], v["psnr"], color=color, marker=markers[name], s=120 if markers[name] == "*" else 60)
    for name, marker in markers.items():
        ax.scatter([], [], color="gray", marker=marker, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("FPS (deformation + rasterization), log scale")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(f"{BASELINE} (o) against {len(markers)} variant(s), per scene")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return md, save_figure(fig, output)


def table_cost(loaded: List[Tuple[str, Dict[str, Any]]]) -> List[Dict[str, Any]]:
    """Per scene and variant that rendered with a time table: its MB, load to first frame (where the run recorded
    it: `load_seconds` plus `first_frame_seconds`), the profile's lookup stage and the frame, in milliseconds."""
    rows = []
    for source, r in loaded:
        for name, v in r["variants"].items():
            if not v.get("time_table"):
                continue
            load = v.get("load_seconds")
            table, lookup = v["time_table"], (v.get("profile") or {}).get("ms_deformation")
            rows.append({"scene": r["scene"], "variant": name, "source": source, "git_commit": r.get("git_commit"),
                         "table_mb": table.get("mb"), "build_s": table.get("build_s"),
                         "load_s": None if load is None else load + v["first_frame_seconds"],
                         "lookup_ms": lookup, "frame_ms": 1000.0 / v["fps"]})  # fmt: skip
    return rows


def main(args: SummaryArgs) -> Dict[str, Any]:
    """Read, summarise, write JSON, table and plot; print the table."""
    loaded = read_results(args.results)
    try:
        summary = summarise(loaded, list(args.variants))
        if args.target is not None:
            if args.target_variant is None:
                raise ValueError("--target needs --target-variant (the variant it is judged for)")
            summary["target_check"] = check_target(
                summary, args.target_variant, TARGETS[args.target], args.size_variant
            )
        attach_official(summary, read_results(args.official) if args.official else [])
        if args.note:
            summary["note"] = f"{args.note} {summary['note']}"
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    publish(summary, args.output, write_report)
    if args.table_cost is not None:
        args.table_cost.write_text(json.dumps({"gpus": summary["gpus"], "rows": table_cost(loaded)}, indent=1))
    return summary


if __name__ == "__main__":
    main(tyro.cli(SummaryArgs))
