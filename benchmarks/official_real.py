"""A real capture (an `ns-process-data video` folder, or a Nerfies / NeRF-DS layout folder) in the official D-3DGS
code's COLMAP layout, with our frames, pixels, times and held-out split: `bash benchmarks/official_d3dgs.sh
prepare-real CAPTURE NAME` runs this here (CPU).

    python benchmarks/official_real.py CAPTURE .d3dgs/scenes/NAME

The pixels are the ones our runs train on and are scored against: our `deform-splatfacto-real` datamanager's
(on the CPU), the reader's downscaled frames undistorted by nerfstudio (OpenCV, alpha 0, cropped to the valid
region), cached as uint8 and written as lossless PNGs; the undistorted intrinsics become one PINHOLE camera. Not
`colmap image_undistorter` (its own warp, size and principal point) nor the official `-r 2` (PIL's resize is not
ns-process-data's downscale): their frames could not be scored against ours pixel for pixel. The official reader
loads these bytes as we do (uint8 / 255, no resize below 1600 pixels wide).

Layout written (what the official `readColmapSceneInfo` reads, plus three files of ours):
  images/NNNNN.png      the posed frames renamed by their place in time order; the official time int(name) /
                        (count - 1) is that place over the posed frames, ours the place over every extracted frame
                        (a Nerfies capture: a held-out frame shares its training twin's warp_id): `time_max_difference`
  frame_times.json      our time of each name, which the official code patched with `frame_times` reads instead
  sparse/0/cameras.txt  one PINHOLE camera: the undistorted size and intrinsics (pixel centres at +0.5)
  sparse/0/images.txt   a video: COLMAP's own poses (colmap/sparse/0/images.bin), in COLMAP's world frame; a
                        Nerfies capture: our reader's cameras, as world-to-camera
  sparse/0/points3D.bin a video: COLMAP's points (ns-process-data's sparse_pc.ply, our seed points); a Nerfies
                        capture: the points our recipe starts from (points.npy, or the same random ones)
  test_frames.txt       the held-out frames (our reader's `val`), read by the official code patched with `split_file`
  garo_frames.json      the mapping (our frame id, name, split, both times), the camera and the checks below

Checks (a SystemExit naming the problem): a video's frames in COLMAP's model are the ones our reader posed, and
its relative rotations and camera distances agree with transforms.json's (as our reader oriented and scaled them);
every frame has the same undistorted intrinsics; the PNGs read back equal the cached images.
"""

from __future__ import annotations

import argparse
import copy
import json
import shutil
import sys
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

METHOD = "deform-splatfacto-real"  # the baseline's recipe: its datamanager and dataparser settings
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


def frame_plan(ids: Sequence[str], held_out: Sequence[str], times: Dict[str, float]) -> List[Dict[str, Any]]:
    """Each posed frame in video order: our id, its official name (its place, 5 digits: string order is video
    order), its split, our time and the official one (place / (count - 1))."""
    order = sorted(ids, key=lambda cid: times[cid])
    if len(set(order)) != len(order):
        raise SystemExit("a frame id is given twice")
    test = set(held_out)
    if not test <= set(order):
        raise SystemExit(f"held-out frames not among the posed ones: {sorted(test - set(order))[:3]}")
    span = max(len(order) - 1, 1)
    return [
        {
            "name": f"{i:05d}",
            "ours": cid,
            "split": "test" if cid in test else "train",
            "time_ours": float(times[cid]),
            "time_official": i / span,
        }
        for i, cid in enumerate(order)
    ]


def images_text(plan: List[Dict[str, Any]], poses: Dict[str, Tuple[np.ndarray, np.ndarray]]) -> str:
    """COLMAP's images.txt for camera 1: each frame's world-to-camera quaternion (w, x, y, z) and translation, under
    its official name; no 2D points (the official reader does not use them)."""
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then POINTS2D (none)"]
    for i, frame in enumerate(plan, 1):
        q, t = poses[frame["ours"]]
        lines += [f"{i} {' '.join(repr(float(v)) for v in (*q, *t))} 1 {frame['name']}.png", ""]
    return "\n".join(lines) + "\n"


