"""The strip of held-out frames: views spread over time (garo_ns.tools.strip, the demo's strip too), saved per
variant, drawn from the saved PNGs (garo_ns.bench.strip)."""

from pathlib import Path

import numpy as np
import pytest
import torch

from garo_ns.bench import strip
from garo_ns.tools.strip import spread


def test_spread_keeps_the_ends_and_order():
    assert spread(5, 17) == [0, 4, 8, 12, 16]
    assert spread(3, 2) == [0, 1]
    assert spread(1, 9) == [4]
    assert spread(0, 9) == [] and spread(4, 0) == []


class _Cameras:
    def __init__(self, times):
        self.times = torch.tensor(times).reshape(-1, 1)

    def __getitem__(self, item):
        sub = _Cameras([0.0])
        sub.times = self.times[item]
        return sub

    def to(self, device):
        return self


class _Model:
    device = "cpu"

    def eval(self):
        return self

    def get_outputs_for_camera(self, camera):
        value = float(camera.times.reshape(-1)[0])  # a render whose grey level is its time
        return {"rgb": torch.full((6, 8, 3), value)}


class _Pipeline:
    model = _Model()


def test_views_are_saved_by_time_and_drawn(tmp_path, monkeypatch):
    times = [0.9, 0.1, 0.5, 0.3, 0.7]  # not in time order
    images = [torch.full((6, 8, 3), 1.0 - t) for t in times]
    monkeypatch.setattr("garo_ns.tools.eval.split_views", lambda pipeline, scene, split: (_Cameras(times), images))
    written = strip.save_views(_Pipeline(), Path("scene"), "val", tmp_path, "arm", count=3)
    # The earliest, middle and latest held-out frames: indices 1 (t 0.1), 2 (t 0.5), 0 (t 0.9).
    assert [p.stem for p in written] == ["0001", "0002", "0000"]
    import imageio.v2 as imageio

    assert imageio.imread(tmp_path / "arm" / "0002.png")[0, 0, 0] == round(0.5 * 255)
    assert imageio.imread(tmp_path / "ground-truth" / "0000.png")[0, 0, 0] == round(0.1 * 255)
    out = strip.draw_strip(tmp_path, tmp_path / "strip.png", ["arm", "missing-arm"], title="t")
    assert out.exists() and imageio.imread(out).shape[0] > 0


def test_a_strip_needs_a_variant_with_views(tmp_path):
    (tmp_path / "ground-truth").mkdir()
    imageio = pytest.importorskip("imageio.v2")
    imageio.imwrite(tmp_path / "ground-truth" / "0000.png", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(SystemExit, match="no views"):
        strip.draw_strip(tmp_path, tmp_path / "s.png", ["arm"])
