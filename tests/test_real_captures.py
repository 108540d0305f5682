"""The real captures of ../shared/data/real (CI has them; a user's clone does not: these tests skip there)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from garo_ns.data.nerfds import NerfDSDataParserConfig, load_capture

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
CAKE = REAL / "nerfies-cake"
needs_cake = pytest.mark.skipif(not CAKE.is_dir(), reason=f"{CAKE} absent (../shared is not part of a clone)")


@needs_cake
def test_the_nerfies_reader_keeps_colmaps_numbers_of_a_real_capture():
    capture = load_capture(CAKE, NerfDSDataParserConfig(data=CAKE))  # 2x by default
    dataset = json.loads((CAKE / "dataset.json").read_text())
    meta = json.loads((CAKE / "metadata.json").read_text())
    scene = json.loads((CAKE / "scene.json").read_text())
    assert capture.splits == {"train": dataset["train_ids"], "val": dataset["val_ids"]}
    assert all("time_id" not in meta[i] and "warp_id" in meta[i] for i in capture.ids)  # an older Nerfies capture
    last = max(meta[i]["warp_id"] for i in capture.ids)
    for cid in capture.ids:
        cam = json.loads((CAKE / "camera" / f"{cid}.json").read_text())
        width, height = cam["image_size"]
        assert capture.size == (round(height / 2), round(width / 2))  # (h, w) of rgb/2x
        fx, fy, cx, cy = capture.intrinsics[cid]
        assert fx == pytest.approx(cam["focal_length"] / 2) and fy == pytest.approx(fx)
        assert (cx, cy) == pytest.approx((cam["principal_point"][0] / 2, cam["principal_point"][1] / 2))
        np.testing.assert_allclose(capture.distortion[cid], cam["radial_distortion"] + cam["tangential_distortion"])
        centre = (np.array(cam["position"]) - np.array(scene["center"])) * scene["scale"]
        np.testing.assert_allclose(capture.c2w[cid][:, 3], centre, atol=1e-9)
        # OpenCV's camera axes (looking down +z) become OpenGL's (looking down -z): the same viewing direction.
        np.testing.assert_allclose(-capture.c2w[cid][:, 2], np.array(cam["orientation"])[2], atol=1e-9)
        assert capture.times[cid] == pytest.approx(meta[cid]["warp_id"] / last)
