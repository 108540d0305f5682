"""`garo-camera-path`: a camera path that sweeps time, for `ns-render camera-path`.

nerfstudio renders a dynamic scene over time only from a camera-path file whose keyframes carry
`render_time` (its `interpolate` and `spiral` renders carry no time). This writes such a file,
one entry per frame, in one of two ways:

* a sweep (the default): the camera starts at a training view of the run, optionally orbits the
  scene's up axis, and time goes linearly from `start_time` to `end_time`;
* `--along-capture`: the training cameras in time order, each at its own frame's time, moved sideways
  by `--shift` (a fraction of their distance from the scene's centre): what a user sees on leaving the
  captured path a little, where a real capture has no views to fit.

    garo-camera-path --load-config RUN/config.yml --output time_sweep.json
    ns-render camera-path --load-config RUN/config.yml --camera-path-filename time_sweep.json \
        --output-path renders/time_sweep.mp4
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Sequence

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
    poses, times = [], []
    for i in range(frames):
        s = i / (frames - 1) if frames > 1 else 0.0
        rot = rotation_about(up, math.radians(orbit_degrees) * s)
        pose = np.eye(4)
        pose[:3, :3] = rot @ c2w[:3, :3]
        pose[:3, 3] = rot @ c2w[:3, 3]
        poses.append(pose)
        times.append(start_time + (end_time - start_time) * s)
    return path_dict(poses, times, fy, width, height, seconds)


def along_capture(
    c2w: np.ndarray,
    times: np.ndarray,
    fy: float,
    width: int,
    height: int,
    frames: int,
    seconds: float,
    shift: float = 0.0,
) -> Dict[str, Any]:
    """A nerfstudio camera-path dict that follows the captured cameras `c2w` [N, 3, 4] in the order of their
    `times` [N], each entry at its camera's time: every camera when `frames` >= N, else `frames` of them evenly
    spaced in time. Each camera moves `shift` times its distance from the origin (the scene's centre, where the
    readers put it) along its own right axis: 0 is the captured path itself."""
    if frames < 1:
        raise GaroInputError(f"frames must be >= 1, got {frames}")
    if not seconds > 0:
        raise GaroInputError(f"seconds must be > 0, got {seconds}")
    if not math.isfinite(shift):
        raise GaroInputError(f"shift must be a finite number, got {shift}")
    order = np.argsort(times, kind="stable")
    if frames < len(order):
        order = order[np.round(np.linspace(0, len(order) - 1, frames)).astype(int)]
    poses = []
    for i in order:
        pose = np.eye(4)
        pose[:3] = c2w[i]
        # nerfstudio's camera-to-world columns are right, up, back: the first moves the camera sideways.
        pose[:3, 3] += shift * np.linalg.norm(c2w[i, :3, 3]) * c2w[i, :3, 0] / np.linalg.norm(c2w[i, :3, 0])
        poses.append(pose)
    return path_dict(poses, [float(times[i]) for i in order], fy, width, height, seconds)


def path_dict(
    poses: Sequence[np.ndarray], times: Sequence[float], fy: float, width: int, height: int, seconds: float
) -> Dict[str, Any]:
    """nerfstudio's camera-path file of camera-to-world `poses` [4, 4] at `times`, with one field of view."""
    fov = math.degrees(2 * math.atan(0.5 * height / fy))  # vertical, as the viewer writes it
    entries = [
        {"camera_to_world": pose.reshape(-1).tolist(), "fov": fov, "aspect": width / height, "render_time": t}
        for pose, t in zip(poses, times)
    ]
    return {
        "camera_type": "perspective",
        "render_height": int(height),
        "render_width": int(width),
        "seconds": float(seconds),
        "camera_path": entries,
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
    along_capture: bool = False
    """Follow the training cameras in time order, each at its frame's time (`--frames` of them at most), instead of
    sweeping from one view (`camera-index`, `orbit-degrees`, `start-time` and `end-time` are then unused)."""
    shift: float = 0.0
    """With `--along-capture`: move each camera sideways by this fraction of its distance from the scene's centre
    (0.05 leaves the captured path a little; 0 renders the captured views' poses)."""


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
    if args.along_capture:
        if cams.times is None:
            raise GaroInputError(f"{args.load_config}: the run's training cameras carry no times to follow")
        times = cams.times.reshape(-1).numpy().astype(np.float64)
        path = along_capture(
            c2w,
            times,
            float(cams.fy[0]),
            int(cams.width[0]),
            int(cams.height[0]),
            args.frames,
            args.seconds,
            args.shift,
        )
        write_path(args.output, path)
        entries = path["camera_path"]
        print(
            f"wrote {args.output}: {len(entries)} captured views in time order, shifted {args.shift:g} of their "
            f"distance, time {entries[0]['render_time']:.3f} -> {entries[-1]['render_time']:.3f}"
        )
        return
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
    write_path(args.output, path)
    print(f"wrote {args.output}: {args.frames} frames, time {args.start_time} -> {args.end_time}")


def write_path(output: Path, path: Dict[str, Any]) -> None:
    """Write the camera-path file whole or not at all."""
    output.parent.mkdir(parents=True, exist_ok=True)
    with written_atomically(output) as partial:
        partial.write_text(json.dumps(path, indent=1))


if __name__ == "__main__":
    main()
