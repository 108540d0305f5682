"""Our D-3DGS baseline against the official D-3DGS code, scene by scene.

    R=benchmarks/results
    python benchmarks/official_compare.py --ours $R/table1_*_H100.json $R/table3_jumpingjacks_H100.json \
        $R/fig5a_jumpingjacks_H100.json $R/fig5b_jumpingjacks_H100.json \
        --official $R/official_d3dgs_H100.json $R/official_d3dgs_jumpingjacks_H100.json \
        --output $R/baseline_vs_official_H100.json

(every 40k `deform-splatfacto` run of ours on the H100: one run's baseline strays by tenths of a dB.)

`--ours` are result files of `python -m garo_ns.bench.benchmark` (variant `deform-splatfacto`) or of
`python -m garo_ns.bench.train_profile --method deform-splatfacto --score`;
`--official` are what `benchmarks/official_score.py` wrote for the official code's runs. A pair is
reported only when both arms ran the same number of steps on the same split with the same
background on the same GPU model: anything else is refused with the reason, never averaged in. A scene
run more than once on a side (several files) is compared as the mean of its runs, with each run's PSNR
kept beside it: the same code's runs of one scene spread by about as much as the target's margin. Writes
the JSON and a Markdown table next to it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

FIELDS = ("psnr", "ssim", "lpips", "num_gaussians", "fps", "iterations", "split", "background")
KEYS = ("iterations", "split", "background", "gpu")
"""What the two arms of a pair, and the runs of one side, must share."""
BASELINE = "deform-splatfacto"
# The accuracy target: ours within this PSNR (dB) and LPIPS of the official code on each scene.
PSNR_TOLERANCE_DB = 0.2
LPIPS_TOLERANCE = 0.003


class PairMismatch(ValueError):
    """The two arms of a scene were not run under the same conditions."""


def scene_name(path_or_name: str) -> str:
    """`/tmp/jumpingjacks` and `jumpingjacks` name the same scene."""
    return Path(str(path_or_name).rstrip("/")).name


# train_profile scores the test split by default, and has since it first scored (66bc3d9); D-NeRF's recipe trains on
# black. Its files before 44c004f do not record either: their arms say so (`assumed`).
PROFILE_DEFAULTS = {"split": "test", "background": "black"}


def profile_arm(result: Dict[str, Any], variant: str = BASELINE) -> Dict[str, Any]:
    """Our side of a pair from a garo_ns.bench.train_profile result (`--score`)."""
    scene = scene_name(result.get("scene", "?"))
    if result.get("method") != variant:
        raise PairMismatch(f"{scene}: a profile of {result.get('method')!r}, not '{variant}'")
    score = result.get("score") or {}
    if score.get("psnr") is None:
        raise PairMismatch(f"{scene}: the profile was not scored (--score)")
    env = result.get("environment") or {}
    arm = {k: score.get(k) for k in ("psnr", "ssim", "lpips", "num_gaussians")}
    arm.update(fps=None, iterations=result.get("steps"), gpu=env.get("gpu"), git_commit=env.get("git_commit"))
    arm.update(shortened=False, model_settings=result.get("model_settings") or {})
    assumed = [k for k in PROFILE_DEFAULTS if k not in score]
    arm.update({k: score.get(k, PROFILE_DEFAULTS[k]) for k in PROFILE_DEFAULTS})
    if assumed:
        arm["assumed"] = assumed
    return arm


def our_arm(result: Dict[str, Any], variant: str = BASELINE) -> Dict[str, Any]:
    """Our side of a pair from a garo_ns.bench.benchmark result, or from a train_profile one (`profile_arm`)."""
    if "variants" not in result and "score" in result:
        return profile_arm(result, variant)
    row = (result.get("variants") or {}).get(variant)
    if row is None or "psnr" not in row:
        raise PairMismatch(f"{scene_name(result.get('scene', '?'))}: no scored '{variant}' arm in our result")
    arm = {k: row.get(k) for k in FIELDS if k in row}
    arm.update(split=result.get("split"), background=result.get("background"))
    arm.update(git_commit=result.get("git_commit"), gpu=result.get("gpu"), shortened=row.get("shortened"))
    return arm


def mean_arm(runs: List[Dict[str, Any]]) -> Dict[str, Any]:
    """One side of a pair from its runs (already checked to share steps, split, background and GPU): the
    mean of each quality metric and of the Gaussian count, FPS only where there is one run, and each run's
    PSNR, LPIPS and commit."""
    arm = dict(runs[0])
    for key in ("psnr", "ssim", "lpips", "num_gaussians"):
        values = [r.get(key) for r in runs]
        arm[key] = None if any(v is None for v in values) else sum(values) / len(values)
    if len(runs) > 1:
        arm["fps"] = None  # timings of different holds are not averaged
    arm["runs"] = [{k: r.get(k) for k in ("psnr", "lpips", "git_commit", "source")} for r in runs]
    assumed = sorted({k for r in runs for k in r.get("assumed", [])})  # any run's unrecorded split or background
    arm.pop("assumed", None)
    if assumed:
        arm["assumed"] = assumed
    return arm


def pair(scene: str, ours: Dict[str, Any], official: Dict[str, Any]) -> Dict[str, Any]:
    """One row; PairMismatch when the arms differ in steps, split, background or GPU model."""
    for key in KEYS:
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


def compare(
    ours_results: List[Dict[str, Any]], official: Union[Dict[str, Any], List[Dict[str, Any]]]
) -> Dict[str, Any]:
    """Rows for every scene present on both sides (each side the mean of its runs on the official runs' GPU
    model), and the refused pairs and runs with their reasons."""
    files = [official] if isinstance(official, dict) else list(official)
    theirs: Dict[str, List[Dict[str, Any]]] = {}
    for f in files:
        for r in f.get("rows", []):
            arm = dict(r["official"], gpu=r["official"].get("gpu", f.get("gpu")))
            arm.setdefault("git_commit", f.get("official_commit"))
            arm.setdefault("source", f.get("source"))
            theirs.setdefault(scene_name(r["scene"]), []).append(arm)
    mine: Dict[str, List[Dict[str, Any]]] = {}
    refused: List[str] = []
    for result in ours_results:
        scene = scene_name(result.get("scene", "?"))
        try:
            arm = our_arm(result)
        except PairMismatch as err:
            refused.append(str(err))
            continue
        arm["source"] = result.get("source")
        mine.setdefault(scene, []).append(arm)
    rows: List[Dict[str, Any]] = []
    for scene, runs in mine.items():
        groups: Dict[tuple, List[Dict[str, Any]]] = {}
        for arm in runs:  # runs compared together share steps, split, background and GPU model
            groups.setdefault(tuple(arm.get(k) for k in KEYS), []).append(arm)
        for key, group in groups.items():
            candidates = [t for t in theirs.get(scene, []) if tuple(t.get(k) for k in KEYS) == key]
            if candidates:
                rows.append(pair(scene, mean_arm(group), mean_arm(candidates)))
                continue
            if scene not in theirs:
                refused.append(f"{scene}: no official run")
                continue
            try:  # no official run shares these keys, so pairing with one says what differs
                pair(scene, group[0], theirs[scene][0])
            except PairMismatch as err:
                refused.append(str(err))
    refused += [f"{scene}: no run of ours" for scene in sorted(theirs) if scene not in mine]
    return {
        "gpu": sorted({str(f.get("gpu")) for f in files}),
        "official_commit": sorted({str(f.get("official_commit")) for f in files}),
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
            f"{f(t.get('ssim'), '.4f')} | {o['num_gaussians']:,.0f} / {t['num_gaussians']:,.0f} | "
            f"{f(o.get('fps'), '.1f')} / {f(t.get('fps'), '.1f')} | {'met' if r['target_met'] else 'missed'} |"
        )
    for r in summary["rows"]:
        o, t = r["ours"], r["official"]
        if len(o.get("runs", [])) > 1 or len(t.get("runs", [])) > 1:
            each = lambda arm: ", ".join(f"{run['psnr']:.2f}" for run in arm["runs"])  # noqa: E731
            lines.append(
                f"\n{r['scene']}: the mean of {len(o['runs'])} run(s) of ours ({each(o)} dB) against "
                f"{len(t['runs'])} of the official code ({each(t)} dB)."
            )
    for r in summary["rows"]:
        if r["ours"].get("assumed"):
            lines.append(
                f"\n{r['scene']}: our runs' {' and '.join(r['ours']['assumed'])} are train_profile's defaults, which "
                "its files from before 44c004f do not record."
            )
    for reason in summary["refused"]:
        lines.append(f"\nRefused: {reason}")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ours", type=Path, nargs="+", required=True)
    parser.add_argument("--official", type=Path, nargs="+", required=True)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()

    def load(path: Path) -> Dict[str, Any]:
        return {**json.loads(path.read_text()), "source": path.name}

    summary = compare([load(p) for p in args.ours], [load(p) for p in args.official])
    summary["sources"] = {"ours": [str(p) for p in args.ours], "official": [str(p) for p in args.official]}
    args.output.write_text(json.dumps(summary, indent=2) + "\n")
    args.output.with_suffix(".md").write_text(markdown(summary))
    print(markdown(summary))


if __name__ == "__main__":
    main()
