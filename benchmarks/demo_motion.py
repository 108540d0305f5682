"""Where the demo's error lies: one arm trained on variants of the built-in scene and schedule, scored on the
ball's, the box's and the rest's pixels (floor and background) of the training and test views.

The scene is analytic, so each object's pixel coverage is known exactly (`render_frame(..., parts=...)`): a
pixel belongs to the ball or the box where that object alone covers more than 1% of it. Comparing the training
views' scores across variants separates what the field does not learn (low on training views too) from what
does not carry to new views (low on test views only). Each variant trains in its own single-thread process,
`--jobs` at a time, with the demo's own code path (`garo_ns.tools.demo.train_arm`).

    python benchmarks/demo_motion.py --out /tmp/demo_motion --result benchmarks/results/demo_motion_cpu.json
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

TURNING = {"box_turns": 0.5, "box_slide": 0.0, "ball_turns": 1.25}  # the library's default motions
VARIANTS: Dict[str, Dict[str, Any]] = {
    "turning, 32 px": {**TURNING, "resolution": 32},
    "turning, 32 px, 6x128 field": {
        **TURNING,
        "resolution": 32,
        "deform_width": 128,
        "deform_depth": 6,
        "deform_skip": 3,
    },
    "turning, 32 px, static warm-up 5%": {**TURNING, "resolution": 32, "deform_warmup_frac": 0.05},
    "turning, 48 px": {**TURNING, "resolution": 48},
    "demo motions, 32 px": {"resolution": 32},
    "demo motions, 48 px (the demo)": {},
}


def split_scores(model: Any, scene: Path, split: str, spec: Any) -> Dict[str, float]:
    """PSNR of `split` (mean over views) and on the ball's, the box's and the rest's pixels (pooled), with
    each part's share of the pixels and of the squared error."""
    import numpy as np
    import torch

    from garo_ns.data.dnerf import read_split
    from garo_ns.tools.eval import load_split
    from garo_ns.tools.scene import render_frame

    motion = {"box_turns": spec.box_turns, "box_slide": spec.box_slide, "ball_turns": spec.ball_turns}
    cameras, images = load_split(scene, split, model.background_color)
    _, poses, times, _, (height, _) = read_split(scene, split)
    error = {"ball": 0.0, "box": 0.0, "rest": 0.0}
    pixels = dict(error)
    psnrs = []
    with torch.no_grad():
        for i, gt in enumerate(images):
            pred = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))["rgb"].clamp(0, 1).cpu()
            sq = ((pred - gt) ** 2).sum(-1).numpy()
            psnrs.append(-10 * math.log10(max(sq.mean() / 3, 1e-12)))
            cover = {
                part: render_frame(poses[i], float(times[i]), height, parts=(part,), **motion)[..., 3] > 0.01
                for part in ("ball", "box")
            }
            masks = {**cover, "rest": ~(cover["ball"] | cover["box"])}
            for part, mask in masks.items():
                error[part] += float(sq[mask].sum())
                pixels[part] += float(mask.sum())
    total_error, total_pixels = sum(error.values()), sum(pixels.values())
    out: Dict[str, float] = {"psnr": float(np.mean(psnrs))}
    for part in error:
        out[f"{part}_psnr"] = -10 * math.log10(max(error[part] / (3 * max(pixels[part], 1.0)), 1e-12))
        out[f"{part}_pixel_share"] = pixels[part] / total_pixels
        out[f"{part}_error_share"] = error[part] / total_error
    return out


def run_variant(job: Tuple[str, Dict[str, Any], Path, int, str]) -> Dict[str, Any]:
    """Train one variant in this (spawned) process and score it."""
    name, overrides, out, steps, method = job
    import torch

    from garo_ns.tools.demo import DemoArgs, scene_spec, train_arm
    from garo_ns.tools.eval import load_run
    from garo_ns.tools.scene import generate_scene

    torch.set_num_threads(1)
    slug = "".join(c if c.isalnum() else "_" for c in name)
    args = DemoArgs(output_dir=out / slug, steps=steps, **overrides)
    spec = scene_spec(args)
    scene = args.output_dir / "scene"
    if not (scene / "transforms_test.json").exists():
        generate_scene(scene, spec)
    start = time.perf_counter()
    result = train_arm(args, method, scene, args.output_dir, "cpu")
    seconds = time.perf_counter() - start
    _, pipeline, _, _ = load_run(Path(result["config"]))
    model = pipeline.model
    model.eval()
    return {
        "variant": name,
        "overrides": overrides,
        "method": method,
        "steps": steps,
        "seconds": seconds,
        "num_gaussians": result["num_gaussians"],
        "train": split_scores(model, scene, "train", spec),
        "test": split_scores(model, scene, "test", spec),
    }


def table(rows: List[Dict[str, Any]]) -> str:
    """Markdown: test PSNR, and the training views' PSNR on the ball, the box and the rest."""
    lines = [
        "| variant | test PSNR | train PSNR | train ball | train box | train rest | test ball | test box |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        tr, te = r["train"], r["test"]
        lines.append(
            f"| {r['variant']} | {te['psnr']:.2f} | {tr['psnr']:.2f} | {tr['ball_psnr']:.1f} | {tr['box_psnr']:.1f} "
            f"| {tr['rest_psnr']:.1f} | {te['ball_psnr']:.1f} | {te['box_psnr']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="work directory (scenes and runs)")
    parser.add_argument("--result", type=Path, required=True, help="where to write the result JSON")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--method", default="garo-deform", choices=["garo-deform", "deform-splatfacto"])
    parser.add_argument("--jobs", type=int, default=2, help="variants trained at once, one core each")
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), help="names of VARIANTS (default: all)")
    a = parser.parse_args()
    jobs = [(name, VARIANTS[name], a.out.resolve(), a.steps, a.method) for name in a.variants]
    with multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
        rows = pool.map(run_variant, jobs, chunksize=1)
    a.result.parent.mkdir(parents=True, exist_ok=True)
    a.result.write_text(json.dumps({"steps": a.steps, "method": a.method, "variants": rows}, indent=2) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main()