def cameras_text(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> str:
    return f"# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n1 PINHOLE {width} {height} {fx!r} {fy!r} {cx!r} {cy!r}\n"


def world_to_camera(c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """COLMAP's (quaternion w, x, y, z; translation) of a camera-to-world pose with OpenGL axes, as our reader's."""
    from nerfstudio.data.utils.colmap_parsing_utils import rotmat2qvec

    rotation = (c2w[:3, :3] @ _CV_TO_GL).T  # world-to-camera, OpenCV axes
    return rotmat2qvec(rotation), -rotation @ c2w[:3, 3]


def write_seed_points(capture: Path, ours: Any, path: Path) -> None:
    """points3D.bin (no tracks: the official reader reads positions and colours) of the points our recipe starts a
    Nerfies capture from: its points.npy as our reader takes it, or `initial_gaussians`' random ones (same seed and
    cube), near grey as ours start."""
    import torch
    from nerfstudio.data.utils.colmap_parsing_utils import Point3D, write_points3D_binary

    from garo_ns.config import METHODS
    from garo_ns.data.nerfds import read_points
    from garo_ns.engine.initialisation import initial_gaussians
    from garo_ns.render.sh import dc_to_rgb

    config, none = METHODS[METHOD].config.pipeline, np.zeros(0, dtype=np.int64)
    points = read_points(capture, ours)
    seed = None if points is None else (torch.from_numpy(points), torch.zeros((0, 3), dtype=torch.uint8))
    start = initial_gaussians(seed, config.model.random_init, config.model.num_random, config.model.random_scale, 0)
    rgb = (dc_to_rgb(start["features_dc"]).clamp(0, 1) * 255).round().byte().numpy()
    xyz = start["means"].double().numpy()
    write_points3D_binary({i: Point3D(i, p, c, 0.0, none, none) for i, (p, c) in enumerate(zip(xyz, rgb), 1)}, path)


def pose_agreement(
    ours: Dict[str, np.ndarray], colmap: Dict[str, Tuple[np.ndarray, np.ndarray]], ids: Sequence[str]
) -> Dict[str, float]:
    """How far our cameras (OpenGL camera-to-world, oriented and scaled) are from COLMAP's (world-to-camera) up to
    a similarity: the largest angle (degrees) between the two rotations from the first frame to each other one, and
    the spread (max / min) of the ratio of the cameras' distances to their mean centre (cameras within a
    thousandth of the largest distance left out: a phone held still at the start sits on the centre)."""
    from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat

    rotations, centres = {}, {}
    for cid in ids:
        q, t = colmap[cid]
        r = qvec2rotmat(np.asarray(q))
        rotations[cid], centres[cid] = r.T, -r.T @ np.asarray(t)
    first = ids[0]
    worst = 0.0
    for cid in ids[1:]:
        rel_ours = ours[first][:3, :3].T @ ours[cid][:3, :3]
        rel_colmap = _CV_TO_GL @ rotations[first].T @ rotations[cid] @ _CV_TO_GL
        cos = (np.trace(rel_ours.T @ rel_colmap) - 1) / 2
        worst = max(worst, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))
    c_ours = np.stack([ours[cid][:3, 3] for cid in ids])
    c_colmap = np.stack([centres[cid] for cid in ids])
    d_ours = np.linalg.norm(c_ours - c_ours.mean(0), axis=1)
    d_colmap = np.linalg.norm(c_colmap - c_colmap.mean(0), axis=1)
    far = d_colmap > 1e-3 * d_colmap.max()
    ratios = d_ours[far] / d_colmap[far]
    return {"max_relative_rotation_deg": worst, "distance_ratio_spread": float(ratios.max() / ratios.min())}


def our_views(capture: Path) -> Tuple[Any, Dict[str, Any]]:
    """Our reader's capture and, per frame id, the cached uint8 image and undistorted intrinsics (fx, fy, cx, cy, w,
    h), as our datamanager makes them (set up on the CPU)."""
    from garo_ns.config import METHODS
    from garo_ns.data.nerfds import load_capture

    config = copy.deepcopy(METHODS[METHOD].config.pipeline.datamanager)
    parser = config.dataparser
    config.data = parser.data = capture
    dm = config.setup(device="cpu", test_mode="val")
    views = {}
    for dataset, cache in ((dm.train_dataset, dm.cached_train), (dm.eval_dataset, dm.cached_eval)):
        cams = dataset.cameras
        for i, cid in enumerate(dataset.metadata["ids"]):
            k = tuple(float(getattr(cams, a)[i]) for a in ("fx", "fy", "cx", "cy"))
            views[cid] = {
                "image": cache[i]["image"][..., :3].cpu().numpy(),
                "intrinsics": (*k, int(cams.width[i]), int(cams.height[i])),
                "split": "train" if dataset is dm.train_dataset else "test",
            }
    return load_capture(capture, parser), views


def prepare(capture: Path, out: Path) -> Dict[str, Any]:
    import imageio.v2 as imageio
    from nerfstudio.data.utils.colmap_parsing_utils import read_images_binary

    from garo_ns.data.video import is_nerfstudio_folder

    ours, views = our_views(capture)
    plan = frame_plan(ours.ids, ours.splits["val"], ours.times)
    if {f["ours"]: f["split"] for f in plan} != {cid: v["split"] for cid, v in views.items()}:
        raise SystemExit(f"{capture}: the datamanager's splits differ from the reader's")
    if is_nerfstudio_folder(capture):
        model = capture / "colmap" / "sparse" / "0"
        colmap = {Path(im.name).stem: (im.qvec, im.tvec) for im in read_images_binary(model / "images.bin").values()}
        if set(colmap) != set(ours.ids):
            raise SystemExit(
                f"{model}: COLMAP's frames differ from those our reader posed (only COLMAP's: "
                f"{sorted(set(colmap) - set(ours.ids))[:3]}, only ours: {sorted(set(ours.ids) - set(colmap))[:3]})"
            )
        agreement = pose_agreement(ours.c2w, colmap, [f["ours"] for f in plan])
        if agreement["max_relative_rotation_deg"] > 0.1 or agreement["distance_ratio_spread"] > 1.001:
            raise SystemExit(f"{capture}: transforms.json's cameras are not COLMAP's up to a similarity: {agreement}")
        poses = colmap
    else:  # Nerfies layout: no COLMAP model; our reader's cameras are the capture's own
        poses, agreement = {cid: world_to_camera(ours.c2w[cid]) for cid in ours.ids}, None
    intrinsics = {v["intrinsics"] for v in views.values()}
    if len(intrinsics) != 1:
        raise SystemExit(f"{capture}: the undistorted frames differ in intrinsics: {sorted(intrinsics)[:2]}")
    fx, fy, cx, cy, w, h = intrinsics.pop()

    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    (out / "sparse" / "0").mkdir(parents=True)
    for frame in plan:
        pixels = views[frame["ours"]]["image"]
        path = out / "images" / f"{frame['name']}.png"
        imageio.imwrite(path, pixels)
        if not np.array_equal(np.asarray(imageio.imread(path))[..., :3], pixels):
            raise SystemExit(f"{path}: the PNG read back differs from the cached image")
    (out / "sparse" / "0" / "cameras.txt").write_text(cameras_text(w, h, fx, fy, cx, cy))
    (out / "sparse" / "0" / "images.txt").write_text(images_text(plan, poses))
    if agreement is None:
        write_seed_points(capture, ours, out / "sparse" / "0" / "points3D.bin")
    else:
        shutil.copyfile(model / "points3D.bin", out / "sparse" / "0" / "points3D.bin")
    test = [f["name"] for f in plan if f["split"] == "test"]
    (out / "test_frames.txt").write_text("\n".join(test) + "\n")
    (out / "frame_times.json").write_text(json.dumps({f["name"]: f["time_ours"] for f in plan}, indent=0))
    manifest = {
        "capture": str(capture),
        "layout": "nerfies" if agreement is None else "video",
        "pixels": f"{METHOD}'s datamanager: images_2/ or rgb/2x/, undistorted and cropped as nerfstudio caches them",
        "camera": {"model": "PINHOLE", "width": w, "height": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy},
        # The official camera is centred (its projection has no principal point): this far off, in pixels.
        "principal_point_offset_px": [cx - w / 2, cy - h / 2],
        "n_frames": len(plan),
        "n_test": len(test),
        "unposed": list(ours.unposed),
        "time_max_difference": max(abs(f["time_ours"] - f["time_official"]) for f in plan),
        "pose_agreement": agreement,
        "frames": plan,
    }
    (out / "garo_frames.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "capture",
        type=Path,
        help="an ns-process-data video folder (transforms.json, images_2/, colmap/) or a Nerfies-layout one",
    )
    ap.add_argument("out", type=Path, help="the scene folder to write, .d3dgs/scenes/NAME")
    args = ap.parse_args()
    m = prepare(args.capture.resolve(), args.out)
    c, off = m["camera"], m["principal_point_offset_px"]
    print(
        f"{args.out}: {m['n_frames']} frames ({m['n_test']} held out), {c['width']}x{c['height']} PINHOLE "
        f"fx {c['fx']:.2f} fy {c['fy']:.2f}, principal point {off[0]:+.2f} {off[1]:+.2f} px off centre; times differ "
        f"by at most {m['time_max_difference']:.3g}; poses: {m['pose_agreement']}"
    )


if __name__ == "__main__":
    sys.exit(main())
