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

from garo_ns.tools import strip

GROUND_TRUTH = "ground-truth"


def _png(image: Any) -> np.ndarray:
    """An image [H, W, 3] in [0, 1] as 8-bit pixels."""
    return (image.clamp(0, 1).numpy() * 255).round().astype(np.uint8)


def save_views(pipeline: Any, scene: Path, split: str, out_dir: Path, variant: str, count: int = 5) -> List[Path]:
    """Render `count` views of `split` spread over time (garo_ns.tools.strip.views_over_time) and write them as
    `out_dir/variant/<index>.png`, with the ground truth in `out_dir/ground-truth/` (written once) and each view's
    time in `views.json`."""
    import imageio.v2 as imageio

    picked, times, truths, renders = strip.views_over_time(pipeline, scene, split, count)
    written: List[Path] = []
    for folder in (out_dir / variant, out_dir / GROUND_TRUTH):
        folder.mkdir(parents=True, exist_ok=True)
    for i, truth, render in zip(picked, truths, renders):
        path = out_dir / variant / f"{i:04d}.png"
        imageio.imwrite(path, _png(render))
        written.append(path)
        if not (out_dir / GROUND_TRUTH / f"{i:04d}.png").exists():
            imageio.imwrite(out_dir / GROUND_TRUTH / f"{i:04d}.png", _png(truth))
    (out_dir / "views.json").write_text(json.dumps({f"{i:04d}": t for i, t in zip(picked, times)}, indent=1))
    return written


def draw_strip(renders_dir: Path, output: Path, variants: Sequence[str], title: str = "") -> Path:
    """A PNG (garo_ns.tools.strip.draw_strip): the ground truth's views in the first row and each variant's below,
    columns by time. A variant without a folder is left out; the views are those every row has."""
    import imageio.v2 as imageio

    rows = [(GROUND_TRUTH, "ground truth")] + [(v, v) for v in variants if (renders_dir / v).is_dir()]
    views = sorted(set.intersection(*(set(p.stem for p in (renders_dir / r).glob("*.png")) for r, _ in rows)))
    if len(rows) < 2 or not views:
        raise SystemExit(f"{renders_dir}: no views shared by the ground truth and a variant")
    times_file = renders_dir / "views.json"
    times = json.loads(times_file.read_text()) if times_file.exists() else {}
    images = [(label, [imageio.imread(renders_dir / folder / f"{v}.png") for v in views]) for folder, label in rows]
    return strip.draw_strip(images, [times.get(v) for v in views], output, title, dpi=90)


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
