"""What the FPS protocol moved out of the timed frame in commit e22ca7d: building a view's camera.

Until then each timed frame also built its camera's matrices from a nerfstudio `Cameras` on the
GPU: the time and the image size read back to the host, the world-to-camera matrix (with a sign
vector copied to the device), and the intrinsics (nerfstudio assembles them on the host from
device values, then they are copied back). Since then the views are prepared before timing, as the
official D-3DGS code prepares its cameras when it loads them. This script times that per-frame
preparation alone, as it was and as `camera_view` does it now, on a scene's split:
    python benchmarks/camera_prep.py --scene /tmp/lego --split val --output camera_prep.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Callable, Dict

import torch

from garo_ns.bench.benchmark import environment
from garo_ns.render.view import viewmat_from_c2w
from garo_ns.tools.eval import load_split


def _viewmat_with_sign_vector(c2w: torch.Tensor) -> torch.Tensor:
    """The world-to-camera matrix as the frame built it before e22ca7d (same values)."""
    rot = c2w[:, :3, :3] * torch.tensor([1.0, -1.0, -1.0], device=c2w.device, dtype=c2w.dtype)
    rot_inv = rot.transpose(1, 2)
    view = torch.zeros(c2w.shape[0], 4, 4, device=c2w.device, dtype=c2w.dtype)
    view[:, :3, :3] = rot_inv
    view[:, :3, 3:4] = -rot_inv @ c2w[:, :3, 3:4]
    view[:, 3, 3] = 1.0
    return view


def prep_before(cam: Any, device: torch.device) -> Any:
    """Per frame before e22ca7d: time, pose, intrinsics and size of a camera held on the device."""
    t = float(cam.times.reshape(-1)[0])
    viewmat = _viewmat_with_sign_vector(cam.camera_to_worlds.to(device))
    K = cam.get_intrinsics_matrices().to(device)
    return t, viewmat, K, int(cam.width.item()), int(cam.height.item())


def prep_now(cam: Any, device: torch.device) -> Any:
    """What `GaroModel.camera_view` does (once per view, before timing, in the benchmarks)."""
    K = cam.get_intrinsics_matrices().to(device)
    size = int(cam.width.item()), int(cam.height.item())
    return viewmat_from_c2w(cam.camera_to_worlds.to(device)), K, size, float(cam.times.reshape(-1)[0])


def mean_ms(fn: Callable[[Any, torch.device], Any], cams: list, device: torch.device, repeats: int) -> float:
    for cam in cams[:5]:
        fn(cam, device)
    times = []
    for _ in range(repeats):
        for cam in cams:
            torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            fn(cam, device)
            torch.cuda.synchronize(device)
            times.append(time.perf_counter() - t0)
    return 1000.0 * sum(times) / len(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--split", default="val")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--output", type=Path, default=Path("camera_prep.json"))
    args = parser.parse_args()
    device = torch.device("cuda")
    cameras, _ = load_split(args.scene, args.split, torch.zeros(3))
    cams = [cameras[i : i + 1].to(device) for i in range(len(cameras))]
    for cam in cams[:3]:  # the two ways give the same matrices
        before, now = prep_before(cam, device), prep_now(cam, device)
        torch.testing.assert_close(before[1], now[0], rtol=0, atol=1e-6)
        torch.testing.assert_close(before[2], now[1], rtol=0, atol=0)
    result: Dict[str, Any] = {
        **environment("cuda"),
        "scene": args.scene.name,
        "split": args.split,
        "views": len(cams),
        "repeats": args.repeats,
        "ms_per_frame_before": mean_ms(prep_before, cams, device, args.repeats),
        "ms_per_view_now": mean_ms(prep_now, cams, device, args.repeats),
    }
    args.output.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
