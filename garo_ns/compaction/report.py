"""What compaction did, told three ways: nerfstudio's writer and one console line per round while
training, and a plain summary for the checkpoint and `garo-eval`'s JSON."""

from __future__ import annotations

from typing import Any, Dict, Optional

from garo_ns.compaction.schedule import REASONS


def round_line(event: Dict[str, Any]) -> str:
    """One console line for a round: the share it tried, what that measured to cost, what it removed."""
    head = f"compaction round {event['round']} at step {event['step']}:"
    if event["share"] is None:
        return f"{head} nothing tried, {event['num_after']} Gaussians"
    tried = "; ".join(
        f"{t['share']:.3g} ({t['count']}) cost {t['cost_worst_db']:.3f} dB worst view, {t['cost_mean_db']:.3f} mean"
        for t in event["tries"]
    )
    if event["removed"] == 0:
        return f"{head} tried {tried}: nothing removed, {event['num_after']} Gaussians"
    return f"{head} tried {tried}: removed {event['removed']} of {event['num_before']}, {event['num_after']} left"


def stop_line(summary: Dict[str, Any]) -> str:
    """The console line that says why compaction stopped, what it kept and what it spent."""
    start, end = summary["num_gaussians_start"], summary["num_gaussians_end"]
    kept = f"kept {end} of {start} Gaussians" + (f" ({end / start:.0%})" if start else "")
    spent = f", {summary.get('spent_db', 0.0):.3f} dB of the {summary['settings'].get('budget_db', 0.0):g} dB budget"
    reason = summary["reason"]
    return (
        f"compaction stopped at step {summary['stopped_step']} ({reason}: {REASONS.get(reason, reason)}; "
        f"{summary['detail']}): {kept}{spent}"
    )


def scalars(event: Dict[str, Any], spent_db: float) -> Dict[str, float]:
    """The round's numbers for nerfstudio's writer (name -> value; the share and costs only when measured),
    the budget spent so far, and at the round that ends compaction `compact/stop_<reason>` (a writer keeps
    numbers only, so the name says why)."""
    out = {
        "compact/removed": float(event["removed"]),
        "compact/num_gaussians": float(event["num_after"]),
        "compact/spent_db": float(spent_db),
    }
    for key in ("share", "cost_mean_db", "cost_worst_db"):
        if event[key] is not None:
            out[f"compact/{key}"] = float(event[key])
    if "stop" in event:
        out[f"compact/stop_{event['stop']}"] = 1.0
    return out


def summary_for_json(summary: Optional[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """The compaction's summary as garo-eval writes it (None for a run without compaction)."""
    if summary is None:
        return None
    out = dict(summary)
    out["reason_text"] = REASONS.get(summary["reason"]) if summary["reason"] else None
    return out
