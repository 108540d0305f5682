"""Score runs of the OFFICIAL D-3DGS code (ingra14m/Deformable-3D-Gaussians, branch `paper`) the way
`garo-eval` scores our models, and time them with the FPS protocol of `garo_ns.tools.fps`.

Runs on the GPU machine, with the official code (built, see benchmarks/official_d3dgs.sh) importable
from `--code`. Nothing of the official code is copied here: its own classes load and render.

Per scene (`--work W`: data in W/data/SCENE, the run in W/out/SCENE, its log in W/SCENE.log):

* Model: the latest iteration saved in both `point_cloud/iteration_N/point_cloud.ply` (official
  `GaussianModel.load_ply`) and `deform/iteration_N/deform.pth` (official `DeformModel`), normally
  N = the run's own --iterations (40000 for D-NeRF, 20000 for a real capture); `iterations` records N, so a run
  stopped early shows as such (`shortened`).
* Rendering: every `test` view at full resolution (official `readCamerasFromTransforms` +
  `cameraList_from_camInfos`, in transforms order), as the official code renders: under no_grad,
  `deform.step(xyz.detach(), fid expanded)` then the official `render` on a black background,
  clamped to [0, 1].
* Ground truth and metrics exactly as `garo_ns.tools.eval.evaluate`: images from
  `garo_ns.tools.eval.load_split` (RGBA PNG -> float / 255, composited on black in float), PSNR per view
  from the MSE (averaged over views), SSIM = nerfstudio's `SSIM(data_range=1.0, size_average=True,
  channel=3)` as `GaroModel.ssim`, LPIPS = `garo_ns.engine.metrics.make_lpips()` (torchmetrics AlexNet,
  normalize=True). `psnr_official_gt` scores the same renders against the official loader's own
  ground truth (composited, then truncated to 8 bits), for comparison with the PSNR that the
  official training script printed (`official_reported_psnr`, parsed from its log).
* FPS by the protocol of `garo_ns.tools.fps` (`fps_protocol`, as `garo-eval` times ours), on the official
  renderer and the cameras the official loader prepares on the GPU.

A real capture (W/data/SCENE has test_frames.txt: `official_d3dgs.sh prepare-real`) is scored as `garo-eval
--split val` scores our run of it (`garo_ns.tools.eval.capture_views`): the held-out frames test_frames.txt names,
read by the official `readColmapSceneInfo` (patched with `split_file`, and `principal_point` unless the run was
made without), rendered in float as above; ground truth = the scene's PNGs / 255, which prepare-real wrote from
our datamanager's cached (undistorted, uint8) images; SSIM = `garo_ns.engine.ssim.SSIM(data_range=1.0)` (what
`GaroModel.ssim` is), LPIPS as above where `lpips_fits`. `gt_max_difference` checks that the official loader's
ground truth is the same pixels (0.0).

Writes W/results/official_SCENE.json per scene and `--output` with all rows.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from argparse import Namespace
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

WARMUP, REPEATS = 5, 3


def latest_iteration(run: Path) -> Optional[int]:
    """The largest N with both the Gaussians and the deformation network saved."""
    found = []
    for d in (run / "point_cloud").glob("iteration_*"):
        n = int(d.name.split("_")[-1])
        if (d / "point_cloud.ply").is_file() and (run / "deform" / f"iteration_{n}" / "deform.pth").is_file():
            found.append(n)
    return max(found) if found else None


def read_cfg(run: Path) -> Namespace:
    """The official run's arguments (cfg_args holds `Namespace(...)`, as the official code reads it)."""
    return eval((run / "cfg_args").read_text(), {"Namespace": Namespace})  # noqa: S307 (official format)


