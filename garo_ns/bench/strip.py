"""A strip of held-out frames: the ground truth above each method's render, views left to right by time.

The benchmark (`--renders-dir DIR`) saves the views on the GPU machine, one folder per variant (`save_views`); the
strip is drawn here from those PNGs, so that it needs neither the models nor a GPU:

    python -m garo_ns.bench.strip DIR docs/images/real_pillow_strip.png --title "pillow, held-out frames" \\
        --variants deform-splatfacto-real garo-deform-real garo-compact-real
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, List, Sequence

import numpy as np

GROUND_TRUTH = "ground-truth"


def spread(count: int, total: int) -> List[int]:
    """`count` indices of `total` items in order, evenly spread and including the first and last (all when fewer)."""
    if total <= 0 or count <= 0:
        return []
    if count >= total:
        return list(range(total))
    if count == 1:
        return [total // 2]
    return sorted({round(k * (total - 1) / (count - 1)) for k in range(count)})


def save_views(pipeline: Any, scene: Path, split: str, out_dir: Path, variant: str, count: int = 5) -> List[Path]:
    """Render `count` views of `split` spread over time and write them as `out_dir/variant/<index>.png`, with the
    ground truth in `out_dir/ground-truth/` (written once) and each view's time in `views.json`."""
    import imageio.v2 as imageio
    import torch

    from garo_ns.tools.eval import split_views

    model = pipeline.model
    model.eval()
    cameras, images = split_views(pipeline, scene, split)
    times = cameras.times.reshape(-1).tolist() if cameras.times is not None else [0.0] * len(images)
    order = sorted(range(len(images)), key=lambda i: times[i])
    picked = [order[k] for k in spread(count, len(order))]
    written: List[Path] = []
    for folder in (out_dir / variant, out_dir / GROUND_TRUTH):
        folder.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        for i in picked:
            out = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))
            render = (out["rgb"].clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
            path = out_dir / variant / f"{i:04d}.png"
            imageio.imwrite(path, render)
            written.append(path)
            truth = out_dir / GROUND_TRUTH / f"{i:04d}.png"
            if not truth.exists():
                imageio.imwrite(truth, (images[i].clamp(0, 1).numpy() * 255).round().astype(np.uint8))
    (out_dir / "views.json").write_text(json.dumps({f"{i:04d}": float(times[i]) for i in picked}, indent=1))
    return written


def draw_strip(renders_dir: Path, output: Path, variants: Sequence[str], title: str = "") -> Path:
    """A PNG: the ground truth's views in the first row and each variant's below, columns by time. A variant
    without a folder is left out; the views are those every row has."""
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(GROUND_TRUTH, "ground truth")] + [(v, v) for v in variants if (renders_dir / v).is_dir()]
    views = sorted(set.intersection(*(set(p.stem for p in (renders_dir / r).glob("*.png")) for r, _ in rows)))
    if len(rows) < 2 or not views:
        raise SystemExit(f"{renders_dir}: no views shared by the ground truth and a variant")
    times_file = renders_dir / "views.json"
    times = json.loads(times_file.read_text()) if times_file.exists() else {}
    fig, axes = plt.subplots(len(rows), len(views), figsize=(1.9 * len(views) + 1.3, 2.0 * len(rows)), squeeze=False)
    for r, (folder, label) in enumerate(rows):
        for c, view in enumerate(views):
            ax = axes[r][c]
            ax.imshow(imageio.imread(renders_dir / folder / f"{view}.png"))
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0 and view in times:
                ax.set_title(f"t = {times[view]:.2f}", fontsize=9)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=90)
    plt.close(fig)
    return output


def main() -> None:
    """Command line (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("renders_dir", type=Path)
    parser.add_argument("output", type=Path)
    parser.add_argument("--variants", nargs="+", required=True)
    parser.add_argument("--title", default="")
    args = parser.parse_args()
    if args.output.exists():
        raise SystemExit(f"{args.output} exists; name a new file")
    print(f"wrote {draw_strip(args.renders_dir, args.output, args.variants, args.title)}")


if __name__ == "__main__":
    main()
