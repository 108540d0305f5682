"""The tabled frame in one kernel (garo_ns.render.table_lookup) against the torch path it replaces, on a CPU through
Triton's interpreter: the same means, quaternions and scales at times between keys, at keys, at anchors and
outside the range, for each storage precision and both scale compositions."""

from __future__ import annotations

import pytest
import torch
from test_time_table import _field, _spec, _xyz

from garo_ns.render.table_lookup import fused_available, table_splats
from garo_ns.render.time_table import TimeTable, row_scales

triton = pytest.importorskip("triton", reason="Triton is not installed: the one-kernel frame is not used here")


def _torch_splats(table, rows, t):
    d = table.rows_at(rows, torch.tensor(t, device=rows.device))
    return d[:, :3], d[:, 3:7], row_scales(d[:, 7:], table.scale_offset)


@pytest.mark.parametrize("precision", ["fp32", "fp16", "int16", "int8"])
@pytest.mark.parametrize("scale_offset", ["log", "linear"])
def test_the_one_kernel_frame_is_the_torch_frame(monkeypatch, precision, scale_offset):
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    field = _field(amp=0.05)
    xyz = _xyz()
    table = TimeTable.build(_spec(61, tolerance=1e-2, anchor_every=4, precision=precision), field, xyz)
    table.scale_offset = scale_offset
    rows = torch.randn(64, 10, generator=torch.Generator().manual_seed(2))
    assert fused_available(table, rows)
    keys = table.spec.key_times()
    times = torch.cat([torch.linspace(-0.05, 1.05, 23), keys[table._anchor_keys[1:-1]], keys[5:8]]).tolist()
    for t in times:
        got = table_splats(table, rows, torch.tensor(t))
        for g, w, name in zip(got, _torch_splats(table, rows, t), ("means", "quats", "scales")):
            assert g.shape == w.shape and g.is_contiguous(), name
            assert torch.allclose(g, w, rtol=1e-6, atol=1e-7), (name, t, float((g - w).abs().max()))


def test_a_table_with_still_gaussians_or_no_device_kernel_is_left_to_the_torch_path(monkeypatch):
    field = _field(amp=0.05)
    field.amp[48:] = 0.0
    table = TimeTable.build(_spec(61, tolerance=1e-2, anchor_every=4), field, _xyz())
    rows = torch.randn(64, 10, generator=torch.Generator().manual_seed(2))
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    assert table.moving.numel() == 48 and not fused_available(table, rows)
    moving = TimeTable.build(_spec(61, tolerance=1e-2, anchor_every=4), _field(amp=0.05), _xyz())
    assert fused_available(moving, rows)
    monkeypatch.delenv("TRITON_INTERPRET")
    assert not fused_available(moving, rows)  # a CPU tensor without the interpreter


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_one_kernel_frame_on_a_gpu_replays_in_a_cuda_graph():
    from garo_ns.render.graphs import TimeGraph

    field = _field(n=4096, amp=0.05)
    field.amp.clamp_(min=0.01)  # every Gaussian moves: the one-kernel case
    xyz = _xyz(4096).cuda()
    cuda_field = lambda p, t: tuple(x.cuda() for x in field(p.cpu(), t))  # noqa: E731
    table = TimeTable.build(_spec(121, tolerance=1e-2, anchor_every=8, precision="int16"), cuda_field, xyz)
    rows = torch.randn(4096, 10, device="cuda")
    assert fused_available(table, rows)
    graph = TimeGraph()
    with torch.no_grad():
        for t in torch.linspace(-0.05, 1.05, 31).tolist():
            got = graph("table", lambda time: table_splats(table, rows, time), t, rows.device)
            for g, w in zip(got, _torch_splats(table, rows, t)):
                assert torch.allclose(g, w, rtol=1e-6, atol=1e-7), t
    assert graph.captures == 1
