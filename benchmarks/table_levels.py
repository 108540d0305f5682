"""Per-Gaussian key spacing for the time table: how much memory would it save at the same per-Gaussian error?

A flat table (garo_ns.render.time_table) keys every Gaussian at the spacing its worst Gaussians need. Here each
Gaussian g could sit on its own level l, keys 2^l times as far apart: on a random subset of a trained model's
Gaussians, per level l = 0 .. 6 and Gaussian, e_l(g) = the largest linear-interpolation error at any segment's
midpoint (fp32 keys, per channel in the table's `channel_units`, max over channels: `midpoint_errors`' measure,
through `midpoint_errors` itself), and what a leveled table would keep of the flat table's keys when each Gaussian
takes the coarsest level with e_l(g) <= max(e_0(g), Q).

    .venv/bin/python benchmarks/table_levels.py [--variants garo-compact garo-deform deform-splatfacto]
        [--subset 2000] [--seed 0] [--levels 6] [--minutes 68]

Reads the exports under .trained/standup/ and the recorded table specs in
benchmarks/results/table_fp32_standup_H200.json; writes benchmarks/results/table_levels_standup_cpu.json after
each variant. Level l's keys lie at t_lo + (k + 0.5) 2^l h (h the recorded spacing) and its midpoints at
t_lo + p 2^l h, all on the half-spacing grid t_lo + j h / 2: the field is sampled once per grid time any level
needs (about 2 x intervals + 4 times), so every level reuses level 0's samples.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import torch
from torch import Tensor

from garo_ns.render.time_table import (
    CHANNELS,
    ORDERS,
    PAD,
    Order,
    TableSpec,
    interpolate,
    iter_field_offsets,
    midpoint_errors,
    table_bytes,
)

ROOT = Path(__file__).resolve().parent.parent
EXPORTS = ROOT / ".trained" / "standup"
RECORDED = ROOT / "benchmarks" / "results" / "table_fp32_standup_H200.json"
OUT = ROOT / "benchmarks" / "results" / "table_levels_standup_cpu.json"
QUANTILES = (0.5, 0.9, 0.99, 0.999, 1.0)
CHUNK = 1 << 14  # rows per field call: the fastest of 2^14, 2^16, 2^18 measured on this CPU


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


def level_intervals(intervals: int, level: int) -> int:
    """Segments of level `level` over the range: keys at (k + 0.5) 2^l h for k = -1 .. M, the last at or past t_hi."""
    step = 1 << level
    return max(1, math.ceil((2 * intervals / step - 1) / 2))


def level_spec(spec: TableSpec, level: int) -> TableSpec:
    """A spec whose keys are level `level`'s: spacing 2^l h, its range extended to a whole number of segments."""
    m = level_intervals(spec.intervals, level)
    t_hi = spec.t_lo + m * (1 << level) * spec.spacing
    return TableSpec(**{**spec.to_dict(), "t_hi": t_hi, "intervals": m})


def key_grid(level: int, i: int) -> int:
    """Half-spacing grid index of level `level`'s key i (a TableSpec's key index, PAD keys before t_lo)."""
    return (2 * (i - PAD) + 1) << level


def level_grid(intervals: int, level: int) -> List[int]:
    """Every grid index level `level` reads: its keys (with PAD beyond each end) and its segments' midpoints."""
    m = level_intervals(intervals, level)
    keys = [key_grid(level, i) for i in range(m + 2 * PAD)]
    mids = [(2 * p) << level for p in range(m + 1)]
    return sorted(set(keys) | set(mids))


class GridField:
    """A stand-in for the field (`midpoint_errors` samples through it): the cached offsets at a grid time."""

    def __init__(self, t_lo: float, unit: float, rows: Dict[int, int], cache: Tensor) -> None:
        self.t_lo, self.unit, self.rows, self.cache = t_lo, unit, rows, cache

    def index(self, time: float) -> int:
        j = round((time - self.t_lo) / self.unit)
        if abs(time - (self.t_lo + j * self.unit)) > 0.01 * self.unit or j not in self.rows:
            raise KeyError(f"time {time} is not a sampled grid time (nearest index {j})")
        return self.rows[j]

    def __call__(self, xyz: Tensor, time: Any) -> Tuple[Tensor, Tensor, Tensor]:
        d = self.cache[self.index(float(time))]
        assert d.shape[0] == xyz.shape[0]
        return d[:, :3], d[:, 3:7], d[:, 7:]


