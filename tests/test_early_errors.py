"""Bad datasets fail early and clean: one line, before nerfstudio's configuration dump, no run folder left."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import garo_ns.config  # noqa: F401  (registers the methods and installs the plugin's nerfstudio hooks)
from garo_ns.errors import GaroInputError
from garo_ns.tools.scene import SceneSpec, generate_scene


@pytest.fixture()
def small_scene(tmp_path: Path) -> Path:
    return generate_scene(tmp_path / "scene", SceneSpec(resolution=16, n_train=3, n_val=1, n_test=1))


def ns_train(out: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "nerfstudio.scripts.train", *args[:1], "--machine.device-type", "cpu"]
    cmd += ["--output-dir", str(out), "--vis", "tensorboard", *args[1:]]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600)


def _assert_early_one_line(proc: subprocess.CompletedProcess, message: str, out: Path) -> None:
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0, text[-2000:]
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error: ") and message in lines[-1], text[-2000:]
    assert [line for line in text.splitlines() if message in line] == [lines[-1]]
    assert "Traceback" not in text
    # Reported before nerfstudio prints ("Config" rule, ~280 lines) and saves its configuration.
    assert "Saving config" not in text and "TrainerConfig(" not in text, text[:2000]
    assert len(text.splitlines()) < 20, text[:3000]
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))


@pytest.mark.parametrize("breakage", ["missing_dir", "broken_json"])
def test_ns_train_on_a_bad_dnerf_dataset(small_scene, tmp_path, breakage):
    data = small_scene
    if breakage == "missing_dir":
        data, message = small_scene.parent / "no_such_scene", "data directory does not exist"
    else:
        (small_scene / "transforms_train.json").write_text('{"frames": [')
        message = "not valid JSON"
    out = tmp_path / "outputs"
    proc = ns_train(out, "garo-deform", "--data", str(data))  # nerfstudio's --data alias
    _assert_early_one_line(proc, message, out)


def test_ns_train_on_a_bad_nerfds_capture(tmp_path):
    capture = generate_scene(tmp_path / "cap", SceneSpec(resolution=16, n_train=3, n_val=1, n_test=1), layout="nerfds")
    cam = sorted((capture / "camera").glob("*.json"))[1]
    cam.write_text(json.dumps({**json.loads(cam.read_text()), "focal_length": -5.0}))
    out = tmp_path / "outputs"
    proc = ns_train(out, "garo-deform-real", "nerfds-data", "--data", str(capture))
    _assert_early_one_line(proc, "must be positive", out)


def test_a_bad_dataset_found_during_setup_leaves_no_run_folder(small_scene, tmp_path):
    """In-process training (no ns-train, so no early check): the dataparser's error still leaves no folder."""
    from garo_ns.tools.train import make_config

    out = tmp_path / "outputs"
    config = make_config("garo-deform", small_scene, out, experiment_name="bad")
    config.set_timestamp()
    config.save_config()
    assert (config.get_base_dir() / "config.yml").exists()
    (small_scene / "train" / "r_001.png").unlink()
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(GaroInputError, match="image listed but missing"):
        trainer.setup()
    assert out.is_dir() and not any(out.iterdir())


def test_a_run_folder_with_results_is_never_removed(small_scene, tmp_path):
    from garo_ns.tools.train import make_config

    out = tmp_path / "outputs"
    config = make_config("garo-deform", small_scene, out, experiment_name="bad")
    config.save_config()
    (config.get_base_dir() / "nerfstudio_models").mkdir()
    (small_scene / "transforms_test.json").unlink()
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(GaroInputError, match="missing transforms file"):
        trainer.setup()
    assert (config.get_base_dir() / "config.yml").exists()


def test_any_error_during_setup_leaves_no_empty_run_folder(small_scene, tmp_path, monkeypatch):
    """Not only bad input: whatever stops the set-up (here the optimizers failing) takes the run folder that
    holds nothing but its config.yml with it, and the error itself still propagates."""
    from nerfstudio.engine.trainer import Trainer

    from garo_ns.tools.train import make_config

    out = tmp_path / "outputs"
    config = make_config("garo-deform", small_scene, out, experiment_name="failed")
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)

    def fail(self):
        raise RuntimeError("no memory left for the optimizers")

    monkeypatch.setattr(Trainer, "setup_optimizers", fail)
    with pytest.raises(RuntimeError, match="no memory left"):
        trainer.setup()
    assert out.is_dir() and not any(out.iterdir())


def test_running_out_of_gpu_memory_is_one_line_that_says_what_to_change():
    code = (
        "import garo_ns.config, torch\n"
        "raise torch.OutOfMemoryError('CUDA out of memory. Tried to allocate 2.00 GiB\\nmore detail')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    lines = [line for line in proc.stderr.splitlines() if line.strip() and "Warning" not in line and "warn" not in line]
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert lines[-1].startswith("error: out of GPU memory") and "max-gaussians" in lines[-1]
    assert "Tried to allocate 2.00 GiB" in lines[-1]