def parse_log(log: Path) -> Dict[str, Any]:
    """From the official training log: test PSNR it printed per evaluated iteration, the last
    progress-bar iteration, and whether it printed 'Training complete.'."""
    if not log.is_file():
        return {"reported": {}, "last_progress": None, "complete": False}
    text = log.read_text(errors="replace")
    num = r"(?:tensor\()?([0-9.eE+-]+)"
    reported = {
        int(m.group(1)): float(m.group(3))
        for m in re.finditer(r"\[ITER (\d+)\] Evaluating test: L1 " + num + r".*? PSNR " + num, text)
    }
    prog = re.findall(r"(\d+)/(\d+) \[", text.replace("\r", "\n"))
    return {
        "reported": reported,
        "last_progress": int(prog[-1][0]) if prog else None,
        "complete": "Training complete." in text,
    }


def run_iterations(cfg: Namespace) -> int:
    """The run's --iterations. cfg_args keeps only the model's arguments, so a run started without the
    D-NeRF wrapper's record has none: official_d3dgs.sh starts D-NeRF at 40000 and a real capture at 20000."""
    recorded = getattr(cfg, "iterations", None)
    if recorded is not None:
        return int(recorded)
    return 40000 if getattr(cfg, "is_blender", False) else 20000


def train_args(cfg: Namespace) -> str:
    """The official run's training switches, from its cfg_args."""
    kind = "--is_blender" if cfg.is_blender else "real scene (no --is_blender)"
    six = " --is_6dof" if cfg.is_6dof else ""
    bg = "white" if cfg.white_background else "black"
    return f"--eval {kind}{six}, {run_iterations(cfg)} iterations, {bg} background, official defaults otherwise"