def quantiles(x: Tensor) -> Dict[str, float]:
    x = x.double()
    return {str(q): float(x.quantile(q)) for q in QUANTILES}


def level_tables(err: List[Tensor], spec: TableSpec, precision: str, flat_mb: float | None) -> Dict[str, Any]:
    """Shares under each bound Q, the leveled table's key and byte fractions, and how errors change per level."""
    e0 = err[0]
    stacked = torch.stack(err)  # [L, n]
    levels = len(err)
    per_gaussian = [table_bytes(level_intervals(spec.intervals, lv), 1, precision) for lv in range(levels)]
    qs = {"e0": 0.0, "median": float(e0.quantile(0.5)), "p90": float(e0.quantile(0.9))}
    qs.update({"p99": float(e0.quantile(0.99)), "max": float(e0.max())})
    out: Dict[str, Any] = {"e_quantiles": {f"l{lv}": quantiles(e) for lv, e in enumerate(err)}, "Q": qs}
    out["share_within_Q"] = {
        name: {f"l{lv}": float((err[lv] <= q).double().mean()) for lv in range(levels)}
        for name, q in qs.items()
        if name != "e0"
    }
    memory: Dict[str, Any] = {}
    for name, q in qs.items():
        ok = stacked <= torch.clamp_min(e0, q)[None]  # level 0 always passes
        chosen = torch.where(ok, torch.arange(levels)[:, None], torch.zeros_like(stacked, dtype=torch.long))
        level = chosen.amax(0)  # the coarsest level within the bound
        monotone = ok.long().cumprod(0).sum(0) - 1  # the coarsest level with every finer one within it too
        row: Dict[str, Any] = {}
        for rule, lv in (("coarsest", level), ("coarsest_all_finer_ok", monotone)):
            key_fraction = float(torch.exp2(-lv.double()).mean())
            byte_fraction = float(torch.tensor(per_gaussian, dtype=torch.float64)[lv].mean() / per_gaussian[0])
            row[rule] = {
                "key_fraction": key_fraction,
                "byte_fraction": byte_fraction,
                "projected_mb": byte_fraction * flat_mb if flat_mb is not None else None,
                "level_shares": [float((lv == k).double().mean()) for k in range(levels)],
            }
        memory[name] = {"Q": q, **row}
    out["memory"] = memory
    ratio: Dict[str, Any] = {}
    for lv in range(1, levels):
        r = (err[lv] / err[lv - 1].clamp_min(1e-30)).double()
        ratio[f"l{lv}/l{lv - 1}"] = {
            "quantiles": {str(q): float(r.quantile(q)) for q in (0.01, 0.1, 0.5, 0.9)},
            "share_not_larger": float((r <= 1.0).double().mean()),  # coarser keys, no larger error: a kink or noise
            "share_below_2": float((r < 2.0).double().mean()),  # error grows slower than the spacing (kink-like)
            "share_above_3_5": float((r > 3.5).double().mean()),  # about 4x: a smooth trajectory's h^2
        }
    out["ratio_to_finer"] = ratio
    return out


