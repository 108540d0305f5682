"""CPU render time of a trained demo run with the pure-torch reference rasterizer.

    python benchmarks/cpu_render.py --config runs/demo/garo-deform/garo-deform/config.yml \
        --output benchmarks/results/cpu_render.json [--threads 1] [--repeats 5] [--note "..."]

Times every test view of the run's scene, each `repeats` times after one warm-up pass:
* `render_ms`: `model.render` without autograd (deformation MLP + rasterization, what the demo's
  render ms/view reports, `garo_ns.bench.timing`);
* `raster_ms` / `raster_train_ms`: the rasterizer alone on the Gaussians at the view's time, forward
  only / forward and backward of a loss on the image (what a training step pays for rendering).
Per view the median over repeats, then the mean over views (a shared machine's stalls hit single
repeats; the median leaves them out). The JSON names the Gaussian count, torch's threads, the CPU and
the load averages before and after (a load above the CPU count means the cores were shared).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path
from typing import Callable, List

import torch

from garo_ns.render.backend import rasterize
from garo_ns.tools.eval import load_run, load_split, scene_dir


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of `fn` in ms over `repeats` calls."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1000.0 * (time.perf_counter() - t0))
    return statistics.median(times)


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo (platform's answer elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=Path("runs/demo/garo-deform/garo-deform/config.yml"))
    p.add_argument("--output", type=Path, default=Path("benchmarks/results/cpu_render.json"))
    p.add_argument("--threads", type=int, default=1, help="torch threads (the demo trains with one per arm)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--note", default="")
    args = p.parse_args()

    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    config, pipeline, _, step = load_run(args.config)
    model = pipeline.model
    model.eval()
    if model.device.type != "cpu":
        raise SystemExit("this benchmark times the CPU path; the run loaded onto " + str(model.device))
    cameras, _ = load_split(scene_dir(config), "test", model.background_color)
    views = [model.camera_view(cameras[i : i + 1]) for i in range(len(cameras))]
    background = model.background_color[None]
    degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)

    def raster(view, splats, train: bool) -> None:
        leaves = [t.detach().requires_grad_(train) for t in splats[:5]]
        with torch.set_grad_enabled(train):
            img, alpha, _ = rasterize(*leaves, view.viewmat, view.K, view.width, view.height, sh_degree=degree)
            if train:
                (img.square().sum() + alpha.sum()).backward()

    render_ms: List[float] = []
    raster_ms: List[float] = []
    train_ms: List[float] = []
    for view in views:
        with torch.no_grad():
            model.render(view, backgrounds=background)  # warm-up
            splats = model.gaussians_at(view.time, exact=True)
            render_ms.append(median_ms(lambda: model.render(view, backgrounds=background), args.repeats))
        raster(view, splats, True)
        raster_ms.append(median_ms(lambda: raster(view, splats, False), args.repeats))
        train_ms.append(median_ms(lambda: raster(view, splats, True), args.repeats))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    result = {
        "config": str(args.config),
        "step": step,
        "num_gaussians": model.num_points,
        "resolution": [views[0].height, views[0].width],
        "views": len(views),
        "repeats": args.repeats,
        "render_ms": statistics.mean(render_ms),
        "raster_ms": statistics.mean(raster_ms),
        "raster_train_ms": statistics.mean(train_ms),
        "render_ms_per_view": render_ms,
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "commit": commit,
        "note": args.note,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if not k.endswith("per_view")}, indent=2))


if __name__ == "__main__":
    main()
