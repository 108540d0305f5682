"""What removing the least important Gaussians of a finished model costs, on the guard's training views and on
the test views, without fine-tuning: `python benchmarks/removal_curve.py`.

`garo-compact` decides each round from the worst of its training guard views (the test split is never read while
training). This measures, on a trained run (a benchmark export), how that training-view cost relates to the
test-view cost of the same removal, over a range of shares: the least important Gaussians by compaction's own
score (blending weight summed over the training views, times volume^beta), or by the largest weight in any one
view, are left out of the render; nothing is retrained.
A removal measured this way costs at least what it costs with the fine-tuning compaction trains in between.
Runs on a CPU (the reference rasterizer) in minutes for a model of some 30k Gaussians at 800x800.

    python benchmarks/removal_curve.py --scene data/dnerf/jumpingjacks --export EXPORT \
        --output benchmarks/results/removal_curve_jumpingjacks_garo-oaa.json
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch

from garo_ns import compat
from garo_ns.bench import transfer
from garo_ns.compaction.guard import TrainingViewGuard, psnr, spread_indices
from garo_ns.compaction.importance import importance
from garo_ns.redundancy.select import lowest
from garo_ns.render.contribution import view_contribution

SHARES = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5)


def view_psnrs(model: Any, guard: TrainingViewGuard, truths: List[torch.Tensor], without: Optional[torch.Tensor]):
    """PSNR [V] of each of the guard's views (the trained field, every Gaussian but `without`)."""
    return torch.tensor(
        [psnr(guard.render(model, i, without=without), gt.to(model.device)) for i, gt in enumerate(truths)],
        dtype=torch.float64,
    )


def contributions(model: Any, cameras: Any) -> Dict[str, torch.Tensor]:
    """Each Gaussian's blending weight over `cameras` (each at its own time): summed over the views (compaction's
    score, LightGaussian's) and the largest of any one view (which keeps a Gaussian that matters to a few frames
    only, as the moving parts of a dynamic scene do)."""
    total = torch.zeros(model.num_points, device=model.device)
    largest = torch.zeros_like(total)
    for i in range(cameras.shape[0]):
        view = model.camera_view(cameras[i : i + 1].to(model.device))
        weight = view_contribution(
            *model.gaussians_at(view.time, exact=True)[:4],
            view.viewmat,
            view.K,
            view.width,
            view.height,
            model.config.rasterizer,
        )
        total += weight
        largest = torch.maximum(largest, weight)
    return {"sum": total, "max": largest}


def costs(plain: torch.Tensor, without: torch.Tensor) -> Dict[str, Any]:
    """Mean and worst view PSNR loss in dB, each view's loss, and the loss of the views' pooled PSNR (from their
    mean squared error), which weighs every pixel alike instead of every view."""
    loss = plain - without
    pooled = 10.0 * torch.log10(torch.mean(10.0 ** (-without / 10.0)) / torch.mean(10.0 ** (-plain / 10.0)))
    return {
        "mean_db": float(loss.mean()),
        "worst_db": float(loss.max()),
        "pooled_db": float(pooled),
        "per_view_db": [round(float(v), 5) for v in loss],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--export", type=Path, required=True, help="a benchmark export (--export-dir)")
    parser.add_argument("--guard-views", type=int, default=16, help="training views judged (compaction's default)")
    parser.add_argument("--score-views", type=int, default=200, help="training views the score sums over")
    parser.add_argument("--shares", type=float, nargs="+", default=list(SHARES))
    parser.add_argument(
        "--scores",
        nargs="+",
        choices=("sum", "max"),
        default=["sum", "max"],
        help="the blending weight a Gaussian is ranked by: summed over the views (compaction's) or its largest",
    )
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    compat.install()
    from garo_ns.tools.eval import load_run, load_split

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        record = transfer.import_run(args.export, Path(work), args.scene)
        _, pipeline, _, step = load_run(Path(record["config"]))
        model = pipeline.model.eval()
        out: Dict[str, Any] = {
            "scene": args.scene.name,
            "variant": record["variant"],
            "step": step,
            "num_gaussians": int(model.means.shape[0]),
            "trained_in": record.get("trained_in"),
            "volume_beta": model.config.compact_volume_beta,
            "guard_views": args.guard_views,
            "rows": [],
        }
        with torch.no_grad():
            train_cams, train_truths = load_split(args.scene, "train", model.background_color)
            test_cams, test_truths = load_split(args.scene, "test", model.background_color)
            scored = spread_indices(train_cams.times, len(train_truths), args.score_views)
            out["score_views"] = len(scored)
            weights = contributions(model, train_cams[torch.tensor(scored)])
            picked = spread_indices(train_cams.times, len(train_truths), args.guard_views)
            guard = TrainingViewGuard(cameras=train_cams, images=[], indices=picked)
            tests = TrainingViewGuard(cameras=test_cams, images=[], indices=list(range(len(test_truths))))
            guard_truths = [train_truths[i] for i in picked]
            plain_guard = view_psnrs(model, guard, guard_truths, None)
            plain_test = view_psnrs(model, tests, test_truths, None)
            out["plain_guard_psnr"] = float(plain_guard.mean())
            out["plain_test_psnr"] = float(plain_test.mean())
            out["plain_guard_psnr_per_view"] = [round(float(v), 4) for v in plain_guard]
            out["plain_test_psnr_per_view"] = [round(float(v), 4) for v in plain_test]
            for kind, share in ((kind, share) for kind in args.scores for share in args.shares):
                count = int(share * out["num_gaussians"])
                mask = lowest(importance(weights[kind], model.scales, out["volume_beta"]), count)
                row = {
                    "score": kind,
                    "share": share,
                    "removed": count,
                    "guard": costs(plain_guard, view_psnrs(model, guard, guard_truths, mask)),
                    "test": costs(plain_test, view_psnrs(model, tests, test_truths, mask)),
                }
                out["rows"].append(row)
                g, t = row["guard"], row["test"]
                print(
                    f"{kind} {share:.0%}: guard worst {g['worst_db']:.3f} mean {g['mean_db']:.3f} pooled "
                    f"{g['pooled_db']:.3f} dB; test mean {t['mean_db']:.3f} worst {t['worst_db']:.3f} pooled "
                    f"{t['pooled_db']:.3f} dB",
                    flush=True,
                )
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    out.update(
        seconds=time.perf_counter() - start,
        cpu=platform.processor() or platform.machine(),
        torch=torch.__version__,
        commit=commit,
    )
    args.output.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
