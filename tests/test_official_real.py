"""A real capture in the official D-3DGS code's COLMAP layout (benchmarks/official_real.py): our frames, pixels and
held-out split, COLMAP's poses; its scoring (benchmarks/official_score.py) and its place in the summary."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from nerfstudio.data.utils import colmap_parsing_utils as colmap
from test_video_data import _pose, make_folder

import garo_ns.config  # noqa: F401  (registers the methods)
from garo_ns.bench.summary import attach_official


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


official_real = _load("official_real")
official_score = _load("official_score")


def test_names_follow_video_order_and_the_held_out_frames_are_ours():
    times = {"frame_00003": 0.5, "frame_00001": 0.0, "frame_00005": 1.0, "frame_00002": 0.25}
    plan = official_real.frame_plan(list(times), ["frame_00003"], times)
    assert [f["ours"] for f in plan] == ["frame_00001", "frame_00002", "frame_00003", "frame_00005"]
    assert [f["name"] for f in plan] == ["00000", "00001", "00002", "00003"]
    assert [f["split"] for f in plan] == ["train", "train", "test", "train"]
    # the official time is the place over the posed frames; ours kept the gap that frame 4 left
    assert [f["time_official"] for f in plan] == [0.0, 1 / 3, 2 / 3, 1.0]
    assert plan[2]["time_ours"] == 0.5
    with pytest.raises(SystemExit, match="not among the posed"):
        official_real.frame_plan(list(times), ["frame_00004"], times)


def test_the_text_model_reads_back(tmp_path):
    plan = official_real.frame_plan(["a", "b"], ["b"], {"a": 0.0, "b": 1.0})
    q, t = np.array([0.5, 0.5, -0.5, 0.5]), np.array([0.1, -0.2, 0.3])
    (tmp_path / "images.txt").write_text(official_real.images_text(plan, {"a": (q, t), "b": (q, 2 * t)}))
    (tmp_path / "cameras.txt").write_text(official_real.cameras_text(183, 239, 208.5, 178.25, 90.1, 115.9))
    images = colmap.read_images_text(tmp_path / "images.txt")
    assert [im.name for im in images.values()] == ["00000.png", "00001.png"]
    assert np.array_equal(images[1].qvec, q) and np.array_equal(images[2].tvec, 2 * t)
    assert {im.camera_id for im in images.values()} == {1}
    (camera,) = colmap.read_cameras_text(tmp_path / "cameras.txt").values()
    assert (camera.model, camera.width, camera.height) == ("PINHOLE", 183, 239)
    assert list(camera.params) == [208.5, 178.25, 90.1, 115.9]


def _colmap_model(root: Path, posed: list) -> None:
    """colmap/sparse/0 of make_folder's capture: COLMAP's world-to-camera poses (OpenCV axes) of its cameras in
    another world frame (rotated, moved and scaled), as ns-process-data converts them to transforms.json."""
    a = 0.7
    world = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]]) * 0.3
    images = {}
    for k in posed:
        c2w = _pose(k) @ np.diag([1.0, -1.0, -1.0, 1.0])
        rotation, centre = world @ c2w[:3, :3] / 0.3, world @ c2w[:3, 3] + [1.0, 2.0, 3.0]
        w2c_r = rotation.T
        images[k] = colmap.Image(
            k, colmap.rotmat2qvec(w2c_r), -w2c_r @ centre, 1, f"frame_{k:05d}.png", np.zeros((0, 2)), np.zeros(0)
        )
    model = root / "colmap" / "sparse" / "0"
    model.mkdir(parents=True)
    colmap.write_images_binary(images, model / "images.bin")
    point = colmap.Point3D(1, np.zeros(3), np.array([10, 20, 30]), 0.5, np.array([1]), np.array([0]))
    colmap.write_points3D_binary({1: point}, model / "points3D.bin")


def test_prepare_writes_our_pixels_split_and_cameras(tmp_path):
    capture = make_folder(tmp_path / "capture", n=20, posed=list(range(1, 19)), downscales=1)
    _colmap_model(capture, list(range(1, 19)))
    out = tmp_path / "scene"
    m = official_real.prepare(capture, out)

    # our reader's held-out frames (every 8th of the capture order, slot 4: frames 5 and 13), renamed
    assert (out / "test_frames.txt").read_text().split() == ["00004", "00012"]
    assert [f["ours"] for f in m["frames"] if f["split"] == "test"] == ["frame_00005", "frame_00013"]
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{i:05d}.png" for i in range(18)]
    # two unposed frames at the end: the official time (over 18) differs from ours (over 20)
    assert m["time_max_difference"] == pytest.approx(17 / 17 - 17 / 19)
    assert m["pose_agreement"]["max_relative_rotation_deg"] < 0.05  # float32 in our orientation
    assert m["pose_agreement"]["distance_ratio_spread"] == pytest.approx(1.0, abs=1e-5)
    (camera,) = colmap.read_cameras_text(out / "sparse" / "0" / "cameras.txt").values()
    assert camera.model == "PINHOLE" and (camera.width, camera.height) == (m["camera"]["width"], m["camera"]["height"])
    images = colmap.read_images_text(out / "sparse" / "0" / "images.txt")
    assert [im.name for im in images.values()] == [f"{i:05d}.png" for i in range(18)]
    assert (out / "sparse" / "0" / "points3D.bin").is_file()

    # the pixels are our datamanager's cached eval images, byte for byte
    ours, views = official_real.our_views(capture)
    names, gts = official_score.real_test_images(out)
    assert names == ["00004", "00012"]
    for name, gt in zip(names, gts):
        cid = next(f["ours"] for f in m["frames"] if f["name"] == name)
        assert torch.equal(gt, torch.from_numpy(views[cid]["image"]).float() / 255.0)
    assert (gts[0].shape[1], gts[0].shape[0]) == (camera.width, camera.height)


@pytest.mark.parametrize("with_points", [True, False])
def test_a_nerfies_capture_gets_our_cameras_times_and_seed_points(tmp_path, with_points):
    """A Nerfies-layout capture has no COLMAP model: the official layout takes our reader's cameras, our times
    (frame_times.json, read by the official code patched with frame_times) and the points our recipe starts from."""
    from garo_ns.data.nerfds import read_capture
    from garo_ns.engine.initialisation import initial_gaussians
    from garo_ns.tools.scene import SceneSpec, generate_scene

    capture = generate_scene(tmp_path / "capture", SceneSpec(resolution=32, n_train=9, n_val=2, n_test=1), "nerfds")
    if not with_points:
        (capture / "points.npy").unlink()
    out = tmp_path / "scene"
    m = official_real.prepare(capture, out)
    ours = read_capture(capture)
    assert m["layout"] == "nerfies" and m["pose_agreement"] is None
    by_name = {f["name"]: f for f in m["frames"]}
    assert [by_name[n]["ours"] for n in (out / "test_frames.txt").read_text().split()] == ours.splits["val"]
    assert json.loads((out / "frame_times.json").read_text()) == {n: ours.times[f["ours"]] for n, f in by_name.items()}
    # each official camera (world-to-camera, OpenCV axes) is our reader's camera-to-world pose (OpenGL axes)
    for image in colmap.read_images_text(out / "sparse" / "0" / "images.txt").values():
        c2w = ours.c2w[by_name[Path(image.name).stem]["ours"]]
        rotation = colmap.qvec2rotmat(image.qvec)
        assert np.allclose(rotation.T @ np.diag([1.0, -1.0, -1.0]), c2w[:, :3], atol=1e-6)
        assert np.allclose(-rotation.T @ image.tvec, c2w[:, 3], atol=1e-6)
    points = colmap.read_points3D_binary(out / "sparse" / "0" / "points3D.bin")
    xyz = np.stack([p.xyz for p in points.values()])
    if with_points:
        expected = np.load(capture / "points.npy")
        expected = (expected - np.array(json.loads((capture / "scene.json").read_text())["center"])) * ours.scale
    else:
        expected = initial_gaussians(None, False, 100_000, 2.0, 0)["means"].numpy()
    assert xyz.shape == expected.shape and np.allclose(xyz, expected, atol=1e-5)
    assert set(np.stack([p.rgb for p in points.values()]).ravel()) <= {127, 128}  # our start's near grey


def test_prepare_stops_when_colmap_holds_other_frames(tmp_path):
    capture = make_folder(tmp_path / "capture", n=12, downscales=1)
    _colmap_model(capture, list(range(1, 12)))  # frame 12 missing from COLMAP's model
    with pytest.raises(SystemExit, match="COLMAP's frames differ"):
        official_real.prepare(capture, tmp_path / "scene")


class _Echo:
    """A stand-in for the official run: renders the ground truth (plus `shift`) of each held-out frame."""

    real = True

    def __init__(self, names, images, shift=0.0):
        self.names = names
        self.views = [SimpleNamespace(original_image=img.permute(2, 0, 1)) for img in images]
        self.shift = shift

    def frame(self, view):
        return view.original_image + self.shift


def test_real_scores_as_garo_eval(tmp_path):
    from PIL import Image

    from garo_ns.engine.ssim import SSIM

    (tmp_path / "images").mkdir()
    rng = np.random.default_rng(0)
    for name in ("00004", "00012"):
        Image.fromarray(rng.integers(0, 200, (40, 30, 3), dtype=np.uint8)).save(tmp_path / "images" / f"{name}.png")
    (tmp_path / "test_frames.txt").write_text("00004\n00012\n")
    assert official_score.is_real(tmp_path)
    names, images = official_score.real_test_images(tmp_path)
    result = official_score.score(_Echo(names, images, shift=0.01), tmp_path, SSIM(data_range=1.0), None)
    assert result["psnr"] == pytest.approx(40.0, abs=1e-3)  # MSE 1e-4 (no pixel clamped)
    assert result["gt_max_difference"] == 0.0 and result["n_images"] == 2 and result["resolution"] == [30, 40]
    with pytest.raises(SystemExit, match="do not match"):
        official_score.score(_Echo(names[::-1], images), tmp_path, SSIM(data_range=1.0), None)


def test_summary_puts_the_official_run_in_the_capture_row():
    summary = {"rows": [{"scene": "pillow", "split": "val", "deform-splatfacto": {"psnr": 25.0}}]}
    arm = {"psnr": 24.6, "ssim": 0.8, "lpips": 0.2, "fps": 300.0, "num_gaussians": 9, "iterations": 20000}
    official = {"gpu": "NVIDIA H100", "rows": [{"scene": "pillow", "official": {**arm, "split": "val"}}]}
    attach_official(summary, [("official_real_H100.json", official)])
    row = summary["rows"][0]["official"]
    assert row["psnr_gap_db"] == pytest.approx(0.4) and row["source"] == "official_real_H100.json"
    official["rows"][0]["official"]["split"] = "test"
    summary["rows"][0].pop("official")
    with pytest.raises(ValueError, match="scored on test"):
        attach_official(summary, [("x.json", official)])
    assert json.dumps(summary)  # stays JSON


def test_a_run_without_a_recorded_length_is_judged_by_its_kind():
    """cfg_args keeps the model's arguments only: a real capture's run records no --iterations, and scoring it must
    not fail on that (it did), nor call a 20k run of a capture shortened against D-NeRF's 40k."""
    from argparse import Namespace

    real = Namespace(is_blender=False, is_6dof=False, white_background=False)
    dnerf = Namespace(is_blender=True, is_6dof=False, white_background=False)
    assert official_score.run_iterations(real) == 20000
    assert official_score.run_iterations(dnerf) == 40000
    assert official_score.run_iterations(Namespace(is_blender=True, iterations=30000)) == 30000
    assert "20000 iterations" in official_score.train_args(real)
