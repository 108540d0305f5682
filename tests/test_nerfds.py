"""NeRF-DS / HyperNeRF-layout data: the parser, the built-in scene in that layout, and the real-scene recipe."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
from garo_ns.data.nerfds import NerfDSDataParserConfig, read_capture
from garo_ns.errors import GaroInputError
from garo_ns.tools.scene import SceneSpec, generate_scene

SPEC = SceneSpec(resolution=32, n_train=6, n_val=3, n_test=2, seed=3)


@pytest.fixture(scope="module")
def both_layouts(tmp_path_factory):
    root = tmp_path_factory.mktemp("layouts")
    return generate_scene(root / "dnerf", SPEC), generate_scene(root / "nerfds", SPEC, layout="nerfds")


def _outputs(config, split):
    return config.setup()._generate_dataparser_outputs(split)


def _snapshot(path: Path):
    return sorted((str(p.relative_to(path)), p.stat().st_mtime_ns, p.stat().st_size) for p in path.rglob("*"))


@pytest.mark.parametrize("split", ["train", "val"])
def test_both_layouts_give_the_same_cameras_times_and_images(both_layouts, split):
    import imageio.v2 as imageio

    dnerf, nerfds = both_layouts
    before = _snapshot(nerfds)
    a = _outputs(GaroDNeRFDataParserConfig(data=dnerf, eval_split="val"), split)
    b = _outputs(NerfDSDataParserConfig(data=nerfds, downscale_factor=1), split)
    assert _snapshot(nerfds) == before  # the parser never writes into the data folder
    ca, cb = a.cameras, b.cameras
    # The NeRF-DS layout stores un-normalised positions (scene.json center and scale); the parser
    # must undo that to land on the same frame.
    assert torch.allclose(ca.camera_to_worlds, cb.camera_to_worlds, atol=1e-5)
    for attr in ("fx", "fy", "cx", "cy", "width", "height", "times"):
        assert torch.allclose(getattr(ca, attr).float(), getattr(cb, attr).float(), atol=1e-4), attr
    assert cb.distortion_params is None  # no lens distortion in the built-in scene
    for pa, pb in zip(a.image_filenames, b.image_filenames):
        rgba = imageio.imread(pa).astype(np.float32) / 255
        composited = rgba[..., :3] * rgba[..., 3:]  # on black, as the NeRF-DS layout stores it
        rgb = imageio.imread(pb).astype(np.float32) / 255
        assert np.abs(composited - rgb).max() <= 1.5 / 255


def test_downscale_scales_intrinsics_and_points_are_normalised(both_layouts):
    _, nerfds = both_layouts
    full = _outputs(NerfDSDataParserConfig(data=nerfds, downscale_factor=1), "train")
    half = _outputs(NerfDSDataParserConfig(data=nerfds, downscale_factor=2), "train")
    assert int(half.cameras.width[0]) == SPEC.resolution // 2
    assert torch.allclose(half.cameras.fx, full.cameras.fx / 2)
    assert torch.allclose(half.cameras.cx, full.cameras.cx / 2)
    pts = full.metadata["points3D_xyz"]
    assert pts.shape == (2000, 3)
    # Points were written around the un-normalised frame; normalised, the ground sits at its height.
    from garo_ns.tools.scene import GROUND_Z

    assert torch.isclose(pts[:1000, 2], torch.tensor(GROUND_Z), atol=1e-5).all()
    assert full.metadata["points3D_rgb"].shape == (0, 3)
    assert math.isfinite(full.metadata["camera_extent"]) and full.metadata["camera_extent"] > 0


def test_warp_ids_are_normalised_and_distortion_is_passed(tmp_path, both_layouts):
    _, nerfds = both_layouts
    data = tmp_path / "cap"
    shutil.copytree(nerfds, data)
    meta = json.loads((data / "metadata.json").read_text())
    for entry in meta.values():
        entry.pop("time")
    (data / "metadata.json").write_text(json.dumps(meta))
    cam_file = data / "camera" / "train_001.json"
    cam = json.loads(cam_file.read_text())
    cam["radial_distortion"] = [0.01, -0.002, 0.0]
    cam["tangential_distortion"] = [0.001, 0.0]
    cam["pixel_aspect_ratio"] = 1.1
    cam_file.write_text(json.dumps(cam))
    capture = read_capture(data, downscale=1)
    top = max(e["warp_id"] for e in meta.values())
    for cid, entry in meta.items():
        assert capture.times[cid] == pytest.approx(entry["warp_id"] / top)
    out = _outputs(NerfDSDataParserConfig(data=data, downscale_factor=1), "train")
    dist = out.cameras.distortion_params
    assert dist is not None and torch.allclose(dist[1], torch.tensor([0.01, -0.002, 0.0, 0.0, 0.001, 0.0]))
    assert torch.allclose(dist[0], torch.zeros(6))
    assert out.cameras.fy[1] == pytest.approx(float(out.cameras.fx[1]) * 1.1)


def _broken(tmp_path, source, edit):
    data = tmp_path / "broken"
    if data.exists():
        shutil.rmtree(data)
    shutil.copytree(source, data)
    edit(data)
    return data


def _edit_json(path: Path, fn):
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


BAD_INPUTS = {
    "no dataset.json": (lambda d: (d / "dataset.json").unlink(), "missing dataset file"),
    "dataset.json not JSON": (lambda d: (d / "dataset.json").write_text("{ids"), "not valid JSON"),
    "no camera file": (lambda d: (d / "camera" / "train_002.json").unlink(), "train_002"),
    "id without image": (lambda d: (d / "rgb" / "2x" / "val_001.png").unlink(), "val_001"),
    "time out of range": (
        lambda d: _edit_json(d / "metadata.json", lambda m: m["train_003"].update(time=1.5)),
        "train_003",
    ),
    "no time": (
        lambda d: _edit_json(d / "metadata.json", lambda m: m.__setitem__("train_004", {"camera_id": 0})),
        "train_004",
    ),
    "non-finite camera": (
        lambda d: _edit_json(d / "camera" / "train_005.json", lambda c: c.update(focal_length=float("nan"))),
        "train_005",
    ),
    "not a rotation": (
        lambda d: _edit_json(
            d / "camera" / "val_000.json", lambda c: c.update(orientation=np.eye(3).__mul__(2).tolist())
        ),
        "val_000",
    ),
}


# The file each bad input's line must name (the id, where there is one, is BAD_INPUTS' second entry).
NAMED_FILE = {
    "no dataset.json": "dataset.json",
    "dataset.json not JSON": "dataset.json",
    "no camera file": "camera/train_002.json",
    "id without image": "rgb/2x/val_001.png",
    "time out of range": "metadata.json",
    "no time": "metadata.json",
    "non-finite camera": "camera/train_005.json",
    "not a rotation": "camera/val_000.json",
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_captures_name_the_file_and_id(tmp_path, both_layouts, case):
    edit, expected = BAD_INPUTS[case]
    data = _broken(tmp_path, both_layouts[1], edit)
    before = _snapshot(data)
    with pytest.raises(GaroInputError, match=expected) as err:
        _outputs(NerfDSDataParserConfig(data=data), "train")
    # The very file at fault, by its full path (not merely the capture folder, which every path names).
    assert str(data / NAMED_FILE[case]) in str(err.value), str(err.value)
    assert _snapshot(data) == before


def test_missing_data_directory(tmp_path):
    with pytest.raises(GaroInputError, match="does not exist"):
        read_capture(tmp_path / "nowhere")


@pytest.mark.slow
def test_real_recipe_trains_from_points_on_cpu(tmp_path, both_layouts):
    """The real-scene preset: seeded from points.npy (no .cuda()), 10 time frequencies, time noise."""
    from garo_ns.tools.train import QuickSchedule, make_config, seed_everything

    config = make_config(
        "garo-deform-real",
        both_layouts[1],
        tmp_path,
        schedule=QuickSchedule(steps=30, num_random=500, deform_width=32, deform_depth=2, deform_skip=0),
    )
    model_cfg = config.pipeline.model
    assert model_cfg.deform_time_freqs == 10 and model_cfg.time_noise == 0.1 and not model_cfg.random_init
    assert config.max_num_iterations == 30  # the quick schedule; the preset itself is 20k
    config.set_timestamp()
    seed_everything(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    points = trainer.pipeline.datamanager.train_dataparser_outputs.metadata["points3D_xyz"]
    assert torch.equal(model.means.detach().cpu(), points)  # seeded from points.npy, not random
    trainer.train()
    assert model.deformation.time_freqs == 10
    assert torch.isfinite(model.means).all() and model.step == 29


def test_real_preset_defaults():
    from garo_ns.config import garo_deform_real

    config = garo_deform_real.config
    assert config.max_num_iterations == 20_000
    assert isinstance(config.pipeline.datamanager.dataparser, NerfDSDataParserConfig)
    m = config.pipeline.model
    assert (m.deform_time_freqs, m.time_noise, m.time_noise_steps, m.random_init) == (10, 0.1, 20_000, False)


def test_time_noise_is_annealed_and_off_by_default():
    from garo_ns.deformation import time_noise
    from garo_ns.garo_model import GaroModelConfig

    assert GaroModelConfig().time_noise == 0.0
    config = GaroModelConfig(time_noise=0.1, time_noise_steps=1000)
    frames = 50

    def draw(step: int, training: bool = True) -> float:
        return time_noise(config.time_noise, config.time_noise_steps, step, frames, training)

    torch.manual_seed(0)
    draws = torch.tensor([draw(0) for _ in range(4000)])
    assert draws.std() == pytest.approx(0.1 / 50, rel=0.05)
    half = torch.tensor([draw(500) for _ in range(4000)])
    assert half.std() == pytest.approx(0.05 / 50, rel=0.05)
    assert draw(1000) == 0.0
    assert draw(0, training=False) == 0.0  # renders outside training are never perturbed
