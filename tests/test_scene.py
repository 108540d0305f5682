"""The built-in procedural scene: deterministic, analytic, and readable by nerfstudio."""

from __future__ import annotations

import json

import numpy as np
import pytest

from garo_ns.tools.scene import SceneSpec, generate_scene, look_at_c2w, render_frame
from garo_ns.tools.scene_objects import BOX_CENTER_XY, box_center, sphere_center


def test_deterministic_from_seed(tmp_path):
    spec = SceneSpec(resolution=24, n_train=3, n_val=1, n_test=1, seed=7)
    a, b = generate_scene(tmp_path / "a", spec), generate_scene(tmp_path / "b", spec)
    for split in ("train", "val", "test"):
        assert (a / f"transforms_{split}.json").read_text() == (b / f"transforms_{split}.json").read_text()
    assert (a / "train" / "r_001.png").read_bytes() == (b / "train" / "r_001.png").read_bytes()
    c = generate_scene(tmp_path / "c", SceneSpec(resolution=24, n_train=3, n_val=1, n_test=1, seed=8))
    assert (a / "transforms_val.json").read_text() != (c / "transforms_val.json").read_text()


def test_layout_times_and_moving_content(tmp_path):
    root = generate_scene(tmp_path / "s", SceneSpec(resolution=32, n_train=5, n_val=2, n_test=2))
    meta = json.loads((root / "transforms_train.json").read_text())
    times = [f["time"] for f in meta["frames"]]
    assert times[0] == 0.0 and times[-1] == 1.0 and all(0 <= t <= 1 for t in times)
    assert not meta["frames"][0]["file_path"].endswith(".png")
    # Same camera, two times: the sphere moved, so the images differ; the ground did not.
    c2w = look_at_c2w(np.array([0.0, -4.0, 2.0]))
    early, late = render_frame(c2w, 0.0, 48), render_frame(c2w, 1.0, 48)
    assert np.abs(early - late).mean() > 0.01
    assert not np.allclose(sphere_center(0.0), sphere_center(1.0))
    assert early[..., 3].max() == 1.0 and early[..., 3].min() == 0.0  # object pixels and transparent background


def test_loads_with_nerfstudio_dnerf_parser(tmp_path):
    from nerfstudio.data.dataparsers.dnerf_dataparser import DNeRFDataParserConfig

    root = generate_scene(tmp_path / "s", SceneSpec(resolution=16, n_train=4, n_val=2, n_test=3))
    parser = DNeRFDataParserConfig(data=root).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert len(train.image_filenames) == 4 and len(test.image_filenames) == 3
    assert train.cameras.times is not None and float(train.cameras.times.max()) == 1.0
    assert int(train.cameras.width[0]) == 16


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"n_train": 0}, "n_train"),
        ({"n_val": -1}, "n_val"),
        ({"resolution": 0}, "resolution"),
        ({"resolution": 12.5}, "resolution"),
        ({"checks_per_unit": 0.0}, "checks_per_unit"),
        ({"sphere_stripes": 3}, "sphere_stripes"),
        ({"box_slide": -0.1}, "box_slide"),
        ({"box_slide": 2.0}, "box_slide"),
        ({"box_turns": float("nan")}, "box_turns"),
        ({"ball_turns": "1"}, "ball_turns"),
    ],
)
def test_bad_arguments_name_the_argument(tmp_path, kwargs, name):
    with pytest.raises(ValueError, match=name):
        generate_scene(tmp_path / "x", SceneSpec(**kwargs))
    assert not (tmp_path / "x").exists()


def test_coarser_textures_change_only_the_textures():
    """The demo's coarser floor and ball: same geometry and coverage, fewer colour edges."""
    c2w = look_at_c2w(np.array([0.0, -4.0, 2.0]))
    fine, coarse = render_frame(c2w, 0.3, 48), render_frame(c2w, 0.3, 48, checks_per_unit=2 / 2.4, sphere_stripes=2)
    assert np.array_equal(fine[..., 3], coarse[..., 3])
    assert np.array_equal(render_frame(c2w, 0.3, 48), render_frame(c2w, 0.3, 48, 2, 4.0, 8))  # defaults

    def edges(img):
        return np.abs(np.diff(img[..., :3], axis=1)).sum()

    assert edges(coarse) < 0.7 * edges(fine)


def test_motion_settings_turn_or_slide_the_box_and_fix_the_stripes():
    """Defaults: the box turns in place and the stripes turn; the demo's motion: the box slides without
    turning and the ball carries its stripes without turning them; the floor is the same in both."""
    c2w = look_at_c2w(np.array([0.0, -4.0, 2.0]))
    default = render_frame(c2w, 0.3, 48)
    assert np.array_equal(default, render_frame(c2w, 0.3, 48, box_turns=0.5, box_slide=0.0, ball_turns=1.25))
    assert np.allclose(box_center(0.0)[:2], BOX_CENTER_XY) and np.allclose(box_center(1.0)[:2], BOX_CENTER_XY)
    slid = box_center(1.0, 0.6) - box_center(0.0, 0.6)
    assert np.allclose(slid, [0.0, -0.6, 0.0])
    assert np.allclose(box_center(0.5, 0.6)[:2], BOX_CENTER_XY)
    # No turn, no slide: the box renders the same at every time.
    still = dict(box_turns=0.0, box_slide=0.0, ball_turns=0.0)
    box_only = look_at_c2w(np.array([1.5, -3.5, 1.5]), target=(*BOX_CENTER_XY, -0.35))
    a, b = render_frame(box_only, 0.0, 48, **still), render_frame(box_only, 0.9, 48, **still)
    assert np.array_equal(a[20:28, 20:28], b[20:28, 20:28])
    # The slide moves the box between times.
    moving = dict(box_turns=0.0, box_slide=0.6, ball_turns=0.0)
    assert np.abs(render_frame(box_only, 0.0, 48, **moving) - render_frame(box_only, 0.9, 48, **moving)).mean() > 0.01


def test_parts_draw_single_objects_for_coverage_masks():
    c2w = look_at_c2w(np.array([0.0, -4.0, 2.0]))
    full = render_frame(c2w, 0.3, 32)
    assert np.array_equal(full, render_frame(c2w, 0.3, 32, parts=("ground", "ball", "box")))
    ball, box = (render_frame(c2w, 0.3, 32, parts=(p,))[..., 3] for p in ("ball", "box"))
    assert 0 < ball.sum() and 0 < box.sum() and (ball <= full[..., 3] + 1e-12).all()
    assert render_frame(c2w, 0.3, 32, parts=("ball", "box"))[..., 3].sum() < full[..., 3].sum()
    with pytest.raises(ValueError, match="parts"):
        render_frame(c2w, 0.3, 32, parts=("floor",))
