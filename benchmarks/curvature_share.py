"""How many Gaussians of a trained model GARO's curvature gate would call flat: `python benchmarks/curvature_share.py`.

GARO removes an activity candidate only if its curvature c_i (the mean of 1 - |n_i . n_j| over its K nearest
neighbours) is below tau_curvature. Normals pointing every which way give c = 0.5 on average (|cos| of random
directions is uniform on [0, 1]), so tau = 0.5 passes every Gaussian whose neighbourhood is more aligned than
random. This reads the curvature of every Gaussian of trained runs (benchmark exports) at a few training times,
with the normals carried through the deformation as GARO's step does, and writes the share under tau and the
quantiles.

    python benchmarks/curvature_share.py --scene data/dnerf/jumpingjacks --exports EXPORT... \
        --output benchmarks/results/curvature_share_jumpingjacks_cpu.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any, Dict, List

import torch

from garo_ns import compat
from garo_ns.bench import transfer
from garo_ns.data.dnerf import read_split
from garo_ns.redundancy.curvature import curvature
from garo_ns.redundancy.normals import normals

QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)


def curvature_stats(c: torch.Tensor, tau: float) -> Dict[str, Any]:
    """Share of finite curvatures under `tau`, their mean and quantiles."""
    c = c[torch.isfinite(c)].double()
    q = torch.quantile(c, torch.tensor(QUANTILES, dtype=torch.float64)) if c.numel() else None
    return {
        "count": int(c.numel()),
        "share_under_tau": float((c < tau).double().mean()) if c.numel() else None,
        "mean": float(c.mean()) if c.numel() else None,
        "quantiles": {str(p): float(v) for p, v in zip(QUANTILES, q)} if q is not None else {},
    }


def model_curvature(model: Any, times: List[float], tau: float, k: int) -> Dict[str, Any]:
    """Curvature of every Gaussian of `model` at each time (the field as trained, fp32)."""
    out = {}
    log_scales = model.scales.detach()
    with torch.no_grad():
        for t in times:
            splats = model.gaussians_at(t, exact=True)
            unit = normals(splats.quats, torch.exp(log_scales))
            ids = torch.arange(splats.means.shape[0], device=splats.means.device)
            out[f"{t:.3f}"] = curvature_stats(curvature(splats.means, unit, ids, k), tau)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--exports", type=Path, nargs="+", required=True, help="benchmark exports (--export-dir)")
    parser.add_argument("--times", type=int, default=5, help="training times, spread over the split")
    parser.add_argument("--tau", type=float, default=0.5)
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    compat.install()
    from garo_ns.tools.eval import load_run

    times = sorted(set(float(t) for t in read_split(args.scene, "train")[2]))
    picked = [times[round(i * (len(times) - 1) / max(args.times - 1, 1))] for i in range(args.times)]
    result: Dict[str, Any] = {"scene": args.scene.name, "tau_curvature": args.tau, "k": args.k, "runs": {}}
    with tempfile.TemporaryDirectory() as work:
        for export in args.exports:
            record = transfer.import_run(export, Path(work), args.scene)
            _, pipeline, _, step = load_run(Path(record["config"]))
            model = pipeline.model.eval()
            result["runs"][record["variant"]] = {
                "step": step,
                "num_gaussians": int(model.means.shape[0]),
                "trained_in": record.get("trained_in"),
                "by_time": model_curvature(model, picked, args.tau, args.k),
            }
            shares = [s["share_under_tau"] for s in result["runs"][record["variant"]]["by_time"].values()]
            print(f"{record['variant']}: share under tau {min(shares):.3f} to {max(shares):.3f}")
    args.output.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
