"""Writing training profiles down: a result file's windows as a Markdown table, and the block of docs/benchmarks.md
made from result files (`python -m garo_ns.bench.profile_docs DOC RESULT...` rewrites it)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, Sequence

from garo_ns.bench.step_phases import PHASES

OLD_KEYS = {"gpu_busy_share": "gpu_kernel_share"}
"""A window's keys under their names in older files: the same measure (the profiler window records GPU activity only,
so summing every event there sums the GPU's own)."""


def _window_value(window: Dict[str, Any], key: str) -> Any:
    """`key` of a window: its own, under its older name (OLD_KEYS), or its host pass's."""
    for name in (key, OLD_KEYS.get(key)):
        if name is not None and name in window:
            return window[name]
    return window.get("host_ops", {}).get(key)


def markdown_table(result: Dict[str, Any]) -> str:
    """The windows of a result as a table: device ms per step of each phase (host ms in brackets)."""
    windows = result["windows"]
    if not windows:  # a timing run (`--windows` past its last step): its timeline is what it measured
        marks = [r for r in result.get("timeline") or [] if r["step"] % 5000 == 0 or r["step"] == result.get("steps")]
        if not marks:
            return "No profile window and no timeline in this run.\n"
        steps = " | ".join(f"{r['step']:,}" for r in marks)
        seconds = " | ".join(f"{r['seconds']:.0f}" for r in marks)
        return (
            "No profile window (a run that times the whole run alone). Seconds elapsed at each step:\n\n"
            f"| step | {steps} |\n|---|{'---|' * len(marks)}\n| seconds | {seconds} |\n"
        )
    head = "| phase | " + " | ".join(f"step {w['step']:,} ({w['gaussians']:,} Gaussians)" for w in windows) + " |"
    rows = [head, "|---|" + "---|" * len(windows)]
    for phase in PHASES:
        cells = []
        for w in windows:
            d, h = w.get("device_ms", {}).get(phase), w.get("host_ms", {}).get(phase)
            cells.append("" if d is None else f"{d:.2f} ({h:.2f})")
        rows.append(f"| {phase} | " + " | ".join(cells) + " |")
    for key, label in (
        ("instrumented_ms_per_step", "step, instrumented"),
        ("plain_ms_per_step", "step, plain (wall)"),
        ("host_syncs_per_step", "host syncs per step"),
        ("gpu_busy_share", "GPU busy share"),
        ("launches_per_step", "kernel and graph launches per step"),
    ):
        vals = [_window_value(w, key) for w in windows]
        if any(v is not None for v in vals):
            rows.append(f"| {label} | " + " | ".join("" if v is None else f"{v:.2f}" for v in vals) + " |")
    # Where the GPU's time goes, in the last window that says (its 10 costliest events).
    last = next((w for w in reversed(windows) if w.get("top_kernels")), None)
    if last is not None:
        rows += ["", f"GPU events at step {last['step']:,}, per step:", "", "| event | ms | calls |", "|---|---|---|"]
        rows += [
            f"| `{k['name']}` | {k['ms_per_step']:.3f} | {k['calls_per_step']:.1f} |" for k in last["top_kernels"][:10]
        ]
    return "\n".join(rows) + "\n"


DOCS_BEGIN, DOCS_END = "<!-- train-profile:begin -->", "<!-- train-profile:end -->"


def docs_block(results: Sequence[Path]) -> str:
    """The docs' block for these result files: one table per file, with its run's figures."""
    parts = []
    for path in results:
        r = json.loads(Path(path).read_text())
        gpu = r["environment"].get("gpu") or "a CPU"
        score = r.get("score") or {}
        scored = f", test PSNR {score['psnr']:.2f} dB" if "psnr" in score else ""
        settings = r.get("model_settings") or {}
        named = " with " + ", ".join(f"`{k}={v}`" for k, v in sorted(settings.items())) if settings else ""
        commit = (r["environment"].get("git_commit") or "")[:7]
        at = f" at {commit}" if commit else ""
        parts.append(
            f"`{r['method']}`{at}{named} on {r['scene']}, {gpu}, alone on its GPU: {r['steps']:,} steps in "
            f"{r['train_seconds']:.0f} s ({r['steps_per_second']:.1f} steps/s){scored} "
            f"([`{Path(path).name}`](../benchmarks/results/{Path(path).name})). Device ms per step (host ms):\n\n"
            + markdown_table(r)
        )
    return "\n".join(parts)


def docs_main() -> None:
    """`python -m garo_ns.bench.profile_docs DOC RESULT...`: rewrite DOC's block between the markers with
    `docs_block(RESULT...)`."""
    doc, *results = map(Path, sys.argv[1:])
    text = doc.read_text()
    head, rest = text.split(DOCS_BEGIN, 1)
    new = f"{head}{DOCS_BEGIN}\n{docs_block(results)}{DOCS_END}{rest.split(DOCS_END, 1)[1]}"
    doc.write_text(new)
    print(f"{doc}: {'rewritten' if new != text else 'unchanged'}")


if __name__ == "__main__":
    docs_main()
