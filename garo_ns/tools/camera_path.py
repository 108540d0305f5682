"""`garo-camera-path`: a camera path that sweeps time, for `ns-render camera-path`.

nerfstudio renders a dynamic scene over time only from a camera-path file whose keyframes carry
`render_time` (its `interpolate` and `spiral` renders carry no time). This writes such a file,
one entry per frame: the camera starts at a training view of the run, optionally orbits the
scene's up axis, and time goes linearly from `start_time` to `end_time`. Then:

    garo-camera-path --load-config RUN/config.yml --output time_sweep.json
    ns-render camera-path --load-config RUN/config.yml --camera-path-filename time_sweep.json \
        --output-path renders/time_sweep.mp4
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict

import numpy as np

from garo_ns import compat
from garo_ns.errors import GaroInputError
from garo_ns.tools.eval import scene_dir
from garo_ns.tools.files import check_new_file, written_atomically

compat.install()


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by `angle` radians about the unit vector `axis` (Rodrigues)."""
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def time_sweep(
    c2w: np.ndarray,
    up: np.ndarray,
    fy: float,
    width: int,
    height: int,
    frames: int,
    seconds: float,
    orbit_degrees: float = 0.0,
    start_time: float = 0.0,
    end_time: float = 1.0,
) -> Dict[str, Any]:
    """A nerfstudio camera-path dict of `frames` views from camera-to-world `c2w` [3, 4], orbiting
    `up` through the origin by `orbit_degrees` in all, with render_time from start to end."""
    if frames < 1:
        raise GaroInputError(f"frames must be >= 1, got {frames}")
    if not seconds > 0:
        raise GaroInputError(f"seconds must be > 0, got {seconds}")
    for name, t in (("start_time", start_time), ("end_time", end_time)):
        if not (math.isfinite(t) and 0.0 <= t <= 1.0):
            raise GaroInputError(f"{name} must be in [0, 1], got {t}")
    fov = math.degrees(2 * math.atan(0.5 * height / fy))  # vertical, as the viewer writes it
    path = []
    for i in range(frames):
        s = i / (frames - 1) if frames > 1 else 0.0
        rot = rotation_about(up, math.radians(orbit_degrees) * s)
        pose = np.eye(4)
        pose[:3, :3] = rot @ c2w[:3, :3]
        pose[:3, 3] = rot @ c2w[:3, 3]
        path.append(
            {
                "camera_to_world": pose.reshape(-1).tolist(),
                "fov": fov,
                "aspect": width / height,
                "render_time": start_time + (end_time - start_time) * s,
            }
        )
    return {
        "camera_type": "perspective",
        "render_height": int(height),
        "render_width": int(width),
        "seconds": float(seconds),
        "camera_path": path,
    }


@dataclass
class CameraPathArgs:
    """Write a camera path that sweeps time (for `ns-render camera-path`)."""

    load_config: Path
    """config.yml of the trained run (its training cameras give the start view and intrinsics)."""
    output: Path = Path("time_sweep.json")
    camera_index: int = 0
    """Training camera to start from."""
    frames: int = 48
    seconds: float = 2.0
    orbit_degrees: float = 0.0
    """Orbit this far about the scene's up axis (the mean up vector of the training cameras)."""
    start_time: float = 0.0
    end_time: float = 1.0


def main() -> None:
    """Console entry point."""
    import tyro
    import yaml

    args = tyro.cli(CameraPathArgs)
    if not args.load_config.is_file():
        raise GaroInputError(f"run config not found: {args.load_config}")
    check_new_file(args.output, "--output", overwrite=True)
    config = yaml.load(args.load_config.read_text(), Loader=yaml.Loader)
    # The scene the run trained on: ns-train's --data lands on the datamanager, not on the dataparser.
    dataparser = config.pipeline.datamanager.dataparser
    dataparser.data = scene_dir(config)
    outputs = dataparser.setup().get_dataparser_outputs("train")
    cams = outputs.cameras
    if not 0 <= args.camera_index < len(cams):
        raise GaroInputError(f"camera_index must be in 0..{len(cams) - 1}, got {args.camera_index}")
    c2w = cams.camera_to_worlds.numpy().astype(np.float64)
    up = c2w[:, :3, 1].mean(0)
    i = args.camera_index
    path = time_sweep(
        c2w[i],
        up,
        float(cams.fy[i]),
        int(cams.width[i]),
        int(cams.height[i]),
        args.frames,
        args.seconds,
        args.orbit_degrees,
        args.start_time,
        args.end_time,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with written_atomically(args.output) as partial:
        partial.write_text(json.dumps(path, indent=1))
    print(f"wrote {args.output}: {args.frames} frames, time {args.start_time} -> {args.end_time}")


if __name__ == "__main__":
    main()
