"""A video or photo sequence processed by nerfstudio (`ns-process-data video|images`), read as a dynamic capture.

Layout (nerfstudio's own; read only):
  transforms.json   fl_x, fl_y, cx, cy, w, h, camera_model and k1, k2, k3, p1, p2 (top level or per frame);
                    frames with file_path (`images/frame_00001.png`), transform_matrix (OpenGL camera-to-world)
                    and, optionally, time; ply_file_path (COLMAP's sparse points)
  images/           every frame extracted, posed or not; images_2/, images_4/, ... the same frames downscaled

Time: nerfstudio keeps no time, so a frame's time is its place in the capture order, normalised to [0, 1]:
the order of the frame numbers in the file names (ns-process-data numbers the frames of a video in order,
and the photos of a folder in the order of their names), counted over every frame in `images/`, so that the
frames COLMAP could not pose leave gaps in time instead of shifting it. A `time` on every frame overrides
this (numbers in [0, 1] are kept, others are rescaled to it). The JSON list's order means nothing (COLMAP
writes its frames in no particular order).

Poses are oriented and centred as nerfstudio's own parser does (average up along +z, centred on the
cameras) and scaled so that the farthest camera lies at distance 1.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from garo_ns.data.capture import Capture
from garo_ns.data.dnerf import image_size, matrix, read_json_object
from garo_ns.errors import GaroInputError

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
_PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
_FILM_AGAIN = (
    "film again with slow, steady camera motion that moves the camera (not only turns it) over a static, "
    "textured background, or re-run ns-process-data with --matching-method exhaustive"
)


def is_nerfstudio_folder(data: Path) -> bool:
    """Whether `data` looks like ns-process-data's output (and not a NeRF-DS / HyperNeRF capture)."""
    data = Path(data)
    if (data / "dataset.json").exists():
        return False
    return any((data / name).exists() for name in ("transforms.json", "images", "colmap"))


def frame_number(file_path: str) -> Optional[int]:
    """The frame number in a file name (its last run of digits: `frame_00012.png` -> 12), or None."""
    digits = re.findall(r"\d+", Path(file_path).stem)
    return int(digits[-1]) if digits else None


def _numbers_4x4(value: Any) -> bool:
    """Whether `value` is 4 rows of 4 JSON numbers (finite or not)."""
    return (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(row, list) and len(row) == 4 for row in value)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for row in value for x in row)
    )


def _number(meta: Dict[str, Any], frame: Dict[str, Any], key: str, where: str) -> Optional[float]:
    value = frame.get(key, meta.get(key))
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise GaroInputError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _intrinsics(meta: Dict[str, Any], frame: Dict[str, Any], where: str) -> Tuple[np.ndarray, np.ndarray, Tuple]:
    """(fx, fy, cx, cy), (k1, k2, k3, p1, p2) and (h, w) of a frame, per frame or shared."""
    values = {}
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        value = _number(meta, frame, key, where)
        if value is None:
            raise GaroInputError(f"{where}: no {key} (neither on the frame nor at the top of the file)")
        values[key] = value
    if min(values.values()) <= 0:
        raise GaroInputError(f"{where}: fl_x, fl_y, cx, cy, w and h must be positive")
    if "distortion_params" in frame or "distortion_params" in meta:
        raise GaroInputError(f"{where}: distortion_params are not supported; give k1, k2, k3, p1, p2")
    dist = [_number(meta, frame, key, where) or 0.0 for key in ("k1", "k2", "k3", "p1", "p2")]
    if _number(meta, frame, "k4", where):
        raise GaroInputError(f"{where}: k4 (a fisheye lens) is not supported")
    k = np.array([values["fl_x"], values["fl_y"], values["cx"], values["cy"]])
    return k, np.array(dist), (int(values["h"]), int(values["w"]))


