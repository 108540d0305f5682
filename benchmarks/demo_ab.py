"""A model setting's A/B on the demo's scene and schedule, over seeds: `python benchmarks/demo_ab.py`.

    python benchmarks/demo_ab.py --method deform-splatfacto --set deform_scale_offset=linear --seeds 42 1 2 \\
        --result benchmarks/results/demo_scale_term_cpu.json

Writes the demo's built-in scene (`garo-demo`'s defaults) and trains `--method` on it with the demo's compressed
schedule (the base, as `garo-demo` trains it) and again with `--set` (the arm), once per seed, one run after another
in this process. Keeps each run's test PSNR, SSIM, Gaussians and training seconds, the change per seed and its mean;
the markdown table goes next to the JSON. 42 is the demo's own seed (nerfstudio's default).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from statistics import mean
from typing import Any, Dict, List

from garo_ns.bench.benchmark import environment
from garo_ns.bench.results import utc_stamp, write_with_table
from garo_ns.bench.train_profile import model_overrides
from garo_ns.tools.demo import DemoArgs, demo_config, demo_scene


def train_once(method: str, scene: Path, out: Path, seed: int, overrides: Dict[str, Any], steps: int) -> Dict[str, Any]:
    """One run of the demo's schedule (compressed to `steps`) on the CPU: its test figures and seconds."""
    from garo_ns.tools.eval import evaluate
    from garo_ns.tools.train import train

    config = demo_config(DemoArgs(steps=steps), method, scene, out, "cpu")  # type: ignore[arg-type]
    for name, value in overrides.items():
        setattr(config.pipeline.model, name, value)
    config.machine.seed = seed
    start = time.perf_counter()
    trainer = train(config)
    seconds = time.perf_counter() - start
    scores = evaluate(trainer.pipeline, scene, "test")
    return {
        "seed": seed,
        "psnr": float(scores["psnr"]),
        "ssim": float(scores["ssim"]),
        "gaussians": int(trainer.pipeline.model.num_points),
        "train_seconds": round(seconds, 1),
    }


def markdown(result: Dict[str, Any]) -> str:
    rows = ["| seed | PSNR base / arm | change dB | SSIM base / arm | Gaussians base / arm |", "|---|---|---|---|---|"]
    for b, a in zip(result["base"], result["arm"]):
        rows.append(
            f"| {b['seed']} | {b['psnr']:.2f} / {a['psnr']:.2f} | {a['psnr'] - b['psnr']:+.2f} | "
            f"{b['ssim']:.3f} / {a['ssim']:.3f} | {b['gaussians']:,} / {a['gaussians']:,} |"
        )
    return (
        f"`{result['method']}` on the demo's scene and schedule ({result['steps']} steps, CPU), base as `garo-demo` "
        f"trains it, arm with {', '.join(f'`{k}={v}`' for k, v in result['settings'].items())}:\n\n"
        + "\n".join(rows)
        + f"\n\nMean change over {len(result['base'])} seeds: {result['mean_psnr_change_db']:+.2f} dB.\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="deform-splatfacto", choices=("garo-deform", "deform-splatfacto"))
    parser.add_argument("--set", nargs="+", required=True, metavar="NAME=VALUE", help="the arm's model settings")
    parser.add_argument("--seeds", type=int, nargs="+", default=[42, 1, 2])
    parser.add_argument("--steps", type=int, default=DemoArgs.steps, help="training steps of each run (the demo's)")
    parser.add_argument("--work-dir", type=Path, default=None, help="default: a temporary folder")
    parser.add_argument("--result", type=Path, required=True)
    args = parser.parse_args()
    overrides = model_overrides(args.set)
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="demo_ab_"))
    scene = demo_scene(DemoArgs(), work)
    base: List[Dict[str, Any]] = []
    arm: List[Dict[str, Any]] = []
    load_before = os.getloadavg()
    for seed in args.seeds:
        base.append(train_once(args.method, scene, work / f"base_{seed}", seed, {}, args.steps))
        arm.append(train_once(args.method, scene, work / f"arm_{seed}", seed, overrides, args.steps))
        print(f"seed {seed}: {base[-1]['psnr']:.2f} / {arm[-1]['psnr']:.2f} dB", flush=True)
    result = {
        "date": utc_stamp(),
        "method": args.method,
        "steps": args.steps,
        "settings": {k: str(v) for k, v in overrides.items()},
        "base": base,
        "arm": arm,
        "mean_psnr_change_db": mean(a["psnr"] - b["psnr"] for a, b in zip(arm, base)),
        "environment": environment("cpu"),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
    }
    write_with_table(result, markdown, args.result)


if __name__ == "__main__":
    main()
