"""A run's folder is its own: runs started in the same second, or given the same --timestamp, never share one."""

from __future__ import annotations

import pytest

import garo_ns.config  # noqa: F401  (installs the plugin's nerfstudio hooks)
from garo_ns.errors import GaroInputError
from garo_ns.tools.train import make_config


def _config(tmp_path, output="out"):
    config = make_config("garo-deform", tmp_path / "scene", tmp_path / output, experiment_name="sweep")
    config.timestamp = "2026-11-28_013000"
    return config


def test_a_second_run_in_the_same_second_gets_a_folder_of_its_own(tmp_path):
    first, second = _config(tmp_path), _config(tmp_path)
    first.save_config()
    written = (first.get_base_dir() / "config.yml").read_bytes()
    (first.get_base_dir() / "nerfstudio_models").mkdir()
    (first.get_base_dir() / "nerfstudio_models" / "step-000000100.ckpt").write_bytes(b"first run")
    second.save_config()
    assert second.get_base_dir() != first.get_base_dir()
    assert second.get_base_dir().name == "2026-11-28_013000-2"
    assert (first.get_base_dir() / "config.yml").read_bytes() == written
    assert (first.get_base_dir() / "nerfstudio_models" / "step-000000100.ckpt").read_bytes() == b"first run"
    third = _config(tmp_path)
    third.save_config()
    assert third.get_base_dir().name == "2026-11-28_013000-3"


def test_a_config_saved_twice_stays_in_its_folder(tmp_path):
    config = _config(tmp_path)
    config.save_config()
    base = config.get_base_dir()
    config.save_config()
    assert config.get_base_dir() == base


def test_an_output_dir_that_is_a_file_is_one_line(tmp_path):
    (tmp_path / "out").write_text("a user's file")
    with pytest.raises(GaroInputError, match="is a file"):
        _config(tmp_path).save_config()
    assert (tmp_path / "out").read_text() == "a user's file"