def _times_from_file(frames: List[Dict[str, Any]], path: Path) -> List[float]:
    times = []
    for i, frame in enumerate(frames):
        t = frame["time"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
            raise GaroInputError(f"{path}, frame {i}: time must be a finite number, got {t!r}")
        times.append(float(t))
    lo, hi = min(times), max(times)
    if lo >= 0.0 and hi <= 1.0:
        return times
    if hi == lo:
        raise GaroInputError(f"{path}: every frame has the same time {lo}: the frames cannot be ordered")
    return [(t - lo) / (hi - lo) for t in times]


def _images_present(folder: Path) -> Dict[int, str]:
    """Frame number -> file name of the images in `folder` (ns-process-data puts every extracted frame there)."""
    if not folder.is_dir():
        return {}
    found = {}
    for image in folder.iterdir():
        number = frame_number(image.name)
        if image.suffix.lower() in _IMAGE_SUFFIXES and number is not None:
            found[number] = image.name
    return found


def read_ply_points(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Positions [N, 3] and colours [N, 3] (uint8) of an ASCII PLY with x y z red green blue per vertex (what
    ns-process-data writes from COLMAP's points)."""
    try:
        with open(path, encoding="ascii") as f:
            header = []
            for line in f:
                header.append(line.strip())
                if line.strip() == "end_header":
                    break
            body = f.read()
    except (OSError, UnicodeDecodeError) as err:
        raise GaroInputError(f"cannot read the point cloud {path}: {err}") from None
    if "format ascii 1.0" not in header or header[-1] != "end_header":
        raise GaroInputError(f"{path}: only ASCII PLY point clouds (as ns-process-data writes them) are read")
    names = [line.split()[-1] for line in header if line.startswith("property")]
    try:
        table = np.array(body.split(), dtype=np.float64).reshape(-1, len(names))
        xyz = table[:, [names.index(c) for c in ("x", "y", "z")]]
        rgb = table[:, [names.index(c) for c in ("red", "green", "blue")]] if "red" in names else np.zeros_like(xyz)
    except ValueError as err:
        raise GaroInputError(f"{path}: malformed point cloud ({err})") from None
    keep = np.isfinite(xyz).all(-1)
    return xyz[keep], rgb[keep].clip(0, 255).astype(np.uint8)


def read_video_capture(
    data: Path,
    downscale: int = 2,
    eval_every: int = 8,
    min_posed_fraction: float = 0.5,
    use_points: bool = True,
    camera_distance: float = 0.0,
) -> Capture:
    """Read and validate an ns-process-data folder as a `Capture` (garo_ns.data.capture) with times, train and val
    frames (every `eval_every`-th frame of the capture order held out) and COLMAP's points, oriented and centred as
    nerfstudio does, then scaled so that the farthest camera lies at `camera_distance` on some axis (0: COLMAP's
    own units, as the official D-3DGS code reads a COLMAP capture).

    GaroInputError, naming the file and frame, for a folder that cannot be trained on: no transforms.json, no
    usable frames, frames that cannot be ordered in time, fewer than `min_posed_fraction` of the frames posed.
    """
    if not isinstance(eval_every, int) or isinstance(eval_every, bool) or eval_every < 2:
        raise GaroInputError(f"nerfds-data --eval-every must be an int >= 2, got {eval_every!r}")
    if not (isinstance(camera_distance, (int, float)) and math.isfinite(camera_distance) and camera_distance >= 0):
        raise GaroInputError(f"nerfds-data --camera-distance must be a finite number >= 0, got {camera_distance!r}")
    data = Path(data)
    path = data / "transforms.json"
    images_dir = data / "images"
    if not path.is_file():
        extracted = len(_images_present(images_dir))
        if extracted:
            raise GaroInputError(
                f"{data}: COLMAP posed none of the {extracted} frames in {images_dir} (ns-process-data wrote no "
                f"transforms.json): {_FILM_AGAIN}"
            )
        raise GaroInputError(
            f"{data} holds neither transforms.json (ns-process-data's output) nor dataset.json (a NeRF-DS / "
            "HyperNeRF capture): run `ns-process-data video --data VIDEO --output-dir FOLDER` first"
        )
    meta = read_json_object(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
        raise GaroInputError(f"{path}: frames must be a list of objects")
    model = meta.get("camera_model", "OPENCV")
    if model not in _PERSPECTIVE_MODELS:
        raise GaroInputError(
            f"{path}: camera_model {model} is not supported; re-run ns-process-data with --camera-type perspective"
        )

    usable, poses, index = [], [], []
    for i, frame in enumerate(frames):
        rel = frame.get("file_path")
        value = frame.get("transform_matrix")
        pose = matrix(value, (4, 4))
        if pose is None and value is not None and not _numbers_4x4(value):  # a broken file, not an unposed frame
            raise GaroInputError(
                f"{path}, frame {i} ({rel}): transform_matrix must be a 4x4 matrix of numbers, got {str(value)[:80]}"
            )
        if not isinstance(rel, str) or not rel or pose is None:
            continue  # a frame without an image or a (finite) pose cannot be used
        usable.append(frame)
        poses.append(pose)
        index.append(i)
    if not usable:
        raise GaroInputError(
            f"{path}: no usable frames (none with a file_path and a finite 4x4 transform_matrix): "
            "re-run ns-process-data on the video"
        )

    # A frame's image names its camera: one listed twice would stand for two cameras (and times) at once.
    first: Dict[str, int] = {}
    for k, frame in enumerate(usable):
        stem = Path(frame["file_path"]).stem
        if stem in first:
            j = first[stem]
            raise GaroInputError(
                f"{path}, frame {index[k]} ({frame['file_path']}): the same image as frame {index[j]} "
                f"({usable[j]['file_path']}); list each frame once"
            )
        first[stem] = k

    # Capture order and time.
    with_time = sum("time" in f for f in usable)
    if 0 < with_time < len(usable):
        raise GaroInputError(f"{path}: {with_time} of {len(usable)} frames have a time: give every frame one, or none")
    names = [Path(f["file_path"]).name for f in usable]
    unposed: List[str] = []
    if with_time:
        times = _times_from_file(usable, path)
        order = sorted(range(len(usable)), key=lambda i: times[i])
        position = {i: rank for rank, i in enumerate(order)}
        total = len(usable)
    else:
        numbers = [frame_number(n) for n in names]
        if None in numbers:
            bad = usable[numbers.index(None)]["file_path"]
            raise GaroInputError(
                f"{path}: cannot order the frames in time: {bad} has no frame number in its name and no frame has "
                "a 'time' (a folder processed for a static scene?); process the video with `ns-process-data "
                "video`, or photos named in capture order with `ns-process-data images`, or add a time per frame"
            )
        if len(set(numbers)) < len(numbers):
            twice = next(n for n in numbers if numbers.count(n) > 1)
            raise GaroInputError(
                f"{path}: cannot order the frames in time: two frames carry the number {twice} "
                f"({', '.join(f['file_path'] for f, n in zip(usable, numbers) if n == twice)}); add a time per frame"
            )
        present = _images_present(images_dir)
        every = sorted(set(numbers) | set(present))
        rank_of = {n: r for r, n in enumerate(every)}
        span = max(len(every) - 1, 1)
        times = [rank_of[n] / span for n in numbers]
        position = {i: rank_of[n] for i, n in enumerate(numbers)}
        unposed = [present[n] for n in every if n not in set(numbers)]
        total = len(every)
    if len(usable) < min_posed_fraction * total or len(usable) < 3:
        raise GaroInputError(
            f"{data}: COLMAP posed only {len(usable)} of the {total} frames (fewer than "
            f"{min_posed_fraction:.0%}; nerfds-data --min-posed-fraction): {_FILM_AGAIN}"
        )

    # Cameras: nerfstudio's orientation and centring, then the farthest camera at `camera_distance`. The field's
    # position encoding and the learning rates are absolute, so the scale chosen here is part of the recipe.
    from nerfstudio.cameras import camera_utils

    oriented, transform = camera_utils.auto_orient_and_center_poses(
        torch.from_numpy(np.stack(poses)).float(), method="up", center_method="poses"
    )
    oriented = oriented.double().numpy()
    scale = camera_distance / max(float(np.abs(oriented[:, :3, 3]).max()), 1e-12) if camera_distance else 1.0
    oriented[:, :3, 3] *= scale

    ids, c2w, intrinsics, distortion, images, time_of, slot = [], {}, {}, {}, {}, {}, {}
    size: Optional[Tuple[int, int]] = None
    for i, frame in enumerate(usable):
        where = f"{path}, frame {index[i]} ({frame['file_path']})"
        k, dist, (h, w) = _intrinsics(meta, frame, where)
        name = Path(frame["file_path"])
        image = data / name if downscale == 1 else data / f"{name.parts[0]}_{downscale}" / name.name
        if not image.is_file():
            hint = (
                "end the ns-train command with `nerfds-data --downscale-factor 1` to read the full-size images"
                if downscale > 1
                else "re-run ns-process-data"
            )
            raise GaroInputError(f"{where}: image missing: {image} ({hint})")
        hw = image_size(image)
        expected = (h / downscale, w / downscale)
        if abs(hw[0] - expected[0]) > 1 or abs(hw[1] - expected[1]) > 1:
            raise GaroInputError(
                f"{image}: image is {hw[1]}x{hw[0]}, {path} says {w}x{h} at full size ({downscale}x downscale)"
            )
        if size is None:
            size = hw
        elif hw != size:
            raise GaroInputError(f"{image}: image is {hw[1]}x{hw[0]}, other frames are {size[1]}x{size[0]}")
        cid = name.stem
        ids.append(cid)
        c2w[cid] = oriented[i, :3, :4]
        intrinsics[cid] = k / downscale
        distortion[cid] = dist
        images[cid] = image
        time_of[cid] = times[i]
        slot[cid] = position[i]
    assert size is not None
    ids.sort(key=lambda cid: time_of[cid])
    # Every eval_every-th frame of the capture order is held out, never the first or last posed one: a held-out
    # frame's time then lies between training times (the field is asked to interpolate, not extrapolate).
    ends = {ids[0], ids[-1]}
    held_out = [cid for cid in ids if slot[cid] % eval_every == eval_every // 2 and cid not in ends]
    train = [cid for cid in ids if cid not in set(held_out)]
    if not held_out or len(train) < 2:
        raise GaroInputError(
            f"{data}: {len(ids)} posed frames leave {len(train)} to train on and {len(held_out)} to evaluate "
            f"(every {eval_every}th held out): film a longer video, or set nerfds-data --eval-every"
        )

    points, colors = None, None
    ply = meta.get("ply_file_path")
    if use_points and isinstance(ply, str) and (data / ply).is_file():
        xyz, colors = read_ply_points(data / ply)
        points = ((xyz @ transform[:, :3].double().numpy().T + transform[:, 3].double().numpy()) * scale).astype(
            np.float32
        )
    return Capture(
        ids=ids,
        times=time_of,
        c2w=c2w,
        intrinsics=intrinsics,
        distortion=distortion,
        images=images,
        size=size,
        splits={"train": train, "val": held_out},
        scale=scale,
        center=np.zeros(3),
        near=None,
        far=None,
        points=points,
        point_colors=colors,
        unposed=tuple(unposed),
    )
