"""Per-channel-group storage for the time table: how much memory would storing only the groups that move save?

A table (garo_ns.render.time_table) keys all 10 offset channels of every moving Gaussian. Here, on a random subset of
a trained model's Gaussians, per Gaussian and group g (position 3, rotation 4, scale 3 channels), motion_g = the
largest |offset(t) - offset(mid-range)| over an even time grid on [t_lo, t_hi], in the table's `channel_units`, max
over the group's channels. A group with motion_g <= T could be stored once (its base), costing at most T of error
(up to the grid's resolution of the motion). Reported per threshold T (max e_0 of the subset, 10x, 100x, the spec's
tolerance; e_0 = a Gaussian's linear midpoint error at the recorded spacing, from table_levels_standup_cpu.json):
the share of (Gaussian, group) slots dropped and the share of the table's channels kept. A light check recomputes
e_0 at a few of the table's segments (a lower bound on the recorded one, same subset).

    .venv/bin/python benchmarks/table_channels.py [--variants garo-compact garo-deform deform-splatfacto]
        [--subset 2000] [--seed 0] [--times 1001] [--check-segments 32] [--minutes 45]

Reads the exports under .trained/standup/, the recorded table specs in
benchmarks/results/table_fp32_standup_H200.json and the e_0 quantiles in
benchmarks/results/table_levels_standup_cpu.json; writes benchmarks/results/table_channels_standup_cpu.json after
each variant.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import torch
from torch import Tensor

from garo_ns.render.time_table import PAD, TableSpec, channel_units, field_offsets, iter_field_offsets

ROOT = Path(__file__).resolve().parent.parent
EXPORTS = ROOT / ".trained" / "standup"
RECORDED = ROOT / "benchmarks" / "results" / "table_fp32_standup_H200.json"
LEVELS = ROOT / "benchmarks" / "results" / "table_levels_standup_cpu.json"
OUT = ROOT / "benchmarks" / "results" / "table_channels_standup_cpu.json"
GROUPS: Dict[str, Tuple[int, int]] = {"position": (0, 3), "rotation": (3, 7), "scale": (7, 10)}
QUANTILES = (0.5, 0.9, 0.99, 1.0)
CHUNK = 1 << 14  # rows per field call, as table_levels.py measured fastest on this CPU


def shell(cmd: Sequence[str]) -> str:
    return subprocess.run(list(cmd), capture_output=True, text=True, check=False).stdout.strip()


def load_field(export: Path) -> Tuple[torch.nn.Module, Tensor, str]:
    """The export's deformation field (eval mode, CPU), canonical means [N, 3] and its scale-offset composition."""
    import yaml

    config = yaml.load((export / "config.yml").read_text(), Loader=yaml.Loader)
    model_cfg = config.pipeline.model
    field = model_cfg.make_deformation()
    state = torch.load(export / "model.ckpt", map_location="cpu", weights_only=False)["pipeline"]
    prefix = "_model.deformation."
    field.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})
    field.eval()
    return field, state["_model.gauss_params.means"].float(), str(model_cfg.deform_scale_offset)


def recorded_table(variant: str) -> Dict[str, Any]:
    """The time table record of `variant`+auto: its spec, info (scale_offset, error quantiles, mb)."""
    row = json.loads(RECORDED.read_text())["variants"][f"{variant}+auto"]
    table = row.get("time_table") or row["switch_record"]["time_table"]
    info = table if "keys" in table else table["info"]
    return {"spec": info["spec"], "info": {k: v for k, v in info.items() if k != "spec"}}


def recorded_e0(variant: str, subset: int, seed: int) -> Dict[str, float]:
    """The linear level-0 midpoint error quantiles table_levels.py recorded for the same subset."""
    levels = json.loads(LEVELS.read_text())
    if levels["subset"] != subset or levels["seed"] != seed:
        raise ValueError(f"{LEVELS.name} holds subset {levels['subset']} seed {levels['seed']}, not {subset} {seed}")
    return levels["variants"][variant]["linear"]["e_quantiles"]["l0"]


def quantiles(x: Tensor) -> Dict[str, float]:
    x = x.double()
    return {str(q): float(x.quantile(q)) for q in QUANTILES}


