"""Mutation results per module, and the report built from them (see scripts/mutation.sh).

    python scripts/mutation_report.py collect WORK_DIR RESULTS_DIR
    python scripts/mutation_report.py report RESULTS_DIR NOTES_JSON REPORT_MD

`collect` reads a finished `mutmut run` in WORK_DIR (its results.txt, `mutmut results --all true`)
and writes one file per mutated module, RESULTS_DIR/mutation_<module>.json: the number of mutants,
how many were killed, every survivor with its diff, the commit and date of the run and the sha256
of the module's source. A module whose mutants were all run replaces its file; one that a run
reached only in part (a stopped run, or MUTATION_NAMES naming a few mutants) is written only where
no complete file exists, marked partial. So the two halves of scripts/mutation.sh (the stages and
strategy, then kNN) can run at different times and the report still covers all five modules.

`report` builds REPORT_MD from every mutation_*.json in RESULTS_DIR. NOTES_JSON maps a surviving
mutant's name to {"kind": "equivalent" | "harmless", "why": "..."}. The score is
killed / (all - equivalent): harmless survivors (a change no test of the CPU code can see, such as
a CUDA-only device argument or a speed parameter) stay in the denominator. A module whose source
changed (or moved) since its run is flagged stale (its mutant names may no longer match). Survivors without a
note are listed as UNEXPLAINED and make the exit status 1, as do partial or stale modules.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

KILLED = {"killed", "timeout"}
ROOT = Path(__file__).resolve().parents[1]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def collect(work: Path, results: Path) -> int:
    statuses = {}
    for line in (work / "results.txt").read_text().splitlines():
        if ":" in line and line.startswith("    "):
            name, status = line.strip().rsplit(": ", 1)
            statuses[name] = status
    by_module = defaultdict(dict)
    for n, s in statuses.items():
        # garo_ns.redundancy.knn.x_knn__mutmut_3 or garo_ns.garo_strategy.xǁGaroStrategyǁ..._mutmut_1
        by_module[n[: n.index(".x")]][n] = s
    mutmut = str(Path(sys.executable).parent / "mutmut")
    commit = _git("rev-parse", "--short", "HEAD")
    dirty = _git("status", "--porcelain", "--untracked-files=no", "--", "garo_ns", "tests")
    results.mkdir(parents=True, exist_ok=True)
    for dotted, st in sorted(by_module.items()):
        mod, source = dotted.rsplit(".", 1)[-1], dotted.replace(".", "/") + ".py"
        checked = {n: s for n, s in st.items() if s != "not checked"}
        if not checked:
            continue
        out = results / f"mutation_{mod}.json"
        partial = len(checked) < len(st)
        if partial and out.exists() and not json.loads(out.read_text()).get("partial"):
            print(f"{mod}: {len(checked)} of {len(st)} mutants run; the complete {out} is kept")
            continue
        survivors = {}
        for n in sorted(x for x, s in checked.items() if s not in KILLED):
            diff = subprocess.run([mutmut, "show", n], cwd=work, capture_output=True, text=True).stdout
            body = [ln for ln in diff.splitlines() if ln.startswith(("+", "-")) and not ln.startswith(("+++", "---"))]
            survivors[n] = {"status": checked[n], "diff": body}
        data = {
            "module": mod,
            "source": source,
            "source_sha256": _sha256(work / source),
            "commit": commit + (" (tests or sources modified)" if dirty else ""),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
            "mutmut": "3.8.1",
            "mutants": len(st),
            "run": len(checked),
            "killed": sum(s in KILLED for s in checked.values()),
            "partial": partial,
            "wall_s": int(os.environ.get("MUTATION_WALL_S", 0)) or None,  # the whole run, all modules in it
            "workers": int(os.environ.get("MUTATION_JOBS", 0)) or None,
            "property_examples": int(os.environ.get("GARO_PROPERTY_EXAMPLES", 0)) or None,
            "note": os.environ.get("MUTATION_NOTE", ""),
            "survivors": survivors,
        }
        out.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n")
        print(f"{mod}: {data['killed']} of {len(checked)} run killed ({len(st)} mutants) -> {out}")
    return 0


def report(results: Path, notes_path: Path, out: Path) -> int:
    notes = json.loads(notes_path.read_text()) if notes_path.exists() else {}
    mods = [json.loads(p.read_text()) for p in sorted(results.glob("mutation_*.json"))]
    rows, sections, runs = [], [], defaultdict(list)
    tot = defaultdict(int)
    unexplained = problems = 0
    for m in mods:
        surv = m["survivors"]
        equivalent = sum(notes.get(n, {}).get("kind") == "equivalent" for n in surv)
        scored = m["run"] - equivalent
        src = ROOT / m["source"]
        stale = not src.exists() or _sha256(src) != m["source_sha256"]
        problems += stale + m["partial"]
        flag = (" (partial run)" if m["partial"] else "") + (" (source changed since: stale)" if stale else "")
        rows.append(
            f"| {m['module']}{flag} | {m['mutants']} | {m['run']} | {m['killed']} | {len(surv)} | {equivalent} "
            f"| {m['killed']}/{scored} = {100 * m['killed'] / max(scored, 1):.1f}% |"
        )
        for key, v in (("mutants", m["mutants"]), ("run", m["run"]), ("killed", m["killed"])):
            tot[key] += v
        tot["survived"] += len(surv)
        tot["equivalent"] += equivalent
        how = ", ".join(
            f"{v} {label}"
            for v, label in (
                (m.get("wall_s") and f"{m['wall_s'] / 60:.0f} min", "wall"),
                (m.get("workers"), "workers"),
                (m.get("property_examples"), "hypothesis examples per property test"),
            )
            if v
        )
        note = (f"{how}. " if how else "") + m.get("note", "")
        runs[(m["date"], m["commit"], note)].append(f"`{m['module']}`")
        for n, s in sorted(surv.items()):
            note = notes.get(n)
            unexplained += note is None
            kind = note["kind"] if note else "UNEXPLAINED"
            sections += [f"### `{n}` ({s['status']}): {kind}", "", "```diff", *s["diff"], "```", ""]
            if note:
                sections += [note["why"], ""]
    scored = tot["run"] - tot["equivalent"]
    missing = tot["mutants"] - tot["run"]
    lines = [
        "# Mutation testing of GARO's stages and strategy, and of compaction",
        "",
        "Built by `python scripts/mutation_report.py report` from the per-module results in",
        "`benchmarks/results/mutation_*.json`, which `bash scripts/mutation.sh` writes (mutmut 3.8.1; each",
        "mutant run against the fast tests that scripts/mutation.sh lists: tests/test_redundancy_stages.py,",
        "tests/test_redundancy_strategy.py, tests/test_garo_strategy.py and, since 2026-11-24, the tests of",
        "tests/test_compaction.py and tests/test_model_settings.py not marked slow). Score = killed / (run -",
        "equivalent); harmless survivors count as not killed.",
        "",
        f"**Score: {tot['killed']} killed of {scored} non-equivalent mutants = "
        f"{100 * tot['killed'] / max(scored, 1):.1f}%** ({tot['run']} mutants run, {tot['equivalent']} equivalent, "
        f"{tot['survived'] - tot['equivalent']} harmless or unexplained survivors"
        + (f"; {missing} mutants not run" if missing else "")
        + ").",
        "",
        "| module | mutants | run | killed | survived | equivalent | score |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "## Runs",
        "",
        *(f"* {', '.join(ms)}: {d}, commit {c}. {note}".rstrip() for (d, c, note), ms in runs.items()),
        "",
        "## Survivors",
        "",
        *sections,
    ]
    out.write_text("\n".join(lines).rstrip() + "\n")
    print(
        f"{tot['killed']}/{scored} killed ({tot['equivalent']} equivalent, {missing} not run); "
        f"{unexplained} unexplained survivors; {problems} partial or stale modules -> {out}"
    )
    return 1 if unexplained or problems else 0


if __name__ == "__main__":
    cmd, *args = sys.argv[1:]
    sys.exit(collect(*map(Path, args)) if cmd == "collect" else report(*map(Path, args)))
