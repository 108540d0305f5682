"""A loaded model's time table on disk (garo_ns.render.table_cache): read back key for key, named by what it is made
from, never overwritten, and a file that cannot be read or written costs a build, not the render."""

from __future__ import annotations

import pytest
import torch
from test_time_table import _field, _spec, _xyz

from garo_ns.render import table_cache
from garo_ns.render.time_table import TableSpec, TimeTable


def _table(precision: str = "int8", n: int = 64) -> TimeTable:
    spec = _spec(24, precision=precision, tolerance=1e-3)
    table = TimeTable.build(spec, _field(n), _xyz(n), scale_offset="linear")
    table.tf32 = True  # a flag the file keeps too
    return table


@pytest.mark.parametrize("precision", ["int8", "int16", "fp16", "fp32"])
def test_a_table_read_back_is_the_table_written(tmp_path, precision):
    table = _table(precision)
    path = tmp_path / "run" / "time_tables" / "step-000000010-abc.pt"
    assert table_cache.write(table, path) is None and path.is_file()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no partial file left behind
    got, note = table_cache.read(path, "cpu")
    assert note is None
    for name in TimeTable.TENSORS:
        a, b = getattr(table, name), getattr(got, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name
    assert (table.codec.scale is None) == (got.codec.scale is None)
    if table.codec.scale is not None:
        assert torch.equal(table.codec.scale, got.codec.scale)
    assert got.spec == table.spec and got.info == table.info and got.scale_offset == "linear" and got.tf32
    for t in (0.0, 0.13, 0.5, 0.77, 1.0):  # the same frames, segment for segment
        assert torch.equal(got.offsets_at(t), table.offsets_at(t))


def test_the_file_is_named_by_what_the_table_is_made_of(tmp_path):
    checkpoint = tmp_path / "run" / "nerfstudio_models" / "step-000039999.ckpt"
    spec = TableSpec(0.0, 1.0, 100, "linear", "int8", 0.03, 5.9)
    path = table_cache.table_file(checkpoint, spec, "values-a", "linear", False)
    assert path.parent == tmp_path / "run" / "time_tables" and path.name.startswith("step-000039999-")
    others = {
        table_cache.table_file(checkpoint, spec, "values-b", "linear", False),  # other values (a compact file, fp16)
        table_cache.table_file(
            checkpoint, TableSpec(0.0, 1.0, 200, "linear", "int8", 0.03, 5.9), "values-a", "linear", False
        ),
        table_cache.table_file(checkpoint, spec, "values-a", "log", False),
        table_cache.table_file(checkpoint, spec, "values-a", "linear", True),
        table_cache.table_file(
            tmp_path / "run" / "nerfstudio_models" / "step-000020000.ckpt", spec, "values-a", "linear", False
        ),
    }
    assert len(others) == 5 and path not in others
    assert path == table_cache.table_file(checkpoint, spec, "values-a", "linear", False)
    assert table_cache.table_file(None, spec, "values-a", "linear", False) is None  # not loaded from a checkpoint
    assert table_cache.table_file(checkpoint, spec, None, "linear", False) is None


def test_nothing_is_overwritten_and_an_unreadable_file_is_left_as_it_is(tmp_path):
    path = tmp_path / "time_tables" / "step-1-x.pt"
    path.parent.mkdir()
    path.write_bytes(b"not a table")
    got, note = table_cache.read(path, "cpu")
    assert got is None and "could not be read" in note and str(path) in note
    assert "exists" in table_cache.write(_table(), path)
    assert path.read_bytes() == b"not a table"
    assert table_cache.read(tmp_path / "missing.pt", "cpu") == (None, None)  # no file: no reason to give


def test_a_folder_that_cannot_be_written_costs_the_file_only(tmp_path):
    (tmp_path / "time_tables").write_text("a file where the folder would go")
    note = table_cache.write(_table(), tmp_path / "time_tables" / "step-1-x.pt")
    assert note is not None and "could not be written" in note
    assert (tmp_path / "time_tables").read_text() == "a file where the folder would go"


@pytest.mark.parametrize("order", ["linear", "cubic"])
def test_a_window_cut_from_the_whole_table_renders_its_frames(order):
    from garo_ns.render.time_table import window_spec

    n = 64
    whole = TimeTable.build(_spec(48, precision="int8", tolerance=1e-3, anchor_every=8), _field(n), _xyz(n))
    whole.spec = TableSpec(**{**whole.spec.to_dict(), "order": order})  # either order, from the same keys
    state = whole.state()
    for t in (0.0, 0.21, 0.5, 0.83, 1.0):  # windows at both ends of the range and inside it
        spec = window_spec(whole.spec, t, 12)
        window = TimeTable.window_of(state, spec, "cpu")
        assert window.spec.order == order and window.residual.shape[0] == 12 + 4 and window.nbytes() < whole.nbytes()
        for u in torch.linspace(spec.t_lo, spec.t_hi, 7).tolist():
            torch.testing.assert_close(window.offsets_at(u), whole.offsets_at(u), rtol=0, atol=1e-6)
            if order == "linear":  # the frame's own path (a CUDA graph's): the time a tensor, no host reads
                rows = whole.base.clone()  # the canonical values (here 0) plus the base
                torch.testing.assert_close(
                    window.rows_at(rows, torch.tensor(u)), whole.offsets_at(u), rtol=0, atol=1e-6
                )
    with pytest.raises(ValueError, match="outside"):
        TimeTable.window_of(state, TableSpec(**{**spec.to_dict(), "t_lo": 0.9, "t_hi": 1.2}), "cpu")


def test_a_window_read_from_the_file_reads_the_whole_tables_keys(tmp_path):
    from garo_ns.render.time_table import window_spec

    table = _table()
    path = tmp_path / "step-1-x.pt"
    table_cache.write(table, path)
    spec = window_spec(table.spec, 0.6, 8)
    window, note = table_cache.read(path, "cpu", spec)
    assert note is None and window.spec.t_lo == spec.t_lo and window.spec.intervals == 8
    torch.testing.assert_close(window.offsets_at(0.6), table.offsets_at(0.6), rtol=0, atol=1e-6)