def run_variant(variant: str, subset: int, seed: int, levels: int, deadline: float) -> Dict[str, Any]:
    record = recorded_table(variant)
    spec = TableSpec(**record["spec"])
    field, means, scale_offset = load_field(EXPORTS / variant)
    if scale_offset != record["info"].get("scale_offset", scale_offset):
        raise ValueError(f"{variant}: config says {scale_offset}, the record {record['info']['scale_offset']}")
    pick = torch.randperm(means.shape[0], generator=torch.Generator().manual_seed(seed))[:subset]
    xyz = means[pick].contiguous()
    n = xyz.shape[0]
    unit = 0.5 * spec.spacing
    grids = [level_grid(spec.intervals, lv) for lv in range(levels + 1)]
    middle = spec.intervals  # the range's middle, t_lo + N h / 2: the base (offsets are stored less it, as `build`)
    needed = sorted(set().union(*grids) | {middle})
    rows = {j: r for r, j in enumerate(needed)}
    cache = torch.empty(len(needed), n, CHANNELS)
    result: Dict[str, Any] = {
        "spec": spec.to_dict(),
        "scale_offset": scale_offset,
        "recorded_info": record["info"],
        "gaussians_total": int(means.shape[0]),
        "subset": n,
        "grid_times": len(needed),
        "field_evaluations": len(needed) * n,
        "levels": {},
    }
    done: set[int] = set()
    sampling: List[Dict[str, Any]] = []
    started = time.perf_counter()
    with torch.no_grad():
        for lv in range(levels + 1):
            new = [j for j in grids[lv] + ([middle] if lv == 0 else []) if j not in done]
            new = sorted(set(new))
            t0 = time.perf_counter()
            for k, d in iter_field_offsets(field, xyz, [spec.t_lo + j * unit for j in new], CHUNK):
                cache[rows[new[k]]] = d
            done.update(new)
            seconds = time.perf_counter() - t0
            sampling.append({"level": lv, "times_needed": len(grids[lv]), "times_new": len(new), "seconds": seconds})
            print(f"{variant} level {lv}: {len(new)} new times in {sampling[-1]['seconds']:.1f} s", flush=True)
            if time.perf_counter() > deadline:
                raise TimeoutError(f"{variant}: past the deadline while sampling level {lv}")
        per_time = sum(s["seconds"] for s in sampling) / max(sum(s["times_new"] for s in sampling), 1)
        for s in sampling:
            s["seconds_alone_estimate"] = s["times_needed"] * per_time  # this level sampled on its own
        cache -= cache[rows[middle]].clone()[None]
        stand_in = GridField(spec.t_lo, unit, rows, cache)
        base = torch.zeros(n, CHANNELS)
        errors: Dict[Order, List[Tensor]] = {o: [] for o in ORDERS}
        for lv in range(levels + 1):
            ls = level_spec(spec, lv)
            t0 = time.perf_counter()

            def interp(order: Order, i: int, f: float, lv: int = lv) -> Tensor:
                keys = cache[[rows[key_grid(lv, i + o)] for o in (-1, 0, 1, 2)]]
                return interpolate(keys, order, 1, f)

            err = midpoint_errors(ls, stand_in, xyz, base, interp, ls.intervals + 1, scale_offset)  # type: ignore[arg-type]
            for o in ORDERS:
                errors[o].append(err[o])
            result["levels"][f"l{lv}"] = {
                "intervals": ls.intervals,
                "spacing": ls.spacing,
                "t_hi_covered": ls.t_hi,
                "error_seconds": time.perf_counter() - t0,
                **sampling[lv],
            }
    result["sampling_seconds"] = sum(s["seconds"] for s in sampling)
    result["seconds"] = time.perf_counter() - started
    flat_mb = record["info"].get("mb")
    result["linear"] = level_tables(errors["linear"], spec, spec.precision, flat_mb)
    result["cubic"] = level_tables(errors["cubic"], spec, spec.precision, flat_mb)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=["garo-compact", "garo-deform", "deform-splatfacto"])
    parser.add_argument("--subset", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--levels", type=int, default=6)
    parser.add_argument("--minutes", type=float, default=68.0, help="stop after this much wall time")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    deadline = time.perf_counter() + 60 * args.minutes
    out: Dict[str, Any] = {
        "question": __doc__.splitlines()[0],
        "git_commit": shell(["git", "-C", str(ROOT), "rev-parse", "HEAD"]),
        "command": "python benchmarks/table_levels.py "
        + f"--variants {' '.join(args.variants)} --subset {args.subset} --seed {args.seed} --levels {args.levels}",
        "subset": args.subset,
        "seed": args.seed,
        "levels": list(range(args.levels + 1)),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "uptime_start": shell(["uptime"]),
        "notes": [
            "errors are of fp32 keys (no int16/int8 rounding), linear is what the recorded tables use; cubic is extra",
            "level l covers [t_lo, t_hi] with whole segments of 2^l h; the last segment's midpoint may lie past t_hi",
            "key_fraction: sum_g 2^-l(g) / n; byte_fraction: table_bytes per Gaussian at each level's intervals",
            "Q 'e0': the bound e_l(g) <= e_0(g) alone; the others: e_l(g) <= max(e_0(g), Q)",
        ],
        "variants": {},
        "missing": [],
    }
    for variant in args.variants:
        if time.perf_counter() > deadline:
            out["missing"].append({"variant": variant, "why": "not started: past the deadline"})
            continue
        print(f"== {variant}", flush=True)
        try:
            out["variants"][variant] = run_variant(variant, args.subset, args.seed, args.levels, deadline)
        except TimeoutError as err:
            out["missing"].append({"variant": variant, "why": str(err)})
        out["uptime_end"] = shell(["uptime"])
        args.out.write_text(json.dumps(out, indent=1))
    out["uptime_end"] = shell(["uptime"])
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
