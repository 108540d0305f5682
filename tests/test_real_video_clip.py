"""A real phone video, end to end on the CPU: a downscaled clip of `cat-pikachu-7.mp4` (a cat walking on a parquet
floor, the camera circling it) through nerfstudio's `ns-process-data video` (COLMAP, no GPU) and a few hundred steps
of `garo-deform-real`, as docs/data.md tells a user. Needs `../shared/data/real/` (CI has it) and COLMAP and ffmpeg;
skipped with the reason elsewhere.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, Tuple

import pytest
from test_video_e2e import _tool, train_briefly

VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "cat-pikachu-7.mp4"
CLIP_SECONDS = 3  # of the 7 s video: an arc of the camera's circle
FRAMES = 45  # every other frame: at a third of them, or at half size, COLMAP posed under half (13 of 30)
DOWNSCALE = 4  # images_4/: 216x120, a CPU step stays short
TRAIN_STEPS = 300
MIN_POSED_SHARE = 0.9
# Measured on a 2-core CPU at 4a4a6f5 (the test prints these figures): COLMAP posed 45 of 45 frames in 216 s, and 300
# steps (97 s) reached a held-out mean of 18.37 dB (lowest frame 16.62); the same test with one step scored 10.83.
# The floor sits between, with room for other machines' numerics and COLMAP's randomness.
HELD_OUT_PSNR_FLOOR = 15.0

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not VIDEO.exists(), reason=f"needs the real captures in {VIDEO.parent} (../shared)"),
    pytest.mark.skipif(
        any(subprocess.run(["which", t], capture_output=True).returncode for t in ("colmap", "ffmpeg")),
        reason="needs COLMAP and ffmpeg (Debian: apt-get install colmap ffmpeg; scripts/test.sh installs them)",
    ),
]


@pytest.fixture(scope="module")
def processed(tmp_path_factory) -> Dict[str, Any]:
    """The clip cut and downscaled with ffmpeg, then processed by `ns-process-data video --no-gpu`."""
    root = tmp_path_factory.mktemp("real_clip")
    clip = root / "clip.mp4"
    cut = ["ffmpeg", "-v", "error", "-i", str(VIDEO), "-t", str(CLIP_SECONDS), "-c:v", "libx264", str(clip)]
    subprocess.run(cut, check=True, timeout=300)
    return {"data": root / "data", "clip": clip, "seconds": {"process": process_video(clip, root / "data")}}


def process_video(clip: Path, out: Path, *options: str) -> float:
    """`ns-process-data video --no-gpu` of `clip` into `out` with `options`; the seconds it took."""
    start = time.perf_counter()
    cmd = [_tool("ns-process-data"), "video", "--data", str(clip), "--output-dir", str(out), "--no-gpu"]
    cmd += ["--num-frames-target", str(FRAMES), *options]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=2400, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    return time.perf_counter() - start


def load_posed(data: Path) -> Tuple[Any, str]:
    """The capture in `data` as the reader loads it, or None with the pose check's line where COLMAP posed too few
    of its frames to train on (the line names the remedy)."""
    from garo_ns.data.nerfds import NerfDSDataParserConfig, load_capture
    from garo_ns.errors import GaroInputError

    try:
        return load_capture(data, NerfDSDataParserConfig(data=data, downscale_factor=DOWNSCALE)), ""
    except GaroInputError as err:
        assert "--matching-method exhaustive" in str(err), str(err)  # any other refusal is a failure
        return None, str(err)


def test_a_real_clip_is_posed_in_order_and_trains(processed, tmp_path):
    data = processed["data"]
    extracted = sorted(p.name for p in (data / "images").iterdir())
    capture, refusal = load_posed(data)
    figures: Dict[str, Any] = {"seconds": dict(processed["seconds"]), "frames": len(extracted)}
    if capture is None or len(capture.ids) < MIN_POSED_SHARE * len(extracted):
        # COLMAP's sequential matching on two cores is not repeatable: 45 of 45 frames posed at 4a4a6f5, 15 of 45 at
        # d86d9bd. Where it poses too few, docs/data.md (and the pose check's line) say to match every pair: as a user
        # would, the test processes the clip again with exhaustive matching and goes on with that.
        figures["sequential"] = refusal or f"{len(capture.ids)} of {len(extracted)} posed"
        data = processed["data"].with_name("data_exhaustive")
        figures["seconds"]["process_exhaustive"] = process_video(
            processed["clip"], data, "--matching-method", "exhaustive"
        )
        extracted = sorted(p.name for p in (data / "images").iterdir())
        capture, refusal = load_posed(data)
        assert capture is not None, (refusal, figures)

    # Posed: nearly every frame COLMAP was given.
    assert len(capture.ids) + len(capture.unposed) == len(extracted) >= FRAMES - 1, figures
    figures["posed"] = f"{len(capture.ids)} of {len(extracted)}"
    assert len(capture.ids) >= MIN_POSED_SHARE * len(extracted), figures

    # Time order: times follow the frame numbers; held-out frames lie strictly between training times.
    number = {cid: int(cid.split("_")[-1]) for cid in capture.ids}
    by_time = sorted(capture.ids, key=lambda c: capture.times[c])
    assert [number[c] for c in by_time] == sorted(number.values())
    train_times = sorted(capture.times[c] for c in capture.splits["train"])
    for cid in capture.splits["val"]:
        assert train_times[0] < capture.times[cid] < train_times[-1], cid

    # A few hundred CPU steps of the -real recipe, scored on the held-out frames.
    psnr, figures["seconds"]["train"] = train_briefly(data, tmp_path / "runs", "clip", TRAIN_STEPS, DOWNSCALE)
    figures["held_out_psnr"] = {k: round(v, 2) for k, v in psnr.items()}
    figures["seconds"] = {k: round(v, 1) for k, v in figures["seconds"].items()}
    print(f"\nreal clip end to end: {json.dumps(figures)}")
    assert psnr["mean"] > HELD_OUT_PSNR_FLOOR, figures
