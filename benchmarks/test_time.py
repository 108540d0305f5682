"""Time the README's test command and keep what it took: `python benchmarks/test_time.py`.

    python benchmarks/test_time.py --result benchmarks/results/test_time_cpu.json [--note "..."] [-- ARGS ...]

Runs `bash scripts/test.sh --durations=25 ARGS` (set-up, ruff and pytest, as CI runs them) and writes its wall
time, pytest's closing counts, the 25 slowest test phases, the machine's CPU count and its load averages
before and after (a load above the CPU count means the run shared the cores), the commit and a note.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List

ROOT = Path(__file__).resolve().parent.parent
COUNT = re.compile(r"(\d+) (passed|failed|skipped|errors?|deselected|xfailed|xpassed)")
DURATION = re.compile(r"^([\d.]+)s (call|setup|teardown)\s+(\S+)")


def summary_counts(output: str) -> Dict[str, int]:
    """pytest's closing counts (`328 passed, 21 skipped in ...`), from the last line that has them."""
    for line in reversed(output.splitlines()):
        if " in " in line and COUNT.search(line):
            return {kind.rstrip("s") if kind.startswith("error") else kind: int(n) for n, kind in COUNT.findall(line)}
    return {}


def slowest(output: str) -> List[Dict[str, Any]]:
    """The `--durations` table: seconds, phase and test id of each listed test phase."""
    return [
        {"seconds": float(m.group(1)), "phase": m.group(2), "test": m.group(3)}
        for m in map(DURATION.match, output.splitlines())
        if m
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--result", type=Path, default=ROOT / "benchmarks" / "results" / "test_time_cpu.json")
    parser.add_argument("--note", default="")
    parser.add_argument("args", nargs="*", help="more arguments for scripts/test.sh (pytest's)")
    args = parser.parse_args()
    command = ["bash", "scripts/test.sh", "--durations=25", *args.args]
    load_before = os.getloadavg()
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    output = done.stdout + done.stderr
    sys.stdout.write(output[-3000:])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    result = {
        "command": " ".join(command),
        "exit_code": done.returncode,
        "wall_seconds": seconds,
        "counts": summary_counts(output),
        "slowest": slowest(output),
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "git_commit": commit.stdout.strip(),
        "note": args.note,
    }
    args.result.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {args.result}: {seconds / 60:.1f} min, exit {done.returncode}, {result['counts']}")
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
