"""A validating D-NeRF dataparser (`garo-dnerf-data`).

It reads the same layout as nerfstudio's `dnerf-data` and gives the same cameras and times, but
checks the dataset up front and fails with one line naming the file and frame (nerfstudio's
parser fails with `KeyError: 'time'` or deep inside image loading). It also passes to the
model, through `metadata`, the background the images are composited on and the 3DGS camera
extent that scales the densification thresholds.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.colors import get_color

from garo_ns.errors import GaroConfigError, GaroInputError, finite_number
from garo_ns.render.view import camera_extent


@dataclass
class GaroDNeRFDataParserConfig(DataParserConfig):
    """D-NeRF layout: transforms_{split}.json with camera_angle_x and frames carrying
    file_path (without .png), time in [0, 1] and transform_matrix (OpenGL camera-to-world)."""

    _target: Type = field(default_factory=lambda: GaroDNeRFDataParser)
    data: Path = Path("data/dnerf/lego")
    """Directory of the scene."""
    scale_factor: float = 1.0
    """How much to scale the camera origins by."""
    alpha_color: Literal["black", "white"] = "black"
    """Background the RGBA images are composited on; the model renders on the same colour."""
    eval_split: Literal["val", "test"] = "test"
    """Which split the `test` role reads (D-3DGS scores lego on val)."""

    def check_data(self, data: Optional[Path] = None) -> None:
        """Validate the splits training reads (train and `eval_split`) without loading pixels.

        `ns-train` calls this before it prints or saves its configuration (see `garo_ns.compat`), so a
        bad dataset stops with one line and leaves no run folder. Raises GaroInputError.
        """
        # The camera origins are multiplied by it: 0 puts every camera at one point, a negative one mirrors the scene.
        if not finite_number(self.scale_factor) or self.scale_factor <= 0:
            raise GaroConfigError(f"garo-dnerf-data --scale-factor must be a number > 0, got {self.scale_factor!r}")
        root = Path(data if data is not None else self.data)
        read_split(root, "train")
        read_split(root, self.eval_split)


def read_json_object(path: Path, what: str = "transforms file") -> Dict[str, Any]:
    """A JSON object from `path`; GaroInputError naming `what` and the path when missing or malformed."""
    if not path.is_file():
        raise GaroInputError(f"missing {what}: {path}")
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise GaroInputError(f"{what} is not valid JSON: {path} ({err})") from None
    if not isinstance(meta, dict):
        raise GaroInputError(f"{what} must hold a JSON object: {path}")
    return meta


# Pixel formats nerfstudio's image loader takes apart wrong: it reads a palette image's indices as grey levels and
# asserts on two channels. garo-eval reads them right, but training would not.
UNREADABLE_MODES = {
    "P": "palette (indexed-colour)",
    "PA": "palette (indexed-colour)",
    "LA": "grey+alpha",
    "La": "grey+alpha",
}


def image_size(path: Path) -> Tuple[int, int]:
    """(height, width) of an image file; GaroInputError when it cannot be read, is cut short or corrupt.

    The whole file is checked (PIL's `verify`: every chunk and checksum, no pixels decoded), not only
    its header: a truncated image would otherwise pass here and fail later inside nerfstudio's loader.
    """
    from PIL import Image

    if Path(path).exists() and not Path(path).is_file():  # a FIFO would block the read forever
        raise GaroInputError(f"cannot read image {path}: not a regular file")
    try:
        with Image.open(path) as im:
            size = im.size[1], im.size[0]
            mode = im.mode
            im.verify()
    except Exception as err:  # unreadable, truncated or corrupt image
        raise GaroInputError(f"cannot read image {path}: {err}") from None
    if mode in UNREADABLE_MODES:
        raise GaroInputError(
            f"{path}: a {UNREADABLE_MODES[mode]} image, which nerfstudio's loader reads wrong; save it as RGB or RGBA "
            "(e.g. mogrify -type TrueColorAlpha on the frames)"
        )
    return size


def number(value: Any) -> bool:
    """Whether `value` is a finite JSON number (JSON's true and false are not numbers)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def matrix(value: Any, shape: Tuple[int, ...]) -> Optional[np.ndarray]:
    """`value` as a float array of `shape` when it is one (nested lists of finite numbers), else None."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):  # ragged rows, strings, objects
        return None
    if arr.shape != shape or not np.isfinite(arr).all():
        return None
    if not all(number(x) for x in np.asarray(value, dtype=object).reshape(-1)):
        return None  # strings numpy would parse ("1.0") and booleans are not numbers
    return arr


def inside(root: Path, rel: str) -> Optional[Path]:
    """`root / rel` when `rel` is a relative path that stays inside `root`, else None: a dataset names only
    its own files. Checked on the path's text (absolute, or `..` leading out), so folders inside the
    dataset may still be symbolic links to elsewhere."""
    norm = os.path.normpath(rel)
    if os.path.isabs(norm) or norm in (".", "..") or norm.startswith(".." + os.sep):
        return None
    return root / norm


def read_split(data: Path, split: str) -> Tuple[List[Path], np.ndarray, np.ndarray, float, Tuple[int, int]]:
    """Validate and read one split.

    Returns image paths, camera-to-world [F, 4, 4], times [F], camera_angle_x, (height, width).
    Raises GaroInputError naming the file and frame of the first problem found.
    """
    if data.exists() and not data.is_dir():
        raise GaroInputError(f"--data {data} is a file: give the scene's folder (where transforms_train.json is)")
    if not data.is_dir():
        raise GaroInputError(f"data directory does not exist: {data}")
    path = data / f"transforms_{split}.json"
    if not path.exists() and any((data / name).exists() for name in ("transforms.json", "dataset.json")):
        raise GaroInputError(
            f"{data} is a real capture (an ns-process-data folder or a NeRF-DS / HyperNeRF capture), not a D-NeRF "
            "scene: train it with a -real method (ns-train garo-deform-real --data ...)"
        )
    meta = read_json_object(path)
    angle = meta.get("camera_angle_x")
    if not number(angle) or not 0 < angle < math.pi:
        raise GaroInputError(f"{path}: camera_angle_x must be a finite angle in (0, pi), got {angle!r}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise GaroInputError(f"{path}: no frames")
    images, poses, times = [], [], []
    size = None
    for i, frame in enumerate(frames):
        where = f"{path}, frame {i}"
        if not isinstance(frame, dict):
            raise GaroInputError(f"{where}: frame must be an object")
        if "time" not in frame:
            raise GaroInputError(
                f"{where} has no 'time': this method reconstructs dynamic scenes and needs a timestamp per frame"
            )
        t = frame["time"]
        if not number(t) or not 0.0 <= t <= 1.0:
            raise GaroInputError(f"{where}: time must be a number in [0, 1], got {t!r}")
        pose = matrix(frame.get("transform_matrix"), (4, 4))
        if pose is None:
            raise GaroInputError(f"{where}: transform_matrix must be a 4x4 matrix of finite numbers")
        rotation = pose[:3, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
            raise GaroInputError(
                f"{where}: transform_matrix's rotation is not a rotation (det {np.linalg.det(rotation):.4f}; mirrored, "
                "scaled or all zero): a camera-to-world pose has an orthonormal rotation of determinant 1"
            )
        rel = frame.get("file_path")
        if not isinstance(rel, str) or not rel:
            raise GaroInputError(f"{where}: missing file_path")
        image = inside(data, rel)
        if image is None:
            raise GaroInputError(f"{where}: file_path {rel!r} leads outside the data directory")
        if image.suffix.lower() not in (".png", ".jpg", ".jpeg"):  # D-NeRF names its frames without the suffix
            image = image.with_name(image.name + ".png")
        if not image.exists():
            raise GaroInputError(f"{where}: image listed but missing: {image}")
        hw = image_size(image)
        if size is None:
            size = hw
        elif hw != size:
            raise GaroInputError(f"{where}: image {image} is {hw[1]}x{hw[0]}, other frames are {size[1]}x{size[0]}")
        images.append(image)
        poses.append(pose)
        times.append(float(t))
    assert size is not None
    return images, np.stack(poses), np.asarray(times), float(angle), size


def split_cameras(
    poses: np.ndarray, times: np.ndarray, angle: float, height: int, width: int, scale: float = 1.0
) -> Cameras:
    """nerfstudio cameras (with times) of a split read by `read_split`; origins scaled by `scale`."""
    focal = 0.5 * width / math.tan(0.5 * angle)
    c2w = torch.from_numpy(poses[:, :3].astype(np.float32))
    c2w[..., 3] *= scale
    return Cameras(
        camera_to_worlds=c2w,
        fx=focal,
        fy=focal,
        cx=width / 2.0,
        cy=height / 2.0,
        camera_type=CameraType.PERSPECTIVE,
        times=torch.tensor(times, dtype=torch.float32)[:, None],
    )


@dataclass
class GaroDNeRFDataParser(DataParser):
    """Validating D-NeRF parser; see the module docstring."""

    config: GaroDNeRFDataParserConfig
    includes_time: bool = True

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Any) -> DataparserOutputs:
        data = Path(self.config.data)
        file_split = self.config.eval_split if split in ("test", "val") else split
        images, poses, times, angle, (height, width) = read_split(data, file_split)
        cameras = split_cameras(poses, times, angle, height, width, self.config.scale_factor)
        # The extent always comes from the training cameras, whatever split is being read.
        train_poses = poses if file_split == "train" else read_split(data, "train")[1]
        alpha = get_color(self.config.alpha_color)
        return DataparserOutputs(
            image_filenames=images,
            cameras=cameras,
            alpha_color=alpha,
            scene_box=SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], dtype=torch.float32)),
            dataparser_scale=self.config.scale_factor,
            metadata={
                "alpha_color": alpha,
                "camera_extent": camera_extent(train_poses) * self.config.scale_factor,
                "split": file_split,
            },
        )
