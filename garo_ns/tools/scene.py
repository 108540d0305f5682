"""A procedural dynamic scene in the D-NeRF layout, rendered exactly by ray casting.

The scene has known geometry, so tests can reason about it: a flat checkered ground square
(flat: GARO should find redundancy there), a striped sphere that travels and hops across it
(curved and moving; by default its stripes also spin about the vertical axis), and a box with
differently coloured faces that by default spins about the vertical axis and may also slide
(flat faces, moving). `SceneSpec` sets the textures and how far the box and the stripes turn.
Nothing here uses a Gaussian renderer: images are analytic ray-primitive intersections with
2x2 supersampling and Lambert shading, written as RGBA PNGs (transparent background).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Sequence

import numpy as np

from garo_ns.tools.scene_objects import (
    BOX_HALF,
    GROUND_HALF,
    GROUND_Z,
    SPHERE_RADIUS,
    box_center,
    hit_box,
    hit_ground,
    hit_sphere,
    sphere_center,
)

CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.6911  # the field of view of the D-NeRF synthetic scenes
PARTS = ("ground", "ball", "box")
_LIGHT = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
_AMBIENT = 0.35


@dataclass(frozen=True)
class SceneSpec:
    """What to generate: image size in pixels, frames per split and the random seed."""

    resolution: int = 100
    n_train: int = 40
    n_val: int = 8
    n_test: int = 8
    seed: int = 0
    checks_per_unit: float = 4.0
    """Checker squares of the ground per scene unit (the ground is 2.4 units wide)."""
    sphere_stripes: int = 8
    """Meridian stripes around the sphere (an even number, so that the colours alternate)."""
    box_turns: float = 0.5
    """Turns of the box about the vertical axis over the sequence (its faces differ in colour)."""
    box_slide: float = 0.0
    """Scene units the box slides over the sequence, towards -y, centred on BOX_CENTER_XY."""
    ball_turns: float = 1.25
    """Turns of the ball's stripes about the vertical axis over the sequence (0: the stripes travel with
    the ball without turning, a pure translation)."""

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        if (
            not isinstance(self.resolution, int)
            or isinstance(self.resolution, bool)
            or not 8 <= self.resolution <= 4096
        ):
            raise ValueError(f"resolution must be an int in 8..4096, got {self.resolution!r}")
        for name in ("n_train", "n_val", "n_test"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if not isinstance(self.checks_per_unit, (int, float)) or not self.checks_per_unit > 0:
            raise ValueError(f"checks_per_unit must be > 0, got {self.checks_per_unit!r}")
        if (
            not isinstance(self.sphere_stripes, int)
            or isinstance(self.sphere_stripes, bool)
            or self.sphere_stripes < 2
            or self.sphere_stripes % 2
        ):
            raise ValueError(f"sphere_stripes must be an even int >= 2, got {self.sphere_stripes!r}")
        for name in ("box_turns", "box_slide", "ball_turns"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not 0 <= self.box_slide <= 1.0:
            raise ValueError(f"box_slide must be in 0..1 (the box stays on the floor), got {self.box_slide!r}")


def look_at_c2w(position: np.ndarray, target: Sequence[float] = (0.0, 0.0, -0.3)) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, looking down -z), world z up."""
    forward = np.asarray(target, dtype=np.float64) - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, position
    return c2w


def render_frame(
    c2w: np.ndarray,
    time: float,
    resolution: int,
    supersample: int = 2,
    checks_per_unit: float = 4.0,
    sphere_stripes: int = 8,
    box_turns: float = 0.5,
    box_slide: float = 0.0,
    ball_turns: float = 1.25,
    parts: Sequence[str] = PARTS,
) -> np.ndarray:
    """RGBA float image [H, W, 4] of the scene at `time` seen from OpenGL pose `c2w` (the keywords as in
    SceneSpec). `parts`: the objects drawn (of PARTS); the alpha of one object alone is its pixel coverage."""
    unknown = set(parts) - set(PARTS)
    if unknown or not parts:
        raise ValueError(f"parts must name some of {PARTS}, got {tuple(parts)!r}")
    focal = 0.5 * resolution / math.tan(0.5 * CAMERA_ANGLE_X)
    s = supersample
    sub = (np.arange(resolution * s) + 0.5) / s  # sample positions in pixel units
    u, v = np.meshgrid(sub, sub, indexing="xy")
    dirs_cam = np.stack([(u - 0.5 * resolution) / focal, -(v - 0.5 * resolution) / focal, -np.ones_like(u)], -1)
    d = dirs_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(c2w[:3, 3], d.shape)

    hits = []
    if "ground" in parts:
        hits.append(hit_ground(o, d, checks_per_unit))
    if "ball" in parts:
        hits.append(hit_sphere(o, d, time, sphere_stripes, ball_turns))
    if "box" in parts:
        hits.append(hit_box(o, d, time, box_turns, box_slide))
    ts = np.stack([h[0] for h in hits], 0)
    nearest = np.argmin(ts, 0)
    hit = np.isfinite(np.min(ts, 0))
    albedo = np.choose(nearest[..., None], [np.broadcast_to(h[1], d.shape) for h in hits])
    normal = np.choose(nearest[..., None], [np.broadcast_to(h[2], d.shape) for h in hits])
    # Two-sided Lambert: the ground seen from below is lit like from above.
    shade = _AMBIENT + (1 - _AMBIENT) * np.abs(normal @ _LIGHT)
    rgb = np.clip(albedo * shade[..., None], 0.0, 1.0) * hit[..., None]

    def pool(x: np.ndarray) -> np.ndarray:
        return x.reshape(resolution, s, resolution, s, -1).mean(axis=(1, 3))

    cover = pool(hit[..., None].astype(np.float64))
    color = pool(rgb) / np.maximum(cover, 1e-8)  # straight (not premultiplied) colour, as in PNGs
    return np.concatenate([np.clip(color, 0, 1), cover], -1)


