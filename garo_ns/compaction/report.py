"""What compaction did, told three ways: nerfstudio's writer and one console line per round while
training, and a plain summary for the checkpoint and `garo-eval`'s JSON."""

from __future__ import annotations

from typing import Any, Dict, Optional

from garo_ns.compaction.schedule import REASONS


def round_line(event: Dict[str, Any], tolerance_db: float) -> str:
    """One console line for a round: what it removed or undid, and the guard PSNR before and after."""
    head = f"compaction round {event['round']} at step {event['step']}:"
    before, after = event["psnr_before"], event["psnr_after"]
    if before is None:
        return f"{head} no measurement"
    if event["removed"] == 0 and event["restored"] == 0:
        return f"{head} training-view PSNR {before:.2f} dB, {event['num_after']} Gaussians"
    if event["removed"] > 0 and event["restored"] == event["removed"]:
        return (
            f"{head} removing {event['removed']} of {event['num_before']} Gaussians took the training-view PSNR "
            f"from {before:.2f} to {after:.2f} dB (tolerance {tolerance_db:g} dB): put back"
        )
    if event["restored"] > 0:
        return (
            f"{head} training-view PSNR {before:.2f} dB; the last removal is undone "
            f"({event['restored']} Gaussians back, {after:.2f} dB), {event['num_after']} Gaussians"
        )
    return (
        f"{head} removed {event['removed']} of {event['num_before']} Gaussians, training-view PSNR "
        f"{before:.2f} -> {after:.2f} dB, {event['num_after']} left"
    )


def stop_line(summary: Dict[str, Any]) -> str:
    """The console line that says why compaction stopped and what it kept."""
    start, end = summary["num_gaussians_start"], summary["num_gaussians_end"]
    kept = f"kept {end} of {start} Gaussians" + (f" ({end / start:.0%})" if start else "")
    psnr = ""
    if summary["reference_psnr"] is not None and summary["final_psnr"] is not None:
        psnr = f", training-view PSNR {summary['reference_psnr']:.2f} -> {summary['final_psnr']:.2f} dB"
    reason = summary["reason"]
    return (
        f"compaction stopped at step {summary['stopped_step']} ({reason}: {REASONS[reason]}; "
        f"{summary['detail']}): {kept}{psnr}"
    )


def scalars(event: Dict[str, Any]) -> Dict[str, float]:
    """The round's numbers for nerfstudio's writer (name -> value; PSNRs only when measured)."""
    out = {
        "compact/removed": float(event["removed"] - event["restored"]),
        "compact/num_gaussians": float(event["num_after"]),
    }
    for key in ("psnr_before", "psnr_after"):
        if event[key] is not None:
            out[f"compact/{key}"] = float(event[key])
    return out


def summary_for_json(summary: Optional[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """The compaction's summary as garo-eval writes it (None for a run without compaction)."""
    if summary is None:
        return None
    out = dict(summary)
    out["reason_text"] = REASONS.get(summary["reason"]) if summary["reason"] else None
    return out