def group_motion(field: Any, xyz: Tensor, spec: TableSpec, units: Tensor, times: int) -> Tuple[Tensor, Tensor]:
    """[n, 3] motion per group (position, rotation, scale) over `times` even times on [t_lo, t_hi], from the offsets
    at mid-range (sampled as `TimeTable.build` samples its base), and the base [n, 10]."""
    base = field_offsets(field, xyz, [0.5 * (spec.t_lo + spec.t_hi)])[0]
    grid = torch.linspace(spec.t_lo, spec.t_hi, times, dtype=torch.float64).tolist()
    motion = torch.zeros(xyz.shape[0], 10)
    for _, d in iter_field_offsets(field, xyz, grid, CHUNK):
        motion = torch.maximum(motion, (d - base).abs() * units)
    per_group = torch.stack([motion[:, a:b].amax(-1) for a, b in GROUPS.values()], dim=-1)
    return per_group, base


def check_e0(field: Any, xyz: Tensor, spec: TableSpec, units: Tensor, segments: int) -> Tensor:
    """Per Gaussian, the largest linear midpoint error at `segments` of the table's segments spread over the range
    (`midpoint_errors`' picks, fp32 keys): a lower bound on e_0 over all segments."""
    n_seg = spec.intervals + 1
    picks = torch.linspace(0, n_seg - 1, min(segments, n_seg)).round().long().unique().tolist()
    key_t = spec.key_times()
    times: List[float] = []
    for p in picks:
        i = PAD - 1 + p
        times += [float(key_t[i]), float(key_t[i + 1]), float(key_t[i]) + 0.5 * spec.spacing]
    d = field_offsets(field, xyz, times, CHUNK).view(len(picks), 3, xyz.shape[0], 10)
    err = ((0.5 * (d[:, 0] + d[:, 1]) - d[:, 2]).abs() * units).amax(-1)  # [segments, n]
    return err.amax(0)


def drop_tables(motion: Tensor, thresholds: Dict[str, float]) -> Dict[str, Any]:
    """Per threshold: the share of (Gaussian, group) slots with motion <= T, per group, and the channels kept."""
    n = motion.shape[0]
    sizes = torch.tensor([b - a for a, b in GROUPS.values()], dtype=torch.float64)
    out: Dict[str, Any] = {}
    for name, t in thresholds.items():
        dropped = motion <= t  # [n, 3]
        kept_channels = float(((~dropped).double() * sizes).sum())
        out[name] = {
            "T": t,
            "slots_dropped_share": float(dropped.double().mean()),
            "dropped_share_per_group": {g: float(dropped[:, k].double().mean()) for k, g in enumerate(GROUPS)},
            "gaussians_all_groups_dropped_share": float(dropped.all(-1).double().mean()),
            "memory_fraction_kept": kept_channels / (10 * n),
        }
    return out


