"""Our D-3DGS baseline against the official D-3DGS code, scene by scene.

    python benchmarks/official_compare.py --ours benchmarks/results/standup40k_H200.json ... \
        --official benchmarks/results/official_d3dgs_standup40k_round2_H200.json \
        --output benchmarks/results/baseline_vs_official_H200.json

`--ours` are result files of `python -m garo_ns.bench.benchmark` (variant `deform-splatfacto`);
`--official` is what `benchmarks/official_score.py` wrote for the official code's runs. A pair is
reported only when both arms ran the same number of steps on the same split with the same
background: anything else is refused with the reason, never averaged in. Writes the JSON and a
Markdown table next to it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Dict, List, Optional

FIELDS = ("psnr", "ssim", "lpips", "num_gaussians", "fps", "iterations", "split", "background")
BASELINE = "deform-splatfacto"
# The accuracy target: ours within this PSNR (dB) and LPIPS of the official code on each scene.
PSNR_TOLERANCE_DB = 0.2
LPIPS_TOLERANCE = 0.003


class PairMismatch(ValueError):
    """The two arms of a scene were not run under the same conditions."""


def scene_name(path_or_name: str) -> str:
    """`/tmp/jumpingjacks` and `jumpingjacks` name the same scene."""
    return Path(str(path_or_name).rstrip("/")).name


def our_arm(result: Dict[str, Any], variant: str = BASELINE) -> Dict[str, Any]:
    """Our side of a pair from a garo_ns.bench.benchmark result."""
    row = (result.get("variants") or {}).get(variant)
    if row is None or "psnr" not in row:
        raise PairMismatch(f"{scene_name(result.get('scene', '?'))}: no scored '{variant}' arm in our result")
    arm = {k: row.get(k) for k in FIELDS if k in row}
    arm.update(split=result.get("split"), background=result.get("background"))
    arm.update(git_commit=result.get("git_commit"), gpu=result.get("gpu"), shortened=row.get("shortened"))
    return arm


def pair(scene: str, ours: Dict[str, Any], official: Dict[str, Any]) -> Dict[str, Any]:
    """One row; PairMismatch when the arms differ in steps, split or background."""
    for key in ("iterations", "split", "background"):
        if ours.get(key) is None or official.get(key) is None:
            raise PairMismatch(f"{scene}: '{key}' missing ({ours.get(key)!r} ours, {official.get(key)!r} official)")
        if ours[key] != official[key]:
            raise PairMismatch(f"{scene}: arms differ in {key} ({ours[key]!r} ours, {official[key]!r} official)")
    psnr_gap = ours["psnr"] - official["psnr"]
    lpips_gap = None
    if ours.get("lpips") is not None and official.get("lpips") is not None:
        lpips_gap = ours["lpips"] - official["lpips"]
    return {
        "scene": scene,
        "ours": ours,
        "official": official,
        "psnr_gap_db": psnr_gap,
        "lpips_gap": lpips_gap,
        "target_met": bool(psnr_gap >= -PSNR_TOLERANCE_DB and lpips_gap is not None and lpips_gap <= LPIPS_TOLERANCE),
    }


def compare(ours_results: List[Dict[str, Any]], official: Dict[str, Any]) -> Dict[str, Any]:
    """Rows for every scene present on both sides, and the refused pairs with their reasons."""
    theirs = {scene_name(r["scene"]): r["official"] for r in official.get("rows", [])}
    rows: List[Dict[str, Any]] = []
    refused: List[str] = []
    for result in ours_results:
        scene = scene_name(result.get("scene", "?"))
        if scene not in theirs:
            refused.append(f"{scene}: no official run")
            continue
        try:
            rows.append(pair(scene, our_arm(result), theirs[scene]))
        except PairMismatch as err:
            refused.append(str(err))
    ours_scenes = {scene_name(r.get("scene", "?")) for r in ours_results}
    refused += [f"{scene}: no run of ours" for scene in sorted(theirs) if scene not in ours_scenes]
    return {
        "gpu": official.get("gpu"),
        "official_commit": official.get("official_commit"),
        "target": f"ours >= official - {PSNR_TOLERANCE_DB} dB PSNR and LPIPS <= official + {LPIPS_TOLERANCE}",
        "rows": rows,
        "refused": refused,
    }


def markdown(summary: Dict[str, Any]) -> str:
    """The comparison as a Markdown table."""

    def f(v: Optional[float], fmt: str) -> str:
        return "n/a" if v is None else format(v, fmt)

    lines = [
        "| scene (split) | steps | PSNR ours / official | LPIPS ours / official | SSIM ours / official "
        "| Gaussians ours / official | FPS ours / official | target |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in summary["rows"]:
        o, t = r["ours"], r["official"]
        lines.append(
            f"| {r['scene']} ({o['split']}) | {o['iterations']:,} | {f(o['psnr'], '.2f')} / {f(t['psnr'], '.2f')} "
            f"| {f(o.get('lpips'), '.4f')} / {f(t.get('lpips'), '.4f')} | {f(o.get('ssim'), '.4f')} / "
            f"{f(t.get('ssim'), '.4f')} | {o['num_gaussians']:,} / {t['num_gaussians']:,} | "
            f"{f(o.get('fps'), '.1f')} / {f(t.get('fps'), '.1f')} | {'met' if r['target_met'] else 'missed'} |"
        )
    for reason in summary["refused"]:
        lines.append(f"\nRefused: {reason}")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ours", type=Path, nargs="+", required=True)
    parser.add_argument("--official", type=Path, required=True)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    summary = compare([json.loads(p.read_text()) for p in args.ours], json.loads(args.official.read_text()))
    summary["sources"] = {"ours": [str(p) for p in args.ours], "official": str(args.official)}
    args.output.write_text(json.dumps(summary, indent=2) + "\n")
    args.output.with_suffix(".md").write_text(markdown(summary))
    print(markdown(summary))


if __name__ == "__main__":
    main()
