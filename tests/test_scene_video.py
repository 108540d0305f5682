"""The built-in scene filmed as a hand-held video, and the camera path check the end-to-end test relies on."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from garo_ns.tools.scene_video import (
    ROOM_HALF,
    VideoSpec,
    align_similarity,
    camera_path,
    path_error,
    render_video_frame,
    room_texture,
    true_path_file,
    write_video,
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_align_similarity_recovers_a_known_one():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(20, 3))
    rotation, scale, shift = _random_rotation(rng), 3.7, np.array([1.0, -2.0, 0.5])
    s, r, t = align_similarity(source, scale * source @ rotation.T + shift)
    assert s == pytest.approx(scale) and np.allclose(r, rotation) and np.allclose(t, shift)


def test_path_error_is_zero_for_a_similar_path_and_large_for_a_shuffled_one():
    truth = np.stack(camera_path(VideoSpec(frames=30)))
    rng = np.random.default_rng(1)
    rotation = _random_rotation(rng)
    moved = truth.copy()
    moved[:, :3, :3] = rotation @ truth[:, :3, :3]
    moved[:, :3, 3] = 0.3 * truth[:, :3, 3] @ rotation.T + [4.0, 1.0, -2.0]
    error = path_error(truth, moved)
    assert error["position_rms"] < 1e-9 and error["rotation_max_deg"] < 1e-5
    shuffled = path_error(truth, moved[rng.permutation(30)])
    assert shuffled["position_rms"] > 0.1 and shuffled["rotation_mean_deg"] > 1.0


def test_the_camera_moves_slowly_with_parallax_inside_the_room():
    poses = np.stack(camera_path(VideoSpec(frames=60)))
    centres = poses[:, :3, 3]
    assert np.abs(centres[:, :2]).max() < ROOM_HALF
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=-1)
    span = np.linalg.norm(centres[-1] - centres[0])
    assert span > 1.5  # the camera travels (parallax), it does not only turn
    assert steps.max() < 0.1  # and slowly: no jumps between frames
    assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1.0)


def test_frames_show_motion_and_a_texture_without_repeats():
    spec = VideoSpec(width=64, height=48)
    texture = room_texture(0, size=256)
    pose = camera_path(spec)[0]
    early, late = render_video_frame(pose, 0.0, spec, texture), render_video_frame(pose, 1.0, spec, texture)
    assert early.shape == (48, 64, 3) and np.abs(early - late).mean() > 0.01  # the objects moved
    # Texture patches: no two 32-texel tiles alike (features there match one place only).
    tiles = texture[:256, :256].reshape(8, 32, 8, 32, 3).transpose(0, 2, 1, 3, 4).reshape(64, -1)
    distances = np.abs(tiles[:, None] - tiles[None]).mean(-1) + np.eye(64)
    assert distances.min() > 0.01  # a repeated pattern would give 0


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="needs ffmpeg")
def test_write_video_and_its_true_path(tmp_path):
    import json

    import imageio.v3 as iio

    video = write_video(tmp_path / "v.mp4", VideoSpec(frames=5, width=64, height=48))
    frames = iio.imread(video, plugin="pyav")
    assert frames.shape == (5, 48, 64, 3)
    truth = json.loads(true_path_file(video).read_text())
    assert [f["time"] for f in truth["frames"]] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert truth["w"] == 64 and truth["fl_x"] == pytest.approx(VideoSpec(width=64).focal)
