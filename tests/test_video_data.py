"""`nerfds-data` (the `-real` methods' dataparser) on folders that `ns-process-data video|images` writes.

The folders here are built by hand, in nerfstudio's layout, so that every fact is known: which frames exist,
which have a pose, the order COLMAP lists them in (none in particular). tests/test_video_e2e.py runs the real
tools (ffmpeg, COLMAP) on a rendered video.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np
import pytest
from PIL import Image

import garo_ns.config  # noqa: F401  (registers the methods and installs the plugin's nerfstudio hooks)
from garo_ns.data.nerfds import NerfDSDataParserConfig, load_capture
from garo_ns.data.video import frame_number, read_ply_points
from garo_ns.errors import GaroInputError
from garo_ns.tools.scene import look_at_c2w
from garo_ns.tools.scene_video import path_error

W, H = 24, 16
FOCAL = 20.0


def _pose(k: int) -> np.ndarray:
    """A camera on an arc, looking at the origin (OpenGL camera-to-world), in some arbitrary world frame."""
    a = 0.2 * k
    position = np.array([3 * math.cos(a), 3 * math.sin(a), 1.0 + 0.1 * k]) * 7.0 + [5.0, -2.0, 1.0]
    return look_at_c2w(position, target=(5.0, -2.0, 1.0))


def make_folder(
    root: Path,
    n: int = 10,
    posed: Optional[List[int]] = None,
    names: Optional[Dict[int, str]] = None,
    times: Optional[Dict[int, float]] = None,
    downscales: int = 1,
    seed: int = 0,
) -> Path:
    """An ns-process-data folder: frames 1..n in images/ (and images_2/ ...), poses for `posed` (default: all),
    listed in a shuffled order as COLMAP's output is, with a point cloud."""
    rng = np.random.default_rng(seed)
    posed = list(range(1, n + 1)) if posed is None else posed
    names = names or {}
    for level in range(downscales + 1):
        folder = root / ("images" if level == 0 else f"images_{2**level}")
        folder.mkdir(parents=True, exist_ok=True)
        for k in range(1, n + 1):
            size = (W // 2**level, H // 2**level)
            pixels = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
            Image.fromarray(pixels).save(folder / names.get(k, f"frame_{k:05d}.png"))
    frames = []
    for k in rng.permutation(posed):
        frame = {"file_path": f"images/{names.get(int(k), f'frame_{k:05d}.png')}", "colmap_im_id": int(k)}
        frame["transform_matrix"] = _pose(int(k)).tolist()
        if times is not None:
            frame["time"] = times[int(k)]
        frames.append(frame)
    meta = {"w": W, "h": H, "fl_x": FOCAL, "fl_y": FOCAL, "cx": W / 2, "cy": H / 2, "k1": 0.01, "p2": 0.002}
    meta.update({"camera_model": "OPENCV", "frames": frames, "ply_file_path": "sparse_pc.ply"})
    (root / "transforms.json").write_text(json.dumps(meta))
    # One point at the centre of frame 1's camera, one at the world origin of its frame.
    points = [_pose(1)[:3, 3], np.array([5.0, -2.0, 1.0])]
    lines = ["ply", "format ascii 1.0", "element vertex 2"]
    lines += [f"property float {c}" for c in "xyz"] + [f"property uint8 {c}" for c in ("red", "green", "blue")]
    lines += ["end_header"] + [f"{p[0]:f} {p[1]:f} {p[2]:f} 10 20 30" for p in points]
    (root / "sparse_pc.ply").write_text("\n".join(lines) + "\n")
    return root


def _config(root: Path, **kw) -> NerfDSDataParserConfig:
    return NerfDSDataParserConfig(data=root, **{"downscale_factor": 1, **kw})


def test_times_follow_the_frame_numbers_and_unposed_frames_leave_gaps(tmp_path):
    root = make_folder(tmp_path / "v", n=10, posed=[1, 2, 4, 5, 6, 8, 9, 10])
    capture = load_capture(root, _config(root, eval_every=3))
    # Time is the place in the video (frames 1..10), not the place among the posed frames or in the JSON list.
    assert capture.ids == [f"frame_{k:05d}" for k in (1, 2, 4, 5, 6, 8, 9, 10)]
    assert [capture.times[i] for i in capture.ids] == pytest.approx([(k - 1) / 9 for k in (1, 2, 4, 5, 6, 8, 9, 10)])
    assert capture.unposed == ("frame_00003.png", "frame_00007.png")
    # Every 3rd frame of the video held out (places 1, 4, 7: frames 2, 5, 8), interleaved in time.
    assert capture.splits["val"] == ["frame_00002", "frame_00005", "frame_00008"]
    assert capture.splits["train"] == [i for i in capture.ids if i not in capture.splits["val"]]


def test_outputs_cameras_times_and_the_left_out_count(tmp_path, capsys):
    root = make_folder(tmp_path / "v", n=12, posed=[k for k in range(1, 13) if k != 6])
    parser = _config(root, eval_every=4).setup()
    train, val = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("val")
    said = capsys.readouterr().out
    assert "COLMAP posed 11 of 12 frames" in said and "frame_00006.png" in said
    assert [p.name for p in val.image_filenames] == ["frame_00003.png", "frame_00007.png", "frame_00011.png"]
    assert val.cameras.times[:, 0].tolist() == pytest.approx([2 / 11, 6 / 11, 10 / 11])
    assert len(train.image_filenames) == 8 and bool((train.cameras.times[1:] > train.cameras.times[:-1]).all())
    # The poses are the input ones up to a similarity: nothing reordered, mirrored or bent.
    posed = [k for k in range(1, 13) if k != 6 and k not in (3, 7, 11)]
    error = path_error(np.stack([_pose(k) for k in posed]), train.cameras.camera_to_worlds.double().numpy())
    assert error["position_rms"] < 1e-5 and error["rotation_max_deg"] < 0.05, error  # float32 cameras
    # COLMAP's units by default, as the official D-3DGS code reads a capture: distances between cameras as posed.
    centres = train.cameras.camera_to_worlds[:, :, 3].double().numpy()
    given = np.stack([_pose(k)[:3, 3] for k in posed])
    assert np.linalg.norm(centres[-1] - centres[0]) == pytest.approx(np.linalg.norm(given[-1] - given[0]), rel=1e-5)
    assert float(train.cameras.fx[0]) == FOCAL and float(train.cameras.cx[0]) == W / 2
    assert train.cameras.distortion_params[0].tolist() == pytest.approx([0.01, 0, 0, 0, 0, 0.002])


def test_points_share_the_cameras_frame(tmp_path):
    root = make_folder(tmp_path / "v", n=8)
    out = _config(root).setup().get_dataparser_outputs("train")
    points = out.metadata["points3D_xyz"].double()
    camera_1 = out.cameras.camera_to_worlds[0, :, 3].double()  # frame 1 trains (eval_every 8 holds out frame 5)
    assert float((points[0] - camera_1).abs().max()) < 1e-4
    assert out.metadata["points3D_rgb"].tolist() == [[10, 20, 30]] * 2


@pytest.mark.parametrize("distance", [0.0, 1.0, 4.5])
def test_the_camera_distance_scales_cameras_points_and_extent_together(tmp_path, distance):
    """`camera_distance` sets the scene's scale (0: COLMAP's units): cameras, points and the extent the densification
    thresholds scale with all follow it; orientation and times do not."""
    root = make_folder(tmp_path / "v", n=8)
    colmap = load_capture(root, _config(root, camera_distance=0.0))
    capture = load_capture(root, _config(root, camera_distance=distance))
    ids = capture.splits["train"]
    far = max(float(np.abs(colmap.c2w[cid][:, 3]).max()) for cid in colmap.ids)
    factor = distance / far if distance else 1.0
    assert capture.scale == pytest.approx(factor) and colmap.scale == 1.0 and far > 0
    for cid in ids:
        np.testing.assert_allclose(capture.c2w[cid][:, 3], colmap.c2w[cid][:, 3] * factor, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(capture.c2w[cid][:, :3], colmap.c2w[cid][:, :3])
    np.testing.assert_allclose(capture.points, colmap.points * factor, rtol=1e-5, atol=1e-6)
    assert capture.times == colmap.times
    if distance:
        assert max(float(np.abs(capture.c2w[cid][:, 3]).max()) for cid in capture.ids) == pytest.approx(distance)
    extent = _config(root, camera_distance=distance).setup().get_dataparser_outputs("train").metadata["camera_extent"]
    base = _config(root, camera_distance=0.0).setup().get_dataparser_outputs("train").metadata["camera_extent"]
    assert extent == pytest.approx(base * factor)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_camera_distance_gets_one_line(tmp_path, bad):
    root = make_folder(tmp_path / "v", n=8)
    with pytest.raises(GaroInputError, match="--camera-distance"):
        load_capture(root, _config(root, camera_distance=bad))


def test_downscaled_images_and_intrinsics(tmp_path):
    root = make_folder(tmp_path / "v", n=8, downscales=1)
    out = _config(root, downscale_factor=2).setup().get_dataparser_outputs("train")
    assert out.image_filenames[0].parent.name == "images_2"
    assert float(out.cameras.fx[0]) == FOCAL / 2 and int(out.cameras.width[0]) == W // 2
    with pytest.raises(GaroInputError, match="downscale-factor 1"):
        _config(root, downscale_factor=4).setup().get_dataparser_outputs("train")


def test_a_time_per_frame_overrides_the_numbers(tmp_path):
    # Seconds, not in [0, 1], and against the numbering: the times rule and are rescaled.
    seconds = {k: 30.0 - 2.0 * k for k in range(1, 9)}
    root = make_folder(tmp_path / "v", n=8, times=seconds)
    capture = load_capture(root, _config(root))
    assert capture.ids[0] == "frame_00008" and capture.ids[-1] == "frame_00001"
    assert capture.times["frame_00008"] == 0.0 and capture.times["frame_00001"] == 1.0
    assert capture.times["frame_00004"] == pytest.approx(4 / 7)


@pytest.mark.parametrize(
    "name",
    ["frame_00012.png", "images/frame_00012.jpg", "IMG_2024_0012.JPG", "frame_train_00012.png"],
)
def test_frame_numbers(name):
    assert frame_number(name) == 12


def test_ply_reader_rejects_binary(tmp_path):
    (tmp_path / "p.ply").write_text("ply\nformat binary_little_endian 1.0\nend_header\n")
    with pytest.raises(GaroInputError, match="only ASCII PLY"):
        read_ply_points(tmp_path / "p.ply")


def _no_transforms(root: Path) -> None:
    (root / "transforms.json").unlink()


def _no_frames(root: Path) -> None:
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": []}))


def _poses(value: object, frames: int = 0) -> Callable[[Path], None]:
    """Set the transform_matrix of the first `frames` frames (0: every frame) to `value`."""

    def change(root: Path) -> None:
        meta = json.loads((root / "transforms.json").read_text())
        for frame in meta["frames"][: frames or None]:
            frame["transform_matrix"] = value
        (root / "transforms.json").write_text(json.dumps(meta))

    return change


_no_poses = _poses([[float("nan")] * 4] * 4)  # what a frame without a pose holds


BAD = {
    "COLMAP posed nothing": (lambda r: make_folder(r, n=10), _no_transforms, "COLMAP posed none of the 10 frames"),
    "COLMAP posed too few": (lambda r: make_folder(r, n=10, posed=[1, 2, 5, 9]), None, "posed only 4 of the 10"),
    "no frames": (lambda r: make_folder(r, n=10), _no_frames, "no usable frames"),
    "no usable poses": (lambda r: make_folder(r, n=10), _no_poses, "no usable frames"),
    "a ragged pose": (
        lambda r: make_folder(r, n=10),
        _poses([[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]], 1),
        "transform_matrix must be a 4x4 matrix of numbers",
    ),
    "a pose of strings": (
        lambda r: make_folder(r, n=10),
        _poses([["1", "0", "0", "0"]] * 4, 1),
        "transform_matrix must be a 4x4 matrix of numbers",
    ),
    "unnumbered photos": (
        lambda r: make_folder(r, n=8, names={k: f"photo_{chr(96 + k)}.png" for k in range(1, 9)}),
        None,
        "cannot order the frames in time",
    ),
    "some times": (lambda r: make_folder(r, n=8, times={k: k / 8 for k in range(1, 9)}), None, None),
    "empty folder": (lambda r: r.mkdir(), lambda r: (r / "images").mkdir(), "neither transforms.json"),
}


def _partial_times(root: Path) -> None:
    meta = json.loads((root / "transforms.json").read_text())
    del meta["frames"][3]["time"]
    (root / "transforms.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_folders_get_one_line(tmp_path, case):
    build, breakage, message = BAD[case]
    root = tmp_path / "v"
    build(root)
    if case == "some times":
        breakage, message = _partial_times, "7 of 8 frames have a time"
    if breakage is not None:
        breakage(root)
    with pytest.raises(GaroInputError, match=message) as err:
        _config(root).check_data()
    assert "\n" not in str(err.value)


def test_ns_train_real_reads_a_processed_video_and_stops_cleanly_on_a_bad_one(tmp_path):
    """The user's second command, as typed: the -real method finds the layout itself. A folder whose frames
    COLMAP could not pose stops it with one line, before any run folder is made."""
    root = make_folder(tmp_path / "v", n=10, posed=[1, 2, 5, 9], downscales=1)
    out = tmp_path / "outputs"
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", "garo-deform-real", "--data", str(root)]
    cmd += ["--machine.device-type", "cpu", "--output-dir", str(out), "--vis", "tensorboard"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0, text[-2000:]
    last = [line for line in proc.stderr.splitlines() if line.strip()][-1]
    assert last.startswith("error: ") and "COLMAP posed only 4 of the 10 frames" in last, text[-2000:]
    assert "Traceback" not in text and "Saving config" not in text
    assert not out.exists() or not any(out.rglob("*"))


def test_pose_check_prints_the_counts_and_draws_the_path(tmp_path, capsys):
    from garo_ns.tools.poses import main

    root = make_folder(tmp_path / "v", n=12, posed=[k for k in range(1, 13) if k != 6], downscales=1)
    assert main([str(root), str(tmp_path / "path.png")]) == 0
    said = capsys.readouterr().out
    assert "11 of 12 frames posed (1 left out); 10 train, 1 held out" in said
    assert Image.open(tmp_path / "path.png").width > 300
    (root / "transforms.json").unlink()
    assert main([str(root), str(tmp_path / "bad.png")]) == 1
    assert "COLMAP posed none of the 12 frames" in capsys.readouterr().err


def test_pose_check_never_writes_over_a_file(tmp_path, capsys):
    from garo_ns.tools.poses import main

    root = make_folder(tmp_path / "v", n=12, downscales=1)
    frame = next((root / "images").iterdir())
    before = frame.read_bytes()
    assert main([str(root), str(frame)]) == 1  # a capture's own image
    assert frame.read_bytes() == before and "exists" in capsys.readouterr().err
    assert main([str(root)]) == 0  # the default goes beside the capture, not into the working folder
    assert (root / "camera_path.png").is_file() and not Path("camera_path.png").exists()
    drawn = (root / "camera_path.png").read_bytes()
    assert main([str(root)]) == 1  # and is not replaced by a second check
    assert (root / "camera_path.png").read_bytes() == drawn
    assert not [p for p in root.iterdir() if "partial" in p.name]


@pytest.mark.parametrize("n", [5, 8, 13, 149, 150])
def test_held_out_frames_lie_between_training_frames_in_time(tmp_path, n):
    root = make_folder(tmp_path / "v", n=n, downscales=1)
    capture = load_capture(root, _config(root, eval_every=4 if n < 10 else 8))
    train = [capture.times[i] for i in capture.splits["train"]]
    held = [capture.times[i] for i in capture.splits["val"]]
    assert held and min(train) < min(held) and max(held) < max(train)
    assert sorted(capture.times[i] for i in capture.ids) == [capture.times[i] for i in capture.ids]  # video order


def test_the_flags_the_errors_name_are_flags_ns_train_takes(tmp_path):
    import re

    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from garo_ns.errors import GaroInputError

    root = make_folder(tmp_path / "v", n=6, downscales=0)  # images/ only, no images_2/
    with pytest.raises(GaroInputError) as missing:
        load_capture(root, NerfDSDataParserConfig(data=root))
    with pytest.raises(GaroInputError) as short:
        load_capture(root, NerfDSDataParserConfig(data=root, downscale_factor=1, eval_every=40))
    hints = [re.search(r"`?(nerfds-data --[a-z-]+(?: \d+)?)", str(e.value)).group(1) for e in (missing, short)]
    assert hints[0] == "nerfds-data --downscale-factor 1"
    parsed = tyro.cli(AnnotatedBaseConfigUnion, args=["garo-deform-real", "--data", str(root), *hints[0].split()])
    parser = parsed.pipeline.datamanager.dataparser
    assert parser.downscale_factor == 1
    assert load_capture(root, parser.__class__(data=root, downscale_factor=1)).size == (H, W)
    flag = hints[1].split()[1]
    parsed = tyro.cli(AnnotatedBaseConfigUnion, args=["garo-deform-real", "nerfds-data", flag, "3"])
    assert parsed.pipeline.datamanager.dataparser.eval_every == 3