def run_variant(variant: str, subset: int, seed: int, times: int, segments: int) -> Dict[str, Any]:
    record = recorded_table(variant)
    spec = TableSpec(**record["spec"])
    t0 = time.perf_counter()
    field, means, scale_offset = load_field(EXPORTS / variant)
    load_s = time.perf_counter() - t0
    if scale_offset != record["info"].get("scale_offset", scale_offset):
        raise ValueError(f"{variant}: config says {scale_offset}, the record {record['info']['scale_offset']}")
    pick = torch.randperm(means.shape[0], generator=torch.Generator().manual_seed(seed))[:subset]
    xyz = means[pick].contiguous()
    n = xyz.shape[0]
    units = channel_units(spec, scale_offset, xyz.device)  # type: ignore[arg-type]
    e0 = recorded_e0(variant, subset, seed)
    with torch.no_grad():
        t0 = time.perf_counter()
        motion, _ = group_motion(field, xyz, spec, units, times)
        motion_s = time.perf_counter() - t0
        print(f"{variant}: motion over {times} times in {motion_s:.1f} s", flush=True)
        t0 = time.perf_counter()
        e0_check = check_e0(field, xyz, spec, units, segments) if segments > 0 else None
        check_s = time.perf_counter() - t0
        print(f"{variant}: e_0 check at {segments} segments in {check_s:.1f} s", flush=True)
    e0_max = float(e0["1.0"])
    thresholds = {"max_e0": e0_max, "10x_max_e0": 10 * e0_max, "100x_max_e0": 100 * e0_max}
    thresholds["tolerance"] = float(spec.tolerance)
    check_times = 3 * min(segments, spec.intervals + 1) if segments > 0 else 0
    result: Dict[str, Any] = {
        "spec": spec.to_dict(),
        "scale_offset": scale_offset,
        "recorded_info": record["info"],
        "gaussians_total": int(means.shape[0]),
        "subset": n,
        "motion_grid_times": times,
        "field_evaluations": {"motion": (times + 1) * n, "e0_check": check_times * n},
        "e0_recorded_quantiles": e0,
        "motion_quantiles": {g: quantiles(motion[:, k]) for k, g in enumerate(GROUPS)},
        "motion_zero_share": {g: float((motion[:, k] == 0).double().mean()) for k, g in enumerate(GROUPS)},
        "drop": drop_tables(motion, thresholds),
        "seconds": {"load": load_s, "motion": motion_s, "e0_check": check_s},
    }
    if e0_check is not None:
        slot_ok = motion <= e0_check[:, None]
        result["e0_check"] = {
            "segments": min(segments, spec.intervals + 1),
            "quantiles": quantiles(e0_check),
            "max_over_recorded_max": float(e0_check.max()) / e0_max,
            "slots_with_motion_within_own_e0_share": float(slot_ok.double().mean()),
        }
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=["garo-compact", "garo-deform", "deform-splatfacto"])
    parser.add_argument("--subset", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--times", type=int, default=1001, help="even motion grid over [t_lo, t_hi], ends included")
    parser.add_argument("--check-segments", type=int, default=32, help="segments of the e_0 check (0: none)")
    parser.add_argument("--minutes", type=float, default=45.0, help="start no variant after this much wall time")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    deadline = time.perf_counter() + 60 * args.minutes
    out: Dict[str, Any] = {
        "question": __doc__.splitlines()[0],
        "git_commit": shell(["git", "-C", str(ROOT), "rev-parse", "HEAD"]),
        "command": "python benchmarks/table_channels.py "
        + f"--variants {' '.join(args.variants)} --subset {args.subset} --seed {args.seed} --times {args.times} "
        + f"--check-segments {args.check_segments}",
        "subset": args.subset,
        "seed": args.seed,
        "grid": {"motion_times": args.times, "spacing": "even on [t_lo, t_hi], both ends included"},
        "groups": {g: list(range(a, b)) for g, (a, b) in GROUPS.items()},
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "uptime_start": shell(["uptime"]),
        "notes": [
            "motion_g: max over the grid of |offset(t) - offset((t_lo + t_hi) / 2)| x channel_units, max over g's "
            "channels; a grid's max is a lower bound on the continuous max",
            "T max_e0: the largest linear level-0 midpoint error of the same subset (seed, randperm) recorded in "
            "table_levels_standup_cpu.json (all segments, fp32 keys); tolerance: the recorded spec's",
            "memory_fraction_kept: sum over kept (Gaussian, group) slots of the group's channels / (10 n), the share "
            "of the key channels a per-group table would hold (anchors and per-channel scales shrink alike; the "
            "fp32 base of every channel is kept regardless)",
            "e0_check: the linear midpoint error at a few segments (fp32 keys sampled here), a lower bound on e_0 "
            "and a check that the subset matches the recorded one",
        ],
        "variants": {},
        "missing": [],
    }
    started = time.perf_counter()
    for variant in args.variants:
        if time.perf_counter() > deadline:
            out["missing"].append({"variant": variant, "why": "not started: past the deadline"})
            continue
        print(f"== {variant}", flush=True)
        out["variants"][variant] = run_variant(variant, args.subset, args.seed, args.times, args.check_segments)
        out["seconds_total"] = time.perf_counter() - started
        out["uptime_end"] = shell(["uptime"])
        args.out.write_text(json.dumps(out, indent=1))
    out["seconds_total"] = time.perf_counter() - started
    out["uptime_end"] = shell(["uptime"])
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
