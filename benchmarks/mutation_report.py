"""Writes the mutation report from a finished `mutmut run` (see scripts/mutation.sh).

Usage: python benchmarks/mutation_report.py WORK_DIR NOTES_JSON REPORT_MD

WORK_DIR holds mutmut's results.txt (`mutmut results --all true`). NOTES_JSON maps a surviving
mutant's name to {"kind": "equivalent" | "harmless", "why": "..."}. The score is
killed / (all - equivalent): harmless survivors (a change no test of the CPU code can see, such as
a CUDA-only synchronisation or a speed parameter) stay in the denominator. Survivors without a
note are listed as UNEXPLAINED and make the exit status 1.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

KILLED = {"killed", "timeout"}


def main(work: Path, notes_path: Path, out: Path) -> int:
    statuses = {}
    for line in (work / "results.txt").read_text().splitlines():
        if ":" in line and line.startswith("    "):
            name, status = line.strip().rsplit(": ", 1)
            statuses[name] = status
    unchecked = sorted(n for n, s in statuses.items() if s == "not checked")  # a run cut short
    statuses = {n: s for n, s in statuses.items() if s != "not checked"}
    notes = json.loads(notes_path.read_text()) if notes_path.exists() else {}
    survivors = sorted(n for n, s in statuses.items() if s not in KILLED)
    equivalent = [n for n in survivors if notes.get(n, {}).get("kind") == "equivalent"]
    killed = sum(s in KILLED for s in statuses.values())
    scored = len(statuses) - len(equivalent)
    by_module = defaultdict(Counter)
    for n, s in statuses.items():
        by_module[n.split(".")[1]]["killed" if s in KILLED else "survived"] += 1
    mutmut = str(Path(sys.executable).parent / "mutmut")
    lines = [
        "# Mutation testing of GARO's stages and strategy",
        "",
        "Produced by `bash scripts/mutation.sh` (mutmut 3.8.1; each mutant run against",
        "tests/test_redundancy_stages.py, tests/test_redundancy_strategy.py and tests/test_garo_strategy.py).",
        "",
        f"**Score: {killed} killed of {scored} non-equivalent mutants = {100 * killed / max(scored, 1):.1f}%** "
        f"({len(statuses)} mutants, {len(equivalent)} equivalent, {len(survivors) - len(equivalent)} "
        "harmless or unexplained survivors).",
        "",
        f"Not run (the run was stopped before them): {len(unchecked)} mutants"
        + (": " + ", ".join(sorted({n.split("__mutmut")[0] for n in unchecked})) if unchecked else "."),
        "",
        "| module | mutants | killed | survived |",
        "|---|---|---|---|",
    ]
    for mod, c in sorted(by_module.items()):
        lines.append(f"| {mod} | {c['killed'] + c['survived']} | {c['killed']} | {c['survived']} |")
    lines += ["", "## Survivors", ""]
    unexplained = 0
    for n in survivors:
        note = notes.get(n)
        kind = note["kind"] if note else "UNEXPLAINED"
        unexplained += note is None
        diff = subprocess.run([mutmut, "show", n], cwd=work, capture_output=True, text=True).stdout
        body = [ln for ln in diff.splitlines() if ln.startswith(("+", "-")) and not ln.startswith(("+++", "---"))]
        lines += [f"### `{n}` ({statuses[n]}): {kind}", "", "```diff", *body, "```", ""]
        if note:
            lines += [note["why"], ""]
    out.write_text("\n".join(lines) + "\n")
    print(f"{killed}/{scored} killed ({len(equivalent)} equivalent); {unexplained} unexplained survivors -> {out}")
    return 1 if unexplained else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])))
