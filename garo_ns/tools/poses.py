"""Check a processed video's camera poses before training: `python -m garo_ns.tools.poses data/mine`.

Reads the folder as the `-real` methods will (garo_ns.data.nerfds), prints how many frames COLMAP posed and how
they split into training and held-out frames, and writes a picture of the camera path (`camera_path.png` in the
capture's folder unless told otherwise; an existing file is never replaced): seen from above and from the side,
coloured by time, held-out frames ringed.
A good capture's path is one smooth curve in time order; jumps, a path folding back on itself or two separate
pieces mean COLMAP went wrong there, and training on it will not fix that.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, List, Optional

import numpy as np

from garo_ns import compat
from garo_ns.errors import GaroError
from garo_ns.tools.files import check_new_file, written_atomically

compat.install()


def path_summary(capture: Any) -> str:
    """One line on a capture's frames: posed, left out, training and held out."""
    total = len(capture.ids) + len(capture.unposed)
    line = f"{len(capture.ids)} of {total} frames posed"
    if capture.unposed:
        line += f" ({len(capture.unposed)} left out)"
    return line + f"; {len(capture.splits['train'])} train, {len(capture.splits['val'])} held out for evaluation"


def plot_camera_path(capture: Any, path: Path) -> Path:
    """Write the camera path picture (from above and from the side, coloured by time) to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = np.stack([capture.c2w[cid][:3, 3] for cid in capture.ids])
    times = np.array([capture.times[cid] for cid in capture.ids])
    held_out = np.array([cid in set(capture.splits["val"]) for cid in capture.ids])
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, (a, b), title in zip(axes, ((0, 1), (0, 2)), ("from above (x, y)", "from the side (x, z)")):
        ax.plot(centres[:, a], centres[:, b], color="0.8", zorder=1)
        dots = ax.scatter(centres[:, a], centres[:, b], c=times, cmap="viridis", s=14, zorder=2)
        ax.scatter(centres[held_out, a], centres[held_out, b], s=60, facecolors="none", edgecolors="red", zorder=3)
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.colorbar(dots, ax=list(axes), label="time")
    fig.suptitle(f"camera path: {path_summary(capture)} (red rings)", fontsize=9)
    with written_atomically(path) as partial:
        fig.savefig(partial, dpi=100, format="png")
    plt.close(fig)
    return path


def main(argv: Optional[List[str]] = None) -> int:
    """`python -m garo_ns.tools.poses DATA [OUTPUT.png]`."""
    from garo_ns.data.nerfds import NerfDSDataParserConfig, load_capture

    args = sys.argv[1:] if argv is None else argv
    if not 1 <= len(args) <= 2:
        print("usage: python -m garo_ns.tools.poses DATA [OUTPUT.png]", file=sys.stderr)
        return 2
    data = Path(args[0])
    output = Path(args[1]) if len(args) == 2 else data / "camera_path.png"
    try:
        check_new_file(output, "OUTPUT")
        capture = load_capture(data, NerfDSDataParserConfig(data=data))
    except GaroError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(path_summary(capture))
    print(f"camera path: {plot_camera_path(capture, output)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