def read_float(path: Path) -> Optional[float]:
    try:
        return float(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


class OfficialRun:
    """An official D-3DGS run loaded through the official classes."""

    def __init__(self, run: Path, data: Path, iteration: int):
        from gaussian_renderer import render
        from scene.dataset_readers import readCamerasFromTransforms, readColmapSceneInfo
        from scene.deform_model import DeformModel
        from scene.gaussian_model import GaussianModel
        from utils.camera_utils import cameraList_from_camInfos

        cfg = read_cfg(run)
        if cfg.white_background:
            raise SystemExit(f"{run}: trained on a white background; this comparison is on black")
        self.cfg, self.render_fn, self.is_6dof = cfg, render, bool(cfg.is_6dof)
        self.gaussians = GaussianModel(cfg.sh_degree)
        self.gaussians.load_ply(str(run / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply"))
        self.deform = DeformModel(cfg.is_blender, cfg.is_6dof)
        self.deform.load_weights(str(run), iteration)
        self.deform.deform.eval()
        self.real = is_real(data)
        if self.real:  # the held-out frames, as the (split_file-patched) official loader reads them for training
            infos = readColmapSceneInfo(str(data), "images", True).test_cameras
        else:
            infos = readCamerasFromTransforms(str(data), "transforms_test.json", False)
        cam_args = SimpleNamespace(resolution=-1, data_device="cuda", load2gpu_on_the_fly=False)
        self.views = cameraList_from_camInfos(infos, 1.0, cam_args)
        self.names = [v.image_name for v in self.views]
        self.pipe = SimpleNamespace(convert_SHs_python=False, compute_cov3D_python=False, debug=False)
        self.bg = torch.tensor([0.0, 0.0, 0.0], dtype=torch.float32, device="cuda")

    def deformation(self, view: Any):
        xyz = self.gaussians.get_xyz
        time_input = view.fid.unsqueeze(0).expand(xyz.shape[0], -1)
        return self.deform.step(xyz.detach(), time_input)

    def raster(self, view: Any, d) -> torch.Tensor:
        return self.render_fn(view, self.gaussians, self.pipe, self.bg, *d, self.is_6dof)["render"]

    def frame(self, view: Any) -> torch.Tensor:
        return self.raster(view, self.deformation(view))


def is_real(data: Path) -> bool:
    """A real capture that `official_d3dgs.sh prepare-real` wrote (not a D-NeRF scene)."""
    return (data / "test_frames.txt").is_file()


def real_test_images(data: Path) -> Tuple[List[str], List[torch.Tensor]]:
    """The held-out frames' names and images [H, W, 3] (PNG / 255: our datamanager's cached uint8 images)."""
    import imageio.v2 as imageio

    names = (data / "test_frames.txt").read_text().split()
    images = []
    for name in names:
        pixels = np.asarray(imageio.imread(data / "images" / f"{name}.png"))[..., :3]
        images.append(torch.from_numpy(pixels.astype(np.float32)) / 255.0)
    return names, images


@torch.no_grad()
def score(model: OfficialRun, data: Path, ssim: Any, lpips: Any) -> Dict[str, Any]:
    """Metrics as garo_ns.tools.eval.evaluate, on renders made as the official code makes them."""
    from garo_ns.compaction.guard import psnr  # garo-eval's PSNR
    from garo_ns.data.dnerf import read_split
    from garo_ns.engine.metrics import lpips_fits
    from garo_ns.tools.eval import load_split

    if model.real:
        stems, images = real_test_images(data)
    else:
        stems = [Path(p).stem for p in read_split(data, "test")[0]]
        _, images = load_split(data, "test", torch.zeros(3))
    if stems != model.names:
        raise SystemExit(f"{data}: official test views {model.names[:3]}... do not match ours {stems[:3]}...")
    psnrs, ssims, lpipss, psnrs_off, gt_diff = [], [], [], [], 0.0
    for view, gt in zip(model.views, images):
        pred = model.frame(view).clamp(0, 1).permute(1, 2, 0)  # [H, W, 3] like our model's "rgb"
        gt = gt.to(pred.device)
        psnrs.append(psnr(pred, gt))
        p, g = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
        ssims.append(float(ssim(g, p)))
        if lpips is not None and (lpips_fits(pred) or not model.real):
            lpipss.append(float(lpips.to(pred.device)(g, p)))
        # the official loader's ground truth (8-bit composite), as its training log scores it
        off = view.original_image.clamp(0, 1).permute(1, 2, 0)
        gt_diff = max(gt_diff, float((off - gt).abs().max()))
        psnrs_off.append(psnr(pred, off))
    h, w = images[0].shape[:2]
    return {
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "lpips": float(np.mean(lpipss)) if lpipss else None,
        "psnr_official_gt": float(np.mean(psnrs_off)),
        "gt_max_difference": gt_diff,
        "n_images": len(images),
        "resolution": [int(w), int(h)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="W: data/SCENE, out/SCENE, SCENE.log")
    ap.add_argument("--code", type=Path, required=True, help="the built official code (train.py's folder)")
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--output", type=Path, required=True, help="combined JSON")
    ap.add_argument("--sources", type=Path, default=None, help="JSON naming the official commits used")
    ap.add_argument("--note", default="", help="how the GPU was shared during training (other runs beside these)")
    args = ap.parse_args()

    sys.path.insert(0, str(args.code.resolve()))  # the official top-level packages (scene, utils, ...)
    from pytorch_msssim import SSIM  # nerfstudio 1.1.5's splatfacto SSIM, the same class

    from garo_ns.engine.metrics import make_lpips
    from garo_ns.engine.ssim import SSIM as GaroSSIM  # GaroModel.ssim: scores the real captures, as garo-eval does
    from garo_ns.tools.fps import fps_protocol, protocol

    ssim = SSIM(data_range=1.0, size_average=True, channel=3)
    real_ssim = GaroSSIM(data_range=1.0).cuda()
    lpips = make_lpips()
    sources = json.loads(args.sources.read_text()) if args.sources and args.sources.is_file() else {}

    rows: List[Dict[str, Any]] = []
    (args.work / "results").mkdir(parents=True, exist_ok=True)
    for name in args.scenes:
        run, data, log = args.work / "out" / name, args.work / "data" / name, args.work / f"{name}.log"
        info = parse_log(log)
        start, end = read_float(args.work / f"{name}.start"), read_float(args.work / f"{name}.end")
        rc = read_float(args.work / f"{name}.rc")
        it = latest_iteration(run)
        row: Dict[str, Any] = {"scene": name}
        if it is None:
            row["official"] = None
            row["error"] = f"no saved model under {run} (last progress {info['last_progress']})"
            print(f"{name}: {row['error']}", flush=True)
            rows.append(row)
            continue
        torch.cuda.empty_cache()
        model = OfficialRun(run, data, it)
        metrics = score(model, data, real_ssim if model.real else ssim, lpips)
        # The FPS protocol on the official renderer; the official loader's cameras are already prepared on the GPU.
        timing = fps_protocol(model.views, model.frame, model.deformation, model.raster, "cuda", WARMUP, REPEATS)
        official = {
            **{k: metrics[k] for k in ("psnr", "ssim", "lpips")},
            "num_gaussians": int(model.gaussians.get_xyz.shape[0]),
            "fps": timing["fps"],
            "ms_deformation": timing["ms_deformation"],
            "iterations": it,
            "split": "val" if model.real else "test",  # a capture's held-out frames: garo-eval --split val
            "background": "black",
            "kind": "real" if model.real else "dnerf",
            "train_args": train_args(model.cfg),
            "train_seconds": (end - start) if start is not None and end is not None else None,
            **{k: metrics[k] for k in ("psnr_official_gt", "gt_max_difference", "n_images", "resolution")},
            "timing": timing,
        }
        row.update(
            official=official,
            official_reported_psnr=info["reported"].get(it),
            official_reported_psnr_by_iteration={str(k): v for k, v in sorted(info["reported"].items())},
            shortened=it < run_iterations(model.cfg),
            training_complete=bool(info["complete"]),
            training_exit_code=None if rc is None else int(rc),
            last_progress_iteration=info["last_progress"],
        )
        (args.work / "results" / f"official_{name}.json").write_text(json.dumps(row, indent=2))
        print(
            f"{name} it {it}: PSNR {official['psnr']:.3f} (official GT {official['psnr_official_gt']:.3f}, "
            f"their log {row['official_reported_psnr']})  SSIM {official['ssim']:.4f}  "
            f"LPIPS {official['lpips'] if official['lpips'] is None else round(official['lpips'], 4)}  "
            f"G {official['num_gaussians']}  FPS {official['fps']:.1f}  MLP {official['ms_deformation']:.2f} ms  "
            f"train {official['train_seconds']}",
            flush=True,
        )
        rows.append(row)
        del model

    result = {
        "gpu": torch.cuda.get_device_name(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "official_repo": "ingra14m/Deformable-3D-Gaussians",
        "official_branch": "paper",
        "official_commit": sources.get("official_commit"),
        "sources": sources,
        "train_args": sorted({r["official"]["train_args"] for r in rows if r.get("official")}),
        "runs_together": list(args.scenes),
        "note": args.note,
        "protocol": {
            "metrics": "garo_ns.tools.eval.evaluate: GT via garo_ns.tools.eval.load_split (RGBA/255 composited on "
            "black in float), PSNR from per-view MSE averaged over views, SSIM nerfstudio SSIM(data_range=1, "
            "size_average=True, channel=3), LPIPS garo_ns.engine.metrics.make_lpips() (AlexNet, normalize=True)",
            "render": "official: no_grad, deform.step(xyz.detach(), fid) then gaussian_renderer.render, black bg, "
            "clamp [0, 1], full resolution",
            "fps": f"garo_ns.tools.fps: {protocol(WARMUP, REPEATS)}",
        },
        "rows": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2))
    print(f"-> {args.output}")
    if any(r.get("official") is None for r in rows) or not all(math.isfinite(r["official"]["psnr"]) for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
