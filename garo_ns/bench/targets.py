"""Speed and quality targets checked on a cross-scene summary (garo_ns.bench.summary).

A target states what a variant must reach against the baseline of its own run, scene by scene and on average:
a speed-up, an absolute frame rate (on a stated GPU model: elsewhere it is reported, not judged), a PSNR and
LPIPS loss, a model file size in half-precision storage, and how far its worst test view strays from the same
model's plain render; a criterion a target leaves at None is not part of it. Each criterion's verdict is True,
False, or None where the files cannot judge it (another GPU model, a row not measured); a target is met only
when every criterion is True.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Dict, List, Optional


@dataclass(frozen=True)
class Target:
    """What a variant must reach against the baseline (plain fp32) of its own run."""

    name: str
    fps_ratio_mean: float
    """Speed-up, mean over scenes of the per-scene ratios."""
    fps_ratio_each: float
    """Speed-up on every scene."""
    fps_each: float
    """Frames per second on every scene, on `fps_gpu`."""
    fps_gpu: str
    """The GPU model the absolute frame rate is stated for (matched as a substring of the files' GPU name)."""
    psnr_drop_mean_db: float
    psnr_drop_each_db: Optional[float] = None
    lpips_increase_each: Optional[float] = None
    model_mb_each: Optional[float] = None
    """Model file in half-precision storage (the size of the `+fp16` row)."""
    worst_view_db: Optional[float] = None
    """The largest per-view PSNR change of the variant from the same model's plain render (`psnr_vs_plain`), on
    every scene: what an approximate render path may cost."""


# Issue #30's target for `garo-compact+auto` against `deform-splatfacto`, at the full schedule.
COMPACTION = Target(
    name="compaction",
    fps_ratio_mean=6.0,
    fps_ratio_each=4.0,
    fps_each=1000.0,
    fps_gpu="H200",
    psnr_drop_mean_db=0.3,
    psnr_drop_each_db=0.5,
    lpips_increase_each=0.005,
    model_mb_each=5.0,
)
# Issue #44's target for `garo-compact+auto` with the time table against `deform-splatfacto`, at the full schedule.
TIME_TABLE = Target(
    name="time-table",
    fps_ratio_mean=6.0,
    fps_ratio_each=4.0,
    fps_each=1000.0,
    fps_gpu="H200",
    psnr_drop_mean_db=0.3,
    worst_view_db=0.02,
)
# Issue #69's target for `garo-compact+auto` against `deform-splatfacto`: the frame past 1500 FPS.
FRAME = replace(TIME_TABLE, name="frame", fps_ratio_mean=8.0, fps_ratio_each=6.0, fps_each=1500.0)
TARGETS = {t.name: t for t in (COMPACTION, TIME_TABLE, FRAME)}


def _verdict(values: List[Optional[float]], limit: float, at_least: bool) -> Optional[bool]:
    """True when every value is within `limit`; False as soon as one judged value is not (a criterion over every
    scene is missed whatever the unjudged ones hold); None when some are missing and none missed."""
    judged = [v >= limit if at_least else v <= limit for v in values if v is not None]
    if not all(judged):
        return False
    return True if values and len(judged) == len(values) else None


def check_target(
    summary: Dict[str, Any], variant: str, target: Target, size_variant: Optional[str] = None
) -> Dict[str, Any]:
    """Each criterion of `target` for `variant` in `summary` (the output of `summary.summarise`), with the values
    it was judged on. `size_variant` is the row whose model size is the half-precision file (e.g.
    `garo-compact+fp16`); without it the size criterion is not judged."""
    if variant not in summary["variants"]:
        raise ValueError(f"target {target.name}: {variant!r} is not among the summary's variants {summary['variants']}")
    if size_variant is not None and size_variant not in summary["variants"]:
        raise ValueError(f"target {target.name}: size row {size_variant!r} is not among {summary['variants']}")
    rows, average, baseline = summary["rows"], summary["average"][variant], summary["baseline"]
    scenes = [r["scene"] for r in rows]

    def each(key: str) -> List[Optional[float]]:
        return [r[variant].get(key) for r in rows]

    lpips_up = [
        None
        if r[variant].get("lpips") is None or r[baseline].get("lpips") is None
        else r[variant]["lpips"] - r[baseline]["lpips"]
        for r in rows
    ]
    # The absolute frame rate is judged only on rows measured on the target's GPU model; the others are shown.
    on_gpu = [target.fps_gpu in str(r.get("gpu") or "") for r in rows]
    left_out = [s for s, ok in zip(scenes, on_gpu) if not ok]
    fps_note = None
    if left_out:
        where = "measured on " + ", ".join(
            sorted({str(r.get("gpu") or "a CPU") for r, ok in zip(rows, on_gpu) if not ok})
        )
        fps_note = where if len(left_out) == len(scenes) else f"{', '.join(left_out)} left out ({where})"
    sizes = [r[size_variant].get("model_size_mb") for r in rows] if size_variant else []
    # (label, values shown, values judged, limit, at least, note): no judged values leave a criterion unjudged.
    criteria = [
        ("speed-up, mean", [average.get("fps_ratio")], None, target.fps_ratio_mean, True, None),
        ("speed-up, each scene", each("fps_ratio"), None, target.fps_ratio_each, True, None),
        (
            f"FPS on {target.fps_gpu}, each scene",
            each("fps"),
            [v if ok else None for v, ok in zip(each("fps"), on_gpu)],
            target.fps_each,
            True,
            fps_note,
        ),
        ("PSNR loss, mean (dB)", [average.get("psnr_drop_db")], None, target.psnr_drop_mean_db, False, None),
        ("PSNR loss, each scene (dB)", each("psnr_drop_db"), None, target.psnr_drop_each_db, False, None),
        ("LPIPS increase, each scene", lpips_up, None, target.lpips_increase_each, False, None),
        (
            "model MB in half-precision storage, each scene",
            sizes,
            None,
            target.model_mb_each,
            False,
            None if size_variant else "no +fp16 row given",
        ),
        ("worst view vs plain render, each scene (dB)", each("worst_view_db"), None, target.worst_view_db, False, None),
    ]
    out = []
    for label, values, judged, limit, at_least, note in criteria:
        if limit is None:  # not part of this target
            continue
        met = _verdict(values if judged is None else judged, limit, at_least)
        if note is None and any(v is None for v in values):
            note = "a value is missing"
        out.append(
            {"criterion": label, "values": values, "limit": limit, "at_least": at_least, "met": met, "note": note}
        )
    verdicts = [c["met"] for c in out]
    return {
        "target": asdict(target),
        "variant": variant,
        "size_variant": size_variant,
        "scenes": scenes,
        "criteria": out,
        "met": all(v is True for v in verdicts),
        "judged": sum(v is not None for v in verdicts),
        "missed": [c["criterion"] for c in out if c["met"] is False],
    }


def _number(v: Optional[float]) -> str:
    if v is None:
        return "-"
    return f"{v:.1f}" if abs(v) >= 100 else f"{v:.3g}"


def target_lines(result: Dict[str, Any]) -> List[str]:
    """The check as Markdown: one row per criterion, then a sentence."""
    scenes = result["scenes"]
    lines = [
        f"Target `{result['target']['name']}` for {result['variant']}"
        + (f" (size from {result['size_variant']})" if result["size_variant"] else "")
        + ":",
        "",
        "| criterion | limit | " + ("value" if len(scenes) == 1 else "values (" + ", ".join(scenes) + ")") + " | met |",
        "|---|---|---|---|",
    ]
    for c in result["criteria"]:
        values = ", ".join(_number(v) for v in c["values"]) or "-"
        met = {True: "yes", False: "no", None: "not judged"}[c["met"]]
        limit = (">= " if c["at_least"] else "<= ") + f"{c['limit']:g}"
        lines.append(f"| {c['criterion']} | {limit} | {values} | {met}{': ' + c['note'] if c['note'] else ''} |")
    lines.append("")
    judged = f"{result['judged']} of {len(result['criteria'])} criteria judged from these files"
    if result["met"]:
        lines.append(f"Every criterion is met on {len(scenes)} scene(s).")
    elif result["missed"]:
        # Criterion names hold commas ("speed-up, mean"): semicolons keep the list readable.
        lines.append(f"Not met: {len(result['missed'])} missed ({'; '.join(result['missed'])}), {judged}.")
    else:
        lines.append(f"Not settled: no criterion missed, {judged}.")
    return lines
