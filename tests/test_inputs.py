"""Bad input: the validating dataparser names the file and frame; training failures keep checkpoints."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import pytest
import torch

from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
from garo_ns.errors import GaroInputError, GaroTrainingError
from garo_ns.tools.scene import SceneSpec, generate_scene


@pytest.fixture()
def small_scene(tmp_path):
    return generate_scene(tmp_path / "scene", SceneSpec(resolution=16, n_train=3, n_val=1, n_test=1))


def parse(path, split="train"):
    return GaroDNeRFDataParserConfig(data=path).setup().get_dataparser_outputs(split)


def test_valid_scene_parses_with_times_background_and_extent(small_scene):
    out = parse(small_scene)
    assert out.cameras.times.shape == (3, 1)
    assert out.metadata["camera_extent"] > 1.0
    assert out.metadata["alpha_color"].tolist() == [0.0, 0.0, 0.0]
    assert len(parse(small_scene, "test").image_filenames) == 1


def edit(scene, fn):
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize(
    "breakage, message, names",
    [
        ("missing_dir", "does not exist", "{scene}/nope"),
        ("not_json", "not valid JSON", "{train}"),
        ("no_time", "needs a timestamp", "{train}, frame 1 "),
        ("time_out_of_range", "time must be", "{train}, frame 0:"),
        (
            "missing_image",
            "image listed but missing",
            "{train}, frame 2: .*{scene}/train/r_002.png",
        ),
        ("size_mismatch", "other frames are", "{train}, frame 1: image {scene}/train/r_001.png"),
        ("bad_matrix", "transform_matrix", "{train}, frame 2:"),
    ],
)
def test_bad_datasets_fail_with_one_clear_line(small_scene, breakage, message, names):
    target = small_scene
    if breakage == "missing_dir":
        target = small_scene / "nope"
    elif breakage == "not_json":
        (small_scene / "transforms_train.json").write_text("{ this is not json")
    elif breakage == "no_time":
        edit(small_scene, lambda m: m["frames"][1].pop("time"))
    elif breakage == "time_out_of_range":
        edit(small_scene, lambda m: m["frames"][0].update(time=1.5))
    elif breakage == "missing_image":
        (small_scene / "train" / "r_002.png").unlink()
    elif breakage == "size_mismatch":
        shutil.copy(
            generate_scene(small_scene.parent / "big", SceneSpec(resolution=20, n_train=1, n_val=1, n_test=1))
            / "train"
            / "r_000.png",
            small_scene / "train" / "r_001.png",
        )
    elif breakage == "bad_matrix":
        edit(small_scene, lambda m: m["frames"][2].update(transform_matrix=[[1, 0], [0, 1]]))
    before = {p: p.read_bytes() for p in small_scene.rglob("*") if p.is_file()}
    with pytest.raises(GaroInputError, match=message) as err:
        parse(target)
    assert "\n" not in str(err.value)
    # The very file and frame (not merely the scene folder, which every path in it names).
    scene = re.escape(str(small_scene))
    expected = names.format(scene=scene, train=re.escape(str(small_scene / "transforms_train.json")))
    assert re.search(expected, str(err.value)), str(err.value)
    assert {p: p.read_bytes() for p in small_scene.rglob("*") if p.is_file()} == before  # nothing touched


def test_static_dataset_error_through_ns_train_is_one_line(small_scene, tmp_path):
    edit(small_scene, lambda m: [f.pop("time") for f in m["frames"]])
    cmd = [
        sys.executable,
        "-m",
        "nerfstudio.scripts.train",
        "garo-deform",
        "--machine.device-type",
        "cpu",
        "--output-dir",
        str(tmp_path / "out"),
        "--vis",
        "tensorboard",
        "garo-dnerf-data",
        "--data",
        str(small_scene),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert "needs a timestamp per frame" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_non_finite_loss_stops_with_the_step_and_keeps_checkpoints(small_scene, tmp_path):
    import torch

    from garo_ns.tools.train import QuickSchedule, make_config

    config = make_config(
        "garo-deform",
        small_scene,
        tmp_path,
        schedule=QuickSchedule(steps=40, num_random=300, deform_width=16, deform_depth=2, deform_skip=0),
    )
    config.steps_per_save = 10
    config.save_only_latest_checkpoint = False
    config.set_timestamp()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    original = model.get_outputs

    def poisoned(camera):
        out = original(camera)
        if model.step >= 25:
            out["rgb"] = out["rgb"] * float("nan")
        return out

    model.get_outputs = poisoned
    with pytest.raises(GaroTrainingError, match="step 25"):
        trainer.train()
    ckpts = sorted(p.name for p in (config.get_base_dir() / "nerfstudio_models").glob("*.ckpt"))
    assert ckpts == ["step-000000010.ckpt", "step-000000020.ckpt"]
    state = torch.load(config.get_base_dir() / "nerfstudio_models" / ckpts[-1], map_location="cpu")
    assert all(torch.isfinite(v).all() for k, v in state["pipeline"].items() if k.startswith("_model.gauss_params"))


@pytest.mark.slow
def test_nerfstudio_dnerf_parser_background_extent_and_ns_eval(small_scene, tmp_path):
    """With nerfstudio's own dnerf-data (white by default, no metadata) the model still renders on the
    data's colour and scales densification by the camera extent; ns-eval loads the checkpoint (torch >= 2.6)."""
    import json as _json

    from nerfstudio.data.dataparsers.dnerf_dataparser import DNeRFDataParserConfig

    from garo_ns.data.dnerf import read_split
    from garo_ns.render.view import camera_extent
    from garo_ns.tools.train import QuickSchedule, make_config, train

    config = make_config(
        "garo-deform",
        small_scene,
        tmp_path,
        schedule=QuickSchedule(steps=6, num_random=300, deform_width=16, deform_depth=2, deform_skip=0),
    )
    config.pipeline.datamanager.dataparser = DNeRFDataParserConfig(data=small_scene)  # alpha_color white
    trainer = train(config)
    model = trainer.pipeline.model
    assert model.background_color.tolist() == [1.0, 1.0, 1.0]
    expected = camera_extent(read_split(small_scene, "train")[1])
    assert abs(model.strategy_state["scene_scale"] - expected) < 1e-4
    out = tmp_path / "ns_eval.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "nerfstudio.scripts.eval",
            "--load-config",
            str(config.get_base_dir() / "config.yml"),
            "--output-path",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "psnr" in _json.loads(out.read_text())["results"]


def test_garo_eval_reads_a_16_bit_png_on_its_own_scale_and_refuses_what_training_would_misread(tmp_path):
    import numpy as np
    from PIL import Image

    from garo_ns.tools.eval import load_split

    scene = generate_scene(tmp_path / "s", SceneSpec(resolution=16, n_train=2, n_val=1, n_test=1))
    path = scene / "test" / "r_000.png"
    rgba = np.asarray(Image.open(path).convert("RGBA"))
    grey = rgba[..., :3].mean(-1).astype(np.uint16) * 257  # a grey 16-bit PNG: 65535 is white
    Image.fromarray(grey).save(path)
    _, images = load_split(scene, "test", torch.zeros(3))
    np.testing.assert_allclose(images[0].numpy(), np.repeat(grey[..., None] / 65535.0, 3, -1), atol=1e-6)
    for mode in ("P", "LA"):  # nerfstudio's loader reads a palette's indices as grey and asserts on two channels
        image = Image.fromarray(rgba)
        (image.convert("RGB").quantize(8) if mode == "P" else image.convert("LA")).save(path)
        with pytest.raises(GaroInputError, match="save it as RGB or RGBA") as err:
            load_split(scene, "test", torch.zeros(3))
        assert str(path) in str(err.value)
