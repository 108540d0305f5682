"""Files the tools write are whole or absent, and never written over a file they were not asked to replace."""

from __future__ import annotations

import os
from collections import OrderedDict

import numpy as np
import pytest

from garo_ns.errors import GaroInputError
from garo_ns.tools.export import read_ply, time_names, write_ply
from garo_ns.tools.files import check_new_file, written_atomically


def test_a_write_that_fails_leaves_the_previous_file_whole_and_no_partial(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("previous")
    with pytest.raises(OSError):
        with written_atomically(target) as partial:
            partial.write_text("half")
            raise OSError(28, "No space left on device")
    assert target.read_text() == "previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
    with written_atomically(target) as partial:
        assert partial.parent == tmp_path and partial.name != target.name
        partial.write_text("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_a_ply_cut_short_by_a_full_disk_is_never_left_under_its_name(tmp_path, monkeypatch):
    props = OrderedDict((k, np.arange(5, dtype=np.float32)) for k in ("x", "y", "z", "opacity"))
    real_replace = os.replace

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OSError):
        write_ply(tmp_path / "time_0.5000.ply", props)
    assert not any(tmp_path.iterdir())
    monkeypatch.setattr(os, "replace", real_replace)
    assert write_ply(tmp_path / "time_0.5000.ply", props) == 5
    assert np.array_equal(read_ply(tmp_path / "time_0.5000.ply")["y"], props["y"])


def test_export_names_stay_apart_for_close_times():
    assert time_names([0.0, 0.5, 1.0]) == ["time_0.0000.ply", "time_0.5000.ply", "time_1.0000.ply"]
    names = time_names([0.5, 0.50004])
    assert len(set(names)) == 2 and names[0] != "time_0.5000.ply"
    many = [i / 19_999 for i in range(20_000)]
    assert len(set(time_names(many))) == 20_000


def test_check_new_file_refuses_what_it_must_not_write(tmp_path):
    (tmp_path / "taken.png").write_bytes(b"user")
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(GaroInputError, match="exists"):
        check_new_file(tmp_path / "taken.png", "OUTPUT")
    assert check_new_file(tmp_path / "taken.png", "OUTPUT", overwrite=True) == tmp_path / "taken.png"
    with pytest.raises(GaroInputError, match="is a folder"):
        check_new_file(tmp_path, "--output-path")
    with pytest.raises(GaroInputError, match="is a file"):
        check_new_file(tmp_path / "a_file" / "eval.json", "--output-path")
    assert check_new_file(tmp_path / "new" / "eval.json", "--output-path") == tmp_path / "new" / "eval.json"