def _camera_positions(rng: np.random.Generator, n: int) -> np.ndarray:
    azimuth = rng.uniform(0.0, 2 * math.pi, n)
    elevation = rng.uniform(math.radians(15), math.radians(65), n)
    return CAMERA_RADIUS * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1
    )


def _split_times(rng: np.random.Generator, n: int, split: str) -> np.ndarray:
    if split == "train":
        return np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    return np.sort(rng.uniform(0.0, 1.0, n))


# The normalisation written to scene.json by the NeRF-DS layout (world = normalised / scale + center),
# deliberately not the identity so that parsers must apply it.
NERFDS_CENTER = (0.1, -0.2, 0.3)
NERFDS_SCALE = 0.5


def _frames(spec: SceneSpec):
    """(split, index, OpenGL c2w, time, RGBA float image) of every frame, deterministic from the seed."""
    rng = np.random.default_rng(spec.seed)
    for split, n in (("train", spec.n_train), ("val", spec.n_val), ("test", spec.n_test)):
        positions = _camera_positions(rng, n)
        times = _split_times(rng, n, split)
        for i in range(n):
            c2w = look_at_c2w(positions[i])
            image = render_frame(
                c2w,
                float(times[i]),
                spec.resolution,
                checks_per_unit=spec.checks_per_unit,
                sphere_stripes=spec.sphere_stripes,
                box_turns=spec.box_turns,
                box_slide=spec.box_slide,
                ball_turns=spec.ball_turns,
            )
            yield split, i, c2w, float(times[i]), image


def surface_points(n: int = 2000, seed: int = 0, box_slide: float = 0.0) -> np.ndarray:
    """Points on the scene's surfaces at time 0 [n, 3]: what a capture's points.npy would hold."""
    rng = np.random.default_rng(seed)
    n_ground, n_sphere = n // 2, n // 4
    n_box = n - n_ground - n_sphere
    ground = np.stack(
        [
            rng.uniform(-GROUND_HALF, GROUND_HALF, n_ground),
            rng.uniform(-GROUND_HALF, GROUND_HALF, n_ground),
            np.full(n_ground, GROUND_Z),
        ],
        -1,
    )
    d = rng.normal(size=(n_sphere, 3))
    sphere = sphere_center(0.0) + SPHERE_RADIUS * d / np.linalg.norm(d, axis=-1, keepdims=True)
    box = rng.uniform(-BOX_HALF, BOX_HALF, (n_box, 3))
    axis = rng.integers(0, 3, n_box)
    box[np.arange(n_box), axis] = np.sign(rng.uniform(-1, 1, n_box)) * BOX_HALF
    box = box + box_center(0.0, box_slide)
    return np.concatenate([ground, sphere, box]).astype(np.float32)


def generate_scene(out_dir: Path | str, spec: SceneSpec = SceneSpec(), layout: str = "dnerf") -> Path:
    """Write the scene to `out_dir` and return the directory.

    layout "dnerf": transforms_{train,val,test}.json (camera_angle_x; frames with file_path without
    the .png extension, time in [0, 1], rotation, transform_matrix) and {split}/r_XXX.png RGBA images.
    layout "nerfds" (HyperNeRF's): dataset.json (train ids from the train split, val ids from the val
    split), metadata.json (time and warp_id), camera/<id>.json, scene.json (a non-trivial center and
    scale), rgb/1x and rgb/2x RGB images composited on black, and points.npy on the surfaces.
    The same seed gives the same cameras, times and pictures in both layouts.
    """
    spec.validate()
    if layout not in ("dnerf", "nerfds"):
        raise ValueError(f"layout must be 'dnerf' or 'nerfds', got {layout!r}")
    out = Path(out_dir)
    if layout == "nerfds":
        return _write_nerfds(out, spec)
    import imageio.v2 as imageio

    frames: Dict[str, List[Dict]] = {"train": [], "val": [], "test": []}
    for split, i, c2w, t, img in _frames(spec):
        (out / split).mkdir(parents=True, exist_ok=True)
        imageio.imwrite(out / split / f"r_{i:03d}.png", (img * 255 + 0.5).astype(np.uint8))
        frames[split].append(
            {"file_path": f"./{split}/r_{i:03d}", "rotation": 0.0, "time": t, "transform_matrix": c2w.tolist()}
        )
    for split, items in frames.items():
        with open(out / f"transforms_{split}.json", "w") as f:
            json.dump({"camera_angle_x": CAMERA_ANGLE_X, "frames": items}, f, indent=2)
    return out


