"""`garo-demo`: the main job on the embedded default.

Writes the built-in dynamic scene, trains `garo-deform` on it with a compressed schedule (CPU,
or GPU when present), scores the test split and prints where everything is.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

from garo_ns import compat

compat.install()


@dataclass
class DemoArgs:
    """Train garo-deform on the built-in dynamic scene and print its test figures."""

    output_dir: Path = Path("runs/demo")
    """Where the scene, the run and the results go."""
    steps: int = 1000
    """Training steps (the full recipe is 40k; this compresses its phases)."""
    resolution: int = 100
    """Scene resolution in pixels."""
    method: Literal["garo-deform", "deform-splatfacto"] = "garo-deform"
    device: Optional[Literal["cpu", "cuda"]] = None
    """Default: cuda when available."""


def run(args: DemoArgs) -> dict:
    """Generate, train, evaluate; returns the evaluation result."""
    import torch

    from garo_ns.eval import evaluate
    from garo_ns.scene import SceneSpec, generate_scene
    from garo_ns.train import QuickSchedule, make_config, train

    out = args.output_dir.resolve()
    scene = out / f"scene_{args.resolution}px"
    if not (scene / "transforms_test.json").exists():
        generate_scene(scene, SceneSpec(resolution=args.resolution))
        print(f"wrote the built-in scene to {scene}")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    config = make_config(
        args.method, scene, out, device=device, schedule=QuickSchedule(steps=args.steps), experiment_name="demo"
    )
    config.logging.local_writer.enable = True  # show training progress
    config.set_timestamp()
    start = time.perf_counter()
    trainer = train(config)
    seconds = time.perf_counter() - start
    result = evaluate(trainer.pipeline, scene, "test")
    static = trainer.pipeline.model.static_fraction()
    result.update(
        {
            "method": args.method,
            "iterations": args.steps,
            "train_seconds": seconds,
            "device": device,
            "static_fraction": static,
        }
    )
    run_dir = config.get_base_dir()
    (run_dir / "eval_test.json").write_text(json.dumps(result, indent=2))
    print(
        f"\n{args.method} on the built-in scene ({args.resolution}px, {args.steps} steps, {device}, "
        f"{seconds:.0f} s): test PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, "
        f"{result['num_gaussians']} Gaussians"
        + ("" if static is None else f", {static:.0%} of them static (skip the MLP with --pipeline.model.static-skip)")
    )
    print(f"run:      {run_dir}")
    print(f"config:   {run_dir / 'config.yml'}  (ns-viewer --load-config ... --viewer.websocket-host 127.0.0.1)")
    print(f"results:  {run_dir / 'eval_test.json'}")
    return result


def main() -> None:
    """Console entry point."""
    import tyro

    run(tyro.cli(DemoArgs))
