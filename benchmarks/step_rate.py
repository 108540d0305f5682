"""Training step times read from the progress lines of benchmark worker logs, per arm and window of steps.

For planning GPU holds: how fast arms train when several share one GPU. nerfstudio's progress lines print
`STEP (PCT%)  ITER-TIME ms ...` (a running mean of the step time); this takes their mean over each window.

    python benchmarks/step_rate.py --group 3-arms LOG... --group 5-arms LOG... --output RESULT.json
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Dict

PROGRESS = re.compile(r"(\d+) \(\d+\.\d+%\)\s+([\d.]+) ms")
WINDOWS = ((2000, 3000), (4000, 6000), (10_000, 15_000), (20_000, 30_000), (30_000, 40_000))


def step_ms(text: str) -> Dict[int, float]:
    """{step: the log's step time in ms} from the progress lines (lines that print seconds are skipped)."""
    return {int(m.group(1)): float(m.group(2)) for m in PROGRESS.finditer(text)}


def window_means(steps: Dict[int, float]) -> Dict[str, float]:
    """Mean step time per window of steps, for the windows the log reaches."""
    out = {}
    for lo, hi in WINDOWS:
        inside = [ms for step, ms in steps.items() if lo <= step < hi]
        if inside:
            out[f"{lo}-{hi}"] = sum(inside) / len(inside)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--group", nargs="+", action="append", required=True, metavar=("NAME", "LOG"))
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--note", default="")
    args = parser.parse_args()
    groups: Dict[str, Dict[str, Dict[str, float]]] = {}
    for name, *logs in args.group:
        groups[name] = {Path(log).stem: window_means(step_ms(Path(log).read_text(errors="ignore"))) for log in logs}
    result: Dict[str, object] = {"unit": "ms per training step, mean of the progress lines in each window"}
    result["groups"] = groups
    if args.note:
        result["note"] = args.note
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    for name, arms in groups.items():
        for arm, means in arms.items():
            print(name, arm, " ".join(f"{w}: {ms:.1f}" for w, ms in means.items()))


if __name__ == "__main__":
    main()
