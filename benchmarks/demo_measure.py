"""Run the demo under `/usr/bin/time -v` and write its results with the measured wall time and memory.

    python benchmarks/demo_measure.py --out /tmp/demo --result benchmarks/results/demo_cpu.json \
        [--note "..."] [-- COMMAND ...]

COMMAND defaults to `bash scripts/demo.sh --output-dir OUT`; another command (e.g. the demo's Python entry
in an environment set up elsewhere) must write OUT/demo_results.json. The result file is that JSON with a
`measured` block: the command, the environment variables that set threads, /usr/bin/time's elapsed time,
peak RSS, user and system seconds and CPU share, the machine's CPU count and its load averages before and
after (a load above the CPU count means the run shared the cores), and the free-text note.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

TIME_FIELDS = {
    "Elapsed (wall clock) time (h:mm:ss or m:ss)": "time_v_elapsed",
    "Maximum resident set size (kbytes)": "time_v_max_rss_kb",
    "User time (seconds)": "time_v_user_s",
    "System time (seconds)": "time_v_system_s",
    "Percent of CPU this job got": "time_v_cpu_percent",
}


def parse_time_v(text: str) -> dict:
    """The fields of TIME_FIELDS from /usr/bin/time -v's report."""
    out = {}
    for line in text.splitlines():
        key, _, value = line.strip().rpartition(": ")
        if key in TIME_FIELDS:
            value = value.strip()
            out[TIME_FIELDS[key]] = int(value) if re.fullmatch(r"\d+", value) else value
    if "time_v_elapsed" in out:  # `h:mm:ss` or `m:ss.ss`
        out["time_v_elapsed_s"] = functools.reduce(
            lambda t, part: t * 60 + float(part), out["time_v_elapsed"].split(":"), 0.0
        )
    for key in ("time_v_user_s", "time_v_system_s"):
        if key in out:
            out[key] = float(out[key])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="the demo's output directory")
    parser.add_argument("--result", type=Path, required=True, help="where to write the result JSON")
    parser.add_argument("--note", default="", help="what the numbers do not say (e.g. other work on the machine)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND ... (default: scripts/demo.sh)")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    command = command or ["bash", "scripts/demo.sh", "--output-dir", str(args.out)]
    load_before = os.getloadavg()
    with tempfile.NamedTemporaryFile("r", suffix=".time") as report:
        run = subprocess.run(["/usr/bin/time", "-v", "-o", report.name, *command])
        measured = parse_time_v(Path(report.name).read_text())
    load_after = os.getloadavg()
    if run.returncode != 0:
        sys.exit(f"the demo failed with exit status {run.returncode}")
    result = json.loads((args.out / "demo_results.json").read_text())
    env = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "TORCHDYNAMO_DISABLE") if k in os.environ}
    result["measured"] = {
        "command": shlex.join(command),
        "environment": env,
        **measured,
        "cpu_count": os.cpu_count(),
        "load_average_before": list(load_before),
        "load_average_after": list(load_after),
        "note": args.note,
    }
    args.result.parent.mkdir(parents=True, exist_ok=True)
    args.result.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"{args.result}: {measured.get('time_v_elapsed')} wall, {measured.get('time_v_max_rss_kb', 0) / 1024:.0f} MB "
        f"peak RSS; " + ", ".join(f"{a['method']} {a['psnr']:.2f} dB" for a in result["arms"])
    )


if __name__ == "__main__":
    main()
