"""From a phone-like video to a trained dynamic model, with the real tools: ffmpeg, nerfstudio's
`ns-process-data video` (COLMAP on the CPU) and the plugin's `-real` recipe, as docs/data.md tells a user.

The built-in scene is filmed by a hand-held-like camera (garo_ns.tools.scene_video), so the truth is known:
how many frames there are, where the camera was and when. Needs Debian's `colmap` and `ffmpeg` (scripts/test.sh
installs them); skipped with the reason where they are missing.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import numpy as np
import pytest
import torch

FRAMES = 60
TRAIN_STEPS = 300
MIN_POSED_SHARE = 0.9
MAX_POSITION_RMS = 0.02  # of the true path's extent, after the best similarity
MAX_ROTATION_DEG = 5.0
HELD_OUT_PSNR_FLOOR = 22.0  # dB; 300 steps gave 24.5 on the held-out frames (160x120, images_2/)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        shutil.which("colmap") is None or shutil.which("ffmpeg") is None,
        reason="needs COLMAP and ffmpeg (Debian: apt-get install colmap ffmpeg; scripts/test.sh installs them)",
    ),
]


def _tool(name: str) -> str:
    """A console script of the environment running the tests (e.g. .venv/bin/ns-process-data)."""
    local = Path(sys.executable).parent / name
    return str(local) if local.exists() else name


@pytest.fixture(scope="module")
def processed(tmp_path_factory) -> Dict[str, Any]:
    """The video written and processed by `ns-process-data video`, as a user would (no GPU here)."""
    from garo_ns.tools.scene_video import VideoSpec, true_path_file, write_video

    root = tmp_path_factory.mktemp("video")
    start = time.perf_counter()
    video = write_video(root / "capture.mp4", VideoSpec(frames=FRAMES))
    rendered = time.perf_counter()
    cmd = [_tool("ns-process-data"), "video", "--data", str(video), "--output-dir", str(root / "data"), "--no-gpu"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1500, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    seconds = {"render": rendered - start, "process": time.perf_counter() - rendered}
    truth = json.loads(true_path_file(video).read_text())
    return {"data": root / "data", "truth": truth, "seconds": seconds, "log": proc.stdout}


def test_video_to_a_trained_dynamic_model(processed, tmp_path):
    from garo_ns.data.nerfds import NerfDSDataParserConfig, load_capture
    from garo_ns.tools.scene_video import path_error

    data, truth = processed["data"], processed["truth"]
    config = NerfDSDataParserConfig(data=data)
    capture = load_capture(data, config)
    figures: Dict[str, Any] = {"seconds": dict(processed["seconds"])}

    # Frames posed.
    assert len(capture.ids) + len(capture.unposed) == FRAMES
    figures["posed"] = f"{len(capture.ids)} of {FRAMES}"
    assert len(capture.ids) >= MIN_POSED_SHARE * FRAMES, figures

    # Time order: each frame's time is its place in the video, whatever order COLMAP listed it in.
    index = {cid: int(cid.split("_")[-1]) - 1 for cid in capture.ids}
    for cid in capture.ids:
        assert capture.times[cid] == pytest.approx(truth["frames"][index[cid]]["time"], abs=1e-9), cid
    assert [index[c] for c in capture.ids] == sorted(index.values())
    assert all(index[c] % config.eval_every == config.eval_every // 2 for c in capture.splits["val"])

    # The recovered camera path is the true one up to a similarity.
    true_c2w = np.array([truth["frames"][index[c]]["transform_matrix"] for c in capture.ids])
    error = path_error(true_c2w, np.stack([capture.c2w[c] for c in capture.ids]))
    figures["camera_path"] = {k: round(v, 5) for k, v in error.items()}
    assert error["position_rms"] < MAX_POSITION_RMS and error["rotation_mean_deg"] < MAX_ROTATION_DEG, figures

    # Train the -real recipe briefly on the CPU and render the held-out frames.
    psnr, figures["seconds"]["train"] = train_briefly(data, tmp_path / "runs", "video", TRAIN_STEPS)
    figures["held_out_psnr"] = {k: round(v, 2) for k, v in psnr.items()}
    figures["seconds"] = {k: round(v, 1) for k, v in figures["seconds"].items()}
    print(f"\nvideo end to end: {json.dumps(figures)}")
    assert psnr["mean"] > HELD_OUT_PSNR_FLOOR, figures


def train_briefly(
    data: Path, runs: Path, name: str, steps: int, downscale: Optional[int] = None
) -> Tuple[Dict[str, float], float]:
    """`steps` CPU steps of `garo-deform-real` on a processed capture; its held-out PSNR and the training seconds.
    The demo's densification threshold: at the recipe's, a textured scene's Gaussians multiply (47k by step 100)
    and a CPU step takes seconds."""
    from garo_ns.tools.train import QuickSchedule, make_config, train

    schedule = QuickSchedule(
        steps=steps,
        num_random=2000,
        deform_width=64,
        deform_depth=4,
        deform_skip=2,
        extra={"densify_grad_thresh": 0.002},
    )
    config = make_config("garo-deform-real", data, runs, schedule=schedule, experiment_name=name)
    if downscale is not None:
        config.pipeline.datamanager.dataparser.downscale_factor = downscale
    start = time.perf_counter()
    trainer = train(config)
    seconds = time.perf_counter() - start
    return held_out_psnr(trainer.pipeline), seconds


def held_out_psnr(pipeline: Any) -> Dict[str, float]:
    """Mean and lowest PSNR (dB) of the renders of the held-out frames against the frames themselves."""
    model = pipeline.model
    model.eval()
    dm = pipeline.datamanager
    values = []
    with torch.no_grad():
        for i in range(len(dm.eval_dataset)):
            camera = dm.eval_dataset.cameras[i : i + 1].to(model.device)
            truth = model.get_gt_img(dm.cached_eval[i]["image"]).float()[..., :3]
            render = model.get_outputs(camera)["rgb"].clamp(0, 1)
            values.append(-10 * math.log10(float(((render - truth) ** 2).mean())))
    return {"mean": sum(values) / len(values), "lowest": min(values), "frames": float(len(values))}