def _write_nerfds(out: Path, spec: SceneSpec) -> Path:
    import imageio.v2 as imageio

    center, scale = np.array(NERFDS_CENTER), NERFDS_SCALE
    res = spec.resolution
    focal = 0.5 * res / math.tan(0.5 * CAMERA_ANGLE_X)
    for sub in ("camera", "rgb/1x", "rgb/2x"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    ids: Dict[str, List[str]] = {"train": [], "val": []}
    metadata: Dict[str, Dict] = {}
    for split, i, c2w, t, img in _frames(spec):
        if split == "test":  # captures have train and val ids only
            continue
        cid = f"{split}_{i:03d}"
        ids[split].append(cid)
        rgb = img[..., :3] * img[..., 3:]  # composited on black, as a camera sees it
        imageio.imwrite(out / "rgb/1x" / f"{cid}.png", (rgb * 255 + 0.5).astype(np.uint8))
        half = rgb[: res // 2 * 2, : res // 2 * 2].reshape(res // 2, 2, res // 2, 2, 3).mean((1, 3))
        imageio.imwrite(out / "rgb/2x" / f"{cid}.png", (half * 255 + 0.5).astype(np.uint8))
        camera = {
            "orientation": (c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])).T.tolist(),
            "position": (c2w[:3, 3] / scale + center).tolist(),
            "focal_length": focal,
            "principal_point": [res / 2.0, res / 2.0],
            "skew": 0.0,
            "pixel_aspect_ratio": 1.0,
            "radial_distortion": [0.0, 0.0, 0.0],
            "tangential_distortion": [0.0, 0.0],
            "image_size": [res, res],
        }
        (out / "camera" / f"{cid}.json").write_text(json.dumps(camera, indent=2))
        metadata[cid] = {"time": t, "warp_id": len(metadata), "appearance_id": len(metadata), "camera_id": 0}
    dataset = {
        "count": len(metadata),
        "num_exemplars": len(ids["train"]),
        "ids": list(metadata),
        **{f"{k}_ids": v for k, v in ids.items()},
    }
    (out / "dataset.json").write_text(json.dumps(dataset, indent=2))
    (out / "metadata.json").write_text(json.dumps(metadata, indent=2))
    scene = {"center": list(center), "scale": scale, "near": 0.1 / scale, "far": 10.0 / scale}
    (out / "scene.json").write_text(json.dumps(scene, indent=2))
    np.save(out / "points.npy", surface_points(seed=spec.seed, box_slide=spec.box_slide) / scale + center)
    return out


def main() -> None:
    """Console entry: `garo-make-scene OUT_DIR [--resolution R] [--n-train N] ...`."""
    import tyro

    def _cli(
        out_dir: Path,
        resolution: int = 100,
        n_train: int = 40,
        n_val: int = 8,
        n_test: int = 8,
        seed: int = 0,
        layout: Literal["dnerf", "nerfds", "video"] = "dnerf",
        box_turns: float = SceneSpec.box_turns,
        box_slide: float = SceneSpec.box_slide,
        ball_turns: float = SceneSpec.ball_turns,
        frames: int = 60,
    ):
        """Write the built-in dynamic scene in the D-NeRF (default) or NeRF-DS / HyperNeRF layout, or film it as a
        hand-held video (`video`: OUT_DIR/video.mp4 of `frames` frames at 320x240, for `ns-process-data video`,
        and OUT_DIR/video_true.json, the true camera path; the other options do not apply)."""
        if layout == "video":
            from garo_ns.tools.scene_video import VideoSpec, write_video

            print(f"wrote {write_video(Path(out_dir) / 'video.mp4', VideoSpec(frames=frames))}")
            return
        spec = SceneSpec(
            resolution, n_train, n_val, n_test, seed, box_turns=box_turns, box_slide=box_slide, ball_turns=ball_turns
        )
        path = generate_scene(out_dir, spec, layout)
        print(f"wrote scene to {path}")

    try:
        tyro.cli(_cli)
    except (ValueError, RuntimeError) as err:  # bad settings; no ffmpeg for a video
        raise SystemExit(f"error: {err}") from None
