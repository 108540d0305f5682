"""The real-capture dataparser (`nerfds-data`): NeRF-DS / HyperNeRF captures and nerfstudio's processed videos.

A folder with dataset.json is read as NeRF-DS / HyperNeRF (below); one with transforms.json (or the images/
and colmap/ folders that `ns-process-data video|images` leaves) as a video, whose frames' order gives their
times (garo_ns.data.video). Both become the same `Capture`, so the cameras and outputs are built alike.

NeRF-DS / HyperNeRF layout:
Layout (read only; nothing is ever written into the data folder):
  dataset.json      {"ids": [...], "train_ids": [...], "val_ids": [...]}
  metadata.json     {id: {"time": t in [0, 1]} or {"warp_id": k}}; warp ids are normalised by
                    the largest one, as D-3DGS does
  camera/<id>.json  orientation (world-to-camera rotation, OpenCV axes), position (camera centre),
                    focal_length, principal_point, image_size [w, h], pixel_aspect_ratio, skew,
                    radial_distortion [k1, k2, k3], tangential_distortion [p1, p2]
  scene.json        center, scale, near, far: world points map to (p - center) * scale
  rgb/<s>x/<id>.png images downscaled by s (1, 2, 4, ...)
  points.npy        optional [N, 3] world points that seed the Gaussians

Cameras become nerfstudio's (OpenGL axes, camera-to-world) in the normalised frame, with the
intrinsics of the chosen downscale; lens distortion is passed as nerfstudio's distortion
parameters, and nerfstudio's full-image datamanager undistorts the images when it caches them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox

from garo_ns.data.capture import Capture
from garo_ns.data.dnerf import image_size, matrix, number, read_json_object
from garo_ns.data.video import is_nerfstudio_folder, read_video_capture
from garo_ns.errors import GaroInputError
from garo_ns.render.view import camera_extent

# OpenCV camera axes (x right, y down, z forward) to OpenGL's (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


@dataclass
class NerfDSDataParserConfig(DataParserConfig):
    """NeRF-DS / HyperNeRF layout; see the module docstring."""

    _target: Type = field(default_factory=lambda: NerfDSDataParser)
    data: Path = Path("data/nerfds/as")
    """Directory of the capture."""
    downscale_factor: int = 2
    """Read images from rgb/<factor>x/ (D-3DGS uses 2x for NeRF-DS; a video: images_<factor>/, images/ at 1);
    intrinsics are scaled to match."""
    eval_split: Literal["val", "train"] = "val"
    """Which ids the `val`/`test` roles read (captures have train and val ids only)."""
    use_points: bool = True
    """Seed the Gaussians with points.npy (a video: COLMAP's points, sparse_pc.ply) when the capture has it."""
    eval_every: int = 8
    """A video: hold out every n-th frame of the capture order for evaluation (interleaved in time); the rest
    train."""
    min_posed_fraction: float = 0.5
    """A video: stop, rather than train, when COLMAP posed fewer than this share of its frames."""
    camera_distance: float = 0.0
    """A video: scale COLMAP's cameras so that the farthest lies this far from their centre on some axis (0: keep
    COLMAP's units, as the official D-3DGS code does). The field's position encoding and the learning rates are
    absolute, so this scale is part of the recipe. COLMAP's units, with the 700k Gaussian budget, gave held-out frames
    +0.97 dB on cat-pikachu-7 and +0.67 dB on pillow over 1.0 with 200k (docs/data.md)."""

    def check_data(self, data: Optional[Path] = None) -> None:
        """Validate the capture (files, cameras, times, image sizes, points) without loading pixels.

        `ns-train` calls this before it prints or saves its configuration (see `garo_ns.compat`), so a
        bad capture stops with one line and leaves no run folder. Raises GaroInputError.
        """
        root = Path(data if data is not None else self.data)
        capture = load_capture(root, self)
        if not capture.splits[self.eval_split]:
            raise GaroInputError(f"{root / 'dataset.json'}: no {self.eval_split}_ids to evaluate on")
        if self.use_points:
            points_file = root / ("points.npy" if capture.points is None else "sparse_pc.ply")
            check_seed_points(read_points(root, capture), points_file)


def _finite(value: Any, shape: Tuple[int, ...], where: str, name: str) -> np.ndarray:
    arr = matrix(value, shape)
    if arr is None:
        raise GaroInputError(f"{where}: {name} must be finite numbers with shape {shape}, got {value!r}")
    return arr


def load_capture(data: Path, config: "NerfDSDataParserConfig") -> Capture:
    """Read the capture in `data` in whichever layout it has (see the module docstring)."""
    if is_nerfstudio_folder(data):
        return read_video_capture(
            data,
            config.downscale_factor,
            config.eval_every,
            config.min_posed_fraction,
            config.use_points,
            config.camera_distance,
        )
    return read_capture(data, config.downscale_factor)


def read_capture(data: Path, downscale: int = 2) -> Capture:
    """Read and validate a NeRF-DS / HyperNeRF capture; GaroInputError names the file and id."""
    data = Path(data)
    if not data.is_dir():
        raise GaroInputError(f"data directory does not exist: {data}")
    if not isinstance(downscale, int) or downscale < 1:
        raise GaroInputError(f"nerfds-data --downscale-factor must be an int >= 1, got {downscale!r}")
    dataset = read_json_object(data / "dataset.json", "dataset file")
    splits: Dict[str, List[str]] = {}
    for key in ("train_ids", "val_ids"):
        ids = dataset.get(key, [] if key == "val_ids" else None)
        if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
            raise GaroInputError(f"{data / 'dataset.json'}: {key} must be a list of id strings")
        for i in ids:  # an id names files (camera/<id>.json, rgb/<s>x/<id>.png): never a path
            if i in ("", ".", "..") or "/" in i or "\\" in i:
                raise GaroInputError(f"{data / 'dataset.json'}: {key} holds {i!r}, which is not a file name")
        if len(set(ids)) < len(ids):  # an id listed twice would weigh its view double in training or in the scores
            twice = next(i for k, i in enumerate(ids) if i in ids[:k])
            raise GaroInputError(f"{data / 'dataset.json'}: {key} holds {twice!r} twice; list each id once")
        splits[key[: -len("_ids")]] = ids
    if not splits["train"]:
        raise GaroInputError(f"{data / 'dataset.json'}: no train_ids")
    both = [i for i in splits["val"] if i in set(splits["train"])]
    if both:  # a held-out frame that is also trained on would be scored as if unseen
        raise GaroInputError(
            f"{data / 'dataset.json'}: {both[0]!r} is in both train_ids and val_ids; "
            "a held-out id must not be trained on"
        )
    all_ids = list(dict.fromkeys(splits["train"] + splits["val"]))

    scene = read_json_object(data / "scene.json", "scene file")
    where = str(data / "scene.json")
    scale = float(_finite(scene.get("scale", 1.0), (), where, "scale"))
    if scale <= 0:
        raise GaroInputError(f"{where}: scale must be positive, got {scale}")
    center = _finite(scene.get("center", [0.0, 0.0, 0.0]), (3,), where, "center")
    near = float(_finite(scene["near"], (), where, "near")) * scale if "near" in scene else None
    far = float(_finite(scene["far"], (), where, "far")) * scale if "far" in scene else None

    times = _read_times(data / "metadata.json", all_ids)
    c2w, intrinsics, distortion, images = {}, {}, {}, {}
    size: Optional[Tuple[int, int]] = None
    for cid in all_ids:
        cam_path = data / "camera" / f"{cid}.json"
        cam = read_json_object(cam_path, f"camera file of id {cid}")
        where = f"{cam_path} (id {cid})"
        rot = _finite(cam.get("orientation"), (3, 3), where, "orientation")
        if abs(np.linalg.det(rot) - 1.0) > 1e-3:
            raise GaroInputError(f"{where}: orientation is not a rotation (det {np.linalg.det(rot):.4f})")
        pos = _finite(cam.get("position"), (3,), where, "position")
        focal = float(_finite(cam.get("focal_length"), (), where, "focal_length"))
        pp = _finite(cam.get("principal_point"), (2,), where, "principal_point")
        wh = _finite(cam.get("image_size"), (2,), where, "image_size")
        aspect = float(_finite(cam.get("pixel_aspect_ratio", 1.0), (), where, "pixel_aspect_ratio"))
        skew = float(_finite(cam.get("skew", 0.0), (), where, "skew"))
        radial = _finite(cam.get("radial_distortion", [0.0, 0.0, 0.0]), (3,), where, "radial_distortion")
        tangential = _finite(cam.get("tangential_distortion", [0.0, 0.0]), (2,), where, "tangential_distortion")
        if focal <= 0 or aspect <= 0 or (wh <= 0).any():
            raise GaroInputError(f"{where}: focal_length, pixel_aspect_ratio and image_size must be positive")
        if abs(skew) > 1e-6:
            raise GaroInputError(f"{where}: skewed pixels are not supported (skew {skew})")
        image = data / "rgb" / f"{downscale}x" / f"{cid}.png"
        if not image.is_file():
            raise GaroInputError(f"image of id {cid} missing: {image}")
        hw = image_size(image)
        expected = (round(wh[1] / downscale), round(wh[0] / downscale))
        if abs(hw[0] - expected[0]) > 1 or abs(hw[1] - expected[1]) > 1:
            raise GaroInputError(
                f"{image}: image is {hw[1]}x{hw[0]}, camera {cam_path} says {expected[1]}x{expected[0]} at {downscale}x"
            )
        if size is None:
            size = hw
        elif hw != size:
            raise GaroInputError(f"{image}: image is {hw[1]}x{hw[0]}, other images are {size[1]}x{size[0]}")
        pose = np.zeros((3, 4))
        pose[:, :3] = rot.T @ _CV_TO_GL
        pose[:, 3] = (pos - center) * scale
        c2w[cid] = pose
        fx = focal / downscale
        intrinsics[cid] = np.array([fx, fx * aspect, pp[0] / downscale, pp[1] / downscale])
        distortion[cid] = np.concatenate([radial, tangential])
        images[cid] = image
    assert size is not None
    return Capture(all_ids, times, c2w, intrinsics, distortion, images, size, splits, scale, center, near, far)


def _read_times(path: Path, ids: List[str]) -> Dict[str, float]:
    meta = read_json_object(path, "metadata file")
    entries = {}
    for cid in ids:
        entry = meta.get(cid)
        if not isinstance(entry, dict):
            raise GaroInputError(f"{path}: no metadata for id {cid}")
        entries[cid] = entry
    if all("time" in e for e in entries.values()):
        times = {}
        for cid, e in entries.items():
            t = e["time"]
            if not number(t) or not 0.0 <= t <= 1.0:
                raise GaroInputError(f"{path}: time of id {cid} must be a number in [0, 1], got {t!r}")
            times[cid] = float(t)
        return times
    warps = {}
    for cid, e in entries.items():
        w = e.get("warp_id", e.get("time_id"))
        if not isinstance(w, int) or isinstance(w, bool) or w < 0:
            raise GaroInputError(f"{path}: id {cid} needs a time in [0, 1] or a warp_id >= 0, got {e!r}")
        warps[cid] = w
    top = max(warps.values())
    return {cid: (w / top if top > 0 else 0.0) for cid, w in warps.items()}


def capture_cameras(capture: Capture, ids: List[str]) -> Cameras:
    """nerfstudio cameras (with times and distortion parameters) of `ids`."""
    k = np.stack([capture.intrinsics[i] for i in ids])
    dist = np.stack([capture.distortion[i] for i in ids])
    # nerfstudio's order: k1, k2, k3, k4, p1, p2 (OpenCV's model has no k4 here).
    distortion = torch.from_numpy(np.concatenate([dist[:, :3], np.zeros((len(ids), 1)), dist[:, 3:]], -1)).float()
    h, w = capture.size
    return Cameras(
        camera_to_worlds=torch.from_numpy(np.stack([capture.c2w[i] for i in ids])).float(),
        fx=torch.from_numpy(k[:, 0:1]).float(),
        fy=torch.from_numpy(k[:, 1:2]).float(),
        cx=torch.from_numpy(k[:, 2:3]).float(),
        cy=torch.from_numpy(k[:, 3:4]).float(),
        width=w,
        height=h,
        distortion_params=distortion if bool((dist != 0).any()) else None,
        camera_type=CameraType.PERSPECTIVE,
        times=torch.tensor([capture.times[i] for i in ids], dtype=torch.float32)[:, None],
    )


def read_points(data: Path, capture: Capture) -> Optional[np.ndarray]:
    """points.npy (a video: COLMAP's sparse_pc.ply) in the normalised frame [N, 3], or None when absent."""
    if capture.points is not None:
        return capture.points
    path = Path(data) / "points.npy"
    if not path.exists():
        return None
    try:
        pts = np.load(path, allow_pickle=False)
    except Exception as err:
        raise GaroInputError(f"cannot read {path}: {err}") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GaroInputError(f"{path}: points must be an [N, 3] array, got shape {pts.shape}")
    if pts.dtype.kind not in "fiu":
        raise GaroInputError(f"{path}: points must be numbers, got dtype {pts.dtype}")
    pts = pts[np.isfinite(pts).all(-1)]
    return ((pts - capture.center) * capture.scale).astype(np.float32)


def check_seed_points(points: Optional[np.ndarray], path: Path) -> None:
    """GaroInputError for seed points the Gaussians cannot start from: 1 to 3 of them (each takes its size from 3
    neighbours; none means random points)."""
    if points is not None and 0 < len(points) < 4:
        raise GaroInputError(
            f"{path}: {len(points)} seed points; the Gaussians need 4 or more (each takes its size from 3 neighbours): "
            "add points, or start from random ones with nerfds-data --use-points False"
        )


@dataclass
class NerfDSDataParser(DataParser):
    """NeRF-DS / HyperNeRF-layout parser; see the module docstring."""

    config: NerfDSDataParserConfig
    includes_time: bool = True

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Any) -> DataparserOutputs:
        data = Path(self.config.data)
        capture = load_capture(data, self.config)
        if capture.unposed and split == "train":
            total = len(capture.ids) + len(capture.unposed)
            print(
                f"{data}: COLMAP posed {len(capture.ids)} of {total} frames; the {len(capture.unposed)} it could not "
                f"pose are left out ({', '.join(capture.unposed[:5])}{', ...' if len(capture.unposed) > 5 else ''}), "
                "and the times of the others follow the original frame order"
            )
        role = "train" if split == "train" else self.config.eval_split
        ids = capture.splits[role]
        if not ids:
            raise GaroInputError(f"{data / 'dataset.json'}: no {role}_ids to read for the {split} split")
        cameras = capture_cameras(capture, ids)
        train_c2w = np.stack([capture.c2w[i] for i in capture.splits["train"]])
        metadata: Dict[str, Any] = {
            "camera_extent": camera_extent(train_c2w),
            "split": role,
            "ids": ids,
        }
        points = read_points(data, capture) if self.config.use_points else None
        if points is not None and len(points) > 0:
            metadata["points3D_xyz"] = torch.from_numpy(points)
            colors = capture.point_colors
            # Without colours (points.npy has none) the Gaussians start from random ones.
            has_colors = colors is not None and len(colors) == len(points)
            no_colors = torch.zeros((0, 3), dtype=torch.uint8)
            metadata["points3D_rgb"] = torch.from_numpy(colors) if has_colors else no_colors
            lo, hi = points.min(0), points.max(0)
            aabb = torch.from_numpy(np.stack([lo, hi])).float()
        else:
            r = float(np.abs(train_c2w[:, :, 3]).max()) or 1.0
            aabb = torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)
        return DataparserOutputs(
            image_filenames=[capture.images[i] for i in ids],
            cameras=cameras,
            scene_box=SceneBox(aabb=aabb),
            metadata=metadata,
        )
