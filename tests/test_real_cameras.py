"""`nerfds-data` on camera files of real captures (tests/data/README.md gives their sources and licences).

The images are synthetic, of the size the camera files state; the cameras nerfstudio ends up with
are checked against the files: intrinsics, time, pose after the scene's centring and scaling, and,
through nerfstudio's own undistortion, where a point seen by the distorted phone camera lands.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import pytest
import torch
from PIL import Image

import garo_ns.config  # noqa: F401  (registers the plugin's methods and dataparsers)
from garo_ns.data.nerfds import NerfDSDataParserConfig

DATA = Path(__file__).parent / "data"
DYCHECK = DATA / "dycheck_paper_windmill"
NERFIES_CAMERA = DATA / "nerfies_readme" / "camera.json"


def _write_images(capture: Path, factor: int, draw=None) -> None:
    """A synthetic image per camera file, at the size the file gives divided by `factor`."""
    out = capture / "rgb" / f"{factor}x"
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for cam_file in sorted((capture / "camera").glob("*.json")):
        w, h = json.loads(cam_file.read_text())["image_size"]
        w, h = round(w / factor), round(h / factor)
        img = (rng.random((h, w, 3)) * 40 + 20).astype(np.float32)
        if draw is not None:
            img = draw(img)
        Image.fromarray(np.clip(img, 0, 255).astype(np.uint8)).save(out / f"{cam_file.stem}.png")


def _camera_file(capture: Path, cid: str) -> Dict:
    return json.loads((capture / "camera" / f"{cid}.json").read_text())


@pytest.fixture()
def windmill(tmp_path: Path) -> Path:
    capture = tmp_path / "paper-windmill"
    shutil.copytree(DYCHECK, capture)
    _write_images(capture, 2)
    return capture


@pytest.mark.parametrize("split", ["train", "val"])
def test_real_iphone_cameras_agree_with_their_files(windmill, split):
    config = NerfDSDataParserConfig(data=windmill, downscale_factor=2, use_points=False)
    out = config.setup().get_dataparser_outputs(split)
    ids = json.loads((windmill / "dataset.json").read_text())[f"{split}_ids"]
    scene = json.loads((windmill / "scene.json").read_text())
    meta = json.loads((windmill / "metadata.json").read_text())
    top = max(e["warp_id"] for e in meta.values())
    cams = out.cameras
    assert len(cams) == len(ids) and cams.distortion_params is None  # dycheck's iPhone frames are undistorted
    for i, cid in enumerate(ids):
        cam = _camera_file(windmill, cid)
        w, h = cam["image_size"]
        assert (int(cams.width[i]), int(cams.height[i])) == (w // 2, h // 2)
        assert float(cams.fx[i]) == pytest.approx(cam["focal_length"] / 2, rel=1e-6)
        assert float(cams.fy[i]) == pytest.approx(cam["focal_length"] * cam["pixel_aspect_ratio"] / 2, rel=1e-6)
        assert float(cams.cx[i]) == pytest.approx(cam["principal_point"][0] / 2, rel=1e-6)
        assert float(cams.cy[i]) == pytest.approx(cam["principal_point"][1] / 2, rel=1e-6)
        assert float(cams.times[i]) == pytest.approx(meta[cid]["warp_id"] / top)
        # A world point in front of the camera, projected with the file's (OpenCV) model, lies on the
        # ray nerfstudio shoots through that pixel, in the scene's centred and scaled coordinates.
        rot, pos = np.asarray(cam["orientation"]), np.asarray(cam["position"])
        local = np.array([0.12, -0.2, 1.0]) * 0.3
        world = pos + rot.T @ local
        u = cam["focal_length"] * local[0] / local[2] + cam["principal_point"][0]
        v = cam["focal_length"] * cam["pixel_aspect_ratio"] * local[1] / local[2] + cam["principal_point"][1]
        coords = torch.tensor([[v / 2, u / 2]], dtype=torch.float32)  # nerfstudio: (y, x), pixel units
        ray = cams[i : i + 1].generate_rays(camera_indices=0, coords=coords)
        target = (world - np.asarray(scene["center"])) * scene["scale"]
        origin, direction = ray.origins[0].double().numpy(), ray.directions[0].double().numpy()
        assert origin == pytest.approx((pos - np.asarray(scene["center"])) * scene["scale"], abs=1e-5)
        to_point = target - origin
        along = float(to_point @ direction)
        assert along > 0
        assert np.linalg.norm(to_point - along * direction) < 1e-4 * np.linalg.norm(to_point)


def _distort(xy: np.ndarray, k: Tuple[float, float, float], p: Tuple[float, float]) -> np.ndarray:
    """OpenCV / Nerfies radial-tangential distortion of normalised image coordinates."""
    x, y = xy
    r2 = x * x + y * y
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    dx = 2 * p[0] * x * y + p[1] * (r2 + 2 * x * x)
    dy = p[0] * (r2 + 2 * y * y) + 2 * p[1] * x * y
    return np.array([x * radial + dx, y * radial + dy])


def test_distorted_phone_camera_goes_through_nerfstudio_undistortion(tmp_path):
    """The Nerfies camera (a real phone calibration with radial and tangential distortion): a dot drawn
    where the distorted camera sees a point lands, after nerfstudio's undistortion, where the undistorted
    camera nerfstudio reports projects that point."""
    from garo_ns.config import garo_deform_real

    capture = tmp_path / "phone"
    (capture / "camera").mkdir(parents=True)
    shutil.copy(NERFIES_CAMERA, capture / "camera" / "a.json")
    shutil.copy(NERFIES_CAMERA, capture / "camera" / "b.json")  # the held-out view: same camera, another id
    cam = json.loads(NERFIES_CAMERA.read_text())
    (capture / "dataset.json").write_text(json.dumps({"ids": ["a", "b"], "train_ids": ["a"], "val_ids": ["b"]}))
    (capture / "metadata.json").write_text(json.dumps({"a": {"warp_id": 0}, "b": {"warp_id": 1}}))
    (capture / "scene.json").write_text(json.dumps({"center": [0.0, 0.0, 0.0], "scale": 0.0387}))
    factor = 8
    k, p = cam["radial_distortion"], cam["tangential_distortion"]
    point = np.array([0.3, 0.385])  # normalised coordinates where this lens distorts most (about 2 px here)
    f = cam["focal_length"] / factor
    pp = np.asarray(cam["principal_point"]) / factor
    seen = f * _distort(point, k, p) + pp  # pixel coordinates, pixel centres at +0.5 (as Nerfies)

    def dot(img: np.ndarray) -> np.ndarray:
        yy, xx = np.mgrid[: img.shape[0], : img.shape[1]] + 0.5
        blob = np.exp(-((xx - seen[0]) ** 2 + (yy - seen[1]) ** 2) / (2 * 1.5**2))
        return img * 0 + 200 * blob[..., None]

    _write_images(capture, factor, draw=dot)

    config = copy.deepcopy(garo_deform_real.config)
    config.pipeline.datamanager.dataparser = NerfDSDataParserConfig(data=capture, downscale_factor=factor)
    parsed = config.pipeline.datamanager.dataparser.setup().get_dataparser_outputs("train").cameras
    assert parsed.distortion_params is not None
    assert parsed.distortion_params[0].tolist() == pytest.approx([k[0], k[1], k[2], 0.0, p[0], p[1]])
    dm = config.pipeline.datamanager.setup(device="cpu", test_mode="val")
    cams = dm.train_dataset.cameras
    image = dm.cached_train[0]["image"].float().numpy()
    assert image.shape[:2] == (int(cams.height[0]), int(cams.width[0]))
    yy, xx = np.mgrid[: image.shape[0], : image.shape[1]] + 0.5
    weight = np.clip(image[..., 0] - 0.3 * image[..., 0].max(), 0, None)
    found = np.array([(weight * xx).sum(), (weight * yy).sum()]) / weight.sum()
    fx, fy, cx, cy = (float(v[0]) for v in (cams.fx, cams.fy, cams.cx, cams.cy))
    expected = np.array([fx * point[0] + cx, fy * point[1] + cy])
    assert np.linalg.norm(found - expected) < 0.75, (found, expected)
    # Without the distortion the dot would sit elsewhere: the check can tell.
    assert np.linalg.norm(seen - (f * point + pp)) > 1.5
