"""A strip of views over time: the ground truth above each model's renders, views left to right by time (the
demo's `demo_strip.png`; the benchmark saves such views on the GPU machine and draws its strips from them,
garo_ns.bench.strip).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np
import torch


def spread(count: int, total: int) -> List[int]:
    """`count` indices of `total` items in order, evenly spread and including the first and last (all when fewer)."""
    if total <= 0 or count <= 0:
        return []
    if count >= total:
        return list(range(total))
    if count == 1:
        return [total // 2]
    return sorted({round(k * (total - 1) / (count - 1)) for k in range(count)})


@torch.no_grad()
def views_over_time(
    pipeline: Any, scene: Path, split: str, count: int
) -> Tuple[List[int], List[float], List[torch.Tensor], List[torch.Tensor]]:
    """`count` views of `split` spread over time (`spread`), in time order: their indices, times, ground truths and
    renders [H, W, 3] in [0, 1], on the CPU."""
    from garo_ns.tools.eval import split_views

    model = pipeline.model
    model.eval()
    cameras, images = split_views(pipeline, scene, split)
    times = cameras.times.reshape(-1).tolist() if cameras.times is not None else [0.0] * len(images)
    order = sorted(range(len(images)), key=lambda i: times[i])
    picked = [order[k] for k in spread(count, len(order))]
    renders = [
        model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))["rgb"].clamp(0, 1).cpu() for i in picked
    ]
    return picked, [float(times[i]) for i in picked], [images[i] for i in picked], renders


def draw_strip(
    rows: Sequence[Tuple[str, Sequence[Any]]], times: Sequence[Optional[float]], output: Path, title: str = "", dpi=100
) -> Path:
    """A PNG: a row of images per (label, images), the ground truth's first, each column titled by its view's time
    (where known)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = len(times)
    fig, axes = plt.subplots(len(rows), cols, figsize=(1.8 * cols + 1.2, 1.9 * len(rows)), squeeze=False)
    for r, (label, images) in enumerate(rows):
        for c, image in enumerate(images):
            ax = axes[r][c]
            ax.imshow(np.asarray(image))
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0 and times[c] is not None:
                ax.set_title(f"t = {times[c]:.2f}", fontsize=9)
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=dpi)
    plt.close(fig)
    return Path(output)
