"""The built-in dynamic scene filmed as a phone video: a hand-held camera in a textured room.

What `ns-process-data video` needs from a capture, and a synthetic one must therefore have: static
surroundings with plenty of distinct texture (structure from motion matches features there), parallax
(the camera moves, not only turns) and a steady, slow path. The room's floor, walls and ceiling carry
a colour noise posterised into sharp-edged patches, different everywhere (no repeated pattern that
features could mismatch); inside it, the built-in scene's ball travels and hops and its box turns.
The camera sweeps an arc around them at about head height with slow drift, a little shake and roll.

`write_video` renders the frames, encodes them with ffmpeg (H.264) and writes, next to the video, the
true camera path (`<video stem>_true.json`: OpenGL camera-to-world per frame, its time and the focal
length) for checking what structure from motion recovers.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from garo_ns.tools.scene_objects import GROUND_Z, hit_box, hit_sphere

ROOM_HALF = 3.0
ROOM_TOP = 2.0
TEXELS_PER_UNIT = 96.0
_LIGHT = np.array([0.3, -0.4, 0.85]) / np.linalg.norm([0.3, -0.4, 0.85])
_AMBIENT = 0.45


@dataclass(frozen=True)
class VideoSpec:
    """What to film: frame count and size, field of view, the camera's sweep and the random seed."""

    frames: int = 60
    width: int = 320
    height: int = 240
    fov_x_degrees: float = 62.0
    """Horizontal field of view (a phone's main camera films about 65 degrees)."""
    sweep_degrees: float = 60.0
    """How far the camera travels around the scene's centre over the video."""
    fps: int = 30
    seed: int = 0

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        for name, low in (("frames", 2), ("width", 16), ("height", 16), ("fps", 1)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        if self.width % 2 or self.height % 2:
            raise ValueError(f"width and height must be even (H.264), got {self.width}x{self.height}")
        if not 10.0 <= self.fov_x_degrees <= 120.0:
            raise ValueError(f"fov_x_degrees must be in 10..120, got {self.fov_x_degrees!r}")
        if not 0.0 < self.sweep_degrees <= 180.0:
            raise ValueError(f"sweep_degrees must be in (0, 180], got {self.sweep_degrees!r}")

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(0.5 * self.fov_x_degrees))


def room_texture(seed: int, size: int = 2048) -> np.ndarray:
    """An RGB texture [size, size, 3] in [0, 1]: colour noise of three octaves, posterised into patches."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size, 3))
    for cell, weight in ((128, 0.5), (40, 0.35), (12, 0.15)):
        n = size // cell + 2
        grid = rng.uniform(0.0, 1.0, (n, n, 3))
        pos = np.arange(size) / cell
        i = np.floor(pos).astype(int)
        f = pos - i
        f = f * f * (3 - 2 * f)  # smooth interpolation between the grid's values
        rows = grid[i] * (1 - f)[:, None, None] + grid[i + 1] * f[:, None, None]
        out += weight * (rows[:, i] * (1 - f)[None, :, None] + rows[:, i + 1] * f[None, :, None])
    # Posterise: sharp-edged patches give corners and blobs at many scales.
    levels = 5
    out = (out - out.min()) / (out.max() - out.min())
    return np.floor(out * levels).clip(0, levels - 1) / (levels - 1) * 0.8 + 0.1


def _sample(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of `texture` at texel coordinates (u, v), wrapping at the edges."""
    size = texture.shape[0]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = (u - u0)[..., None], (v - v0)[..., None]
    u0, v0 = u0 % size, v0 % size
    u1, v1 = (u0 + 1) % size, (v0 + 1) % size
    top = texture[v0, u0] * (1 - fu) + texture[v0, u1] * fu
    bottom = texture[v1, u0] * (1 - fu) + texture[v1, u1] * fu
    return top * (1 - fv) + bottom * fv


def _hit_room(o: np.ndarray, d: np.ndarray, texture: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where rays from inside the room leave it: distance, albedo and inward normal."""
    lo = np.array([-ROOM_HALF, -ROOM_HALF, GROUND_Z])
    hi = np.array([ROOM_HALF, ROOM_HALF, ROOM_TOP])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_exit = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    t_exit = np.where(np.isfinite(t_exit) & (t_exit > 0), t_exit, np.inf)
    axis = np.argmin(t_exit, -1)
    t = np.take_along_axis(t_exit, axis[..., None], -1)[..., 0]
    p = o + t[..., None] * d
    positive = np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0
    face = axis * 2 + positive  # six faces, each on its own region of the texture
    # In-plane coordinates of each face: the two axes other than its normal.
    a = np.where(axis == 0, p[..., 1], p[..., 0])
    b = np.where(axis == 2, p[..., 1], p[..., 2])
    region = texture.shape[0] / 3.0
    u = (a + ROOM_HALF) * TEXELS_PER_UNIT + (face % 3) * region
    v = (b + ROOM_HALF) * TEXELS_PER_UNIT + (face // 3) * region * 1.5
    albedo = _sample(texture, u, v)
    normal = np.zeros(p.shape)
    np.put_along_axis(normal, axis[..., None], np.where(positive, -1.0, 1.0)[..., None], -1)
    return t, albedo, normal


def render_video_frame(
    c2w: np.ndarray, time: float, spec: VideoSpec, texture: np.ndarray, supersample: int = 2
) -> np.ndarray:
    """RGB float image [H, W, 3] of the room and the moving objects at `time`, from OpenGL pose `c2w`."""
    s = supersample
    w, h = spec.width, spec.height
    u, v = np.meshgrid((np.arange(w * s) + 0.5) / s, (np.arange(h * s) + 0.5) / s, indexing="xy")
    dirs = np.stack([(u - 0.5 * w) / spec.focal, -(v - 0.5 * h) / spec.focal, -np.ones_like(u)], -1)
    d = dirs @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    hits = [_hit_room(o, d, texture), hit_sphere(o, d, time), hit_box(o, d, time)]
    ts = np.stack([hit[0] for hit in hits], 0)
    nearest = np.argmin(ts, 0)
    albedo = np.choose(nearest[..., None], [np.broadcast_to(hit[1], d.shape) for hit in hits])
    normal = np.choose(nearest[..., None], [np.broadcast_to(hit[2], d.shape) for hit in hits])
    shade = _AMBIENT + (1 - _AMBIENT) * np.abs(normal @ _LIGHT)
    rgb = np.clip(albedo * shade[..., None], 0.0, 1.0)
    return rgb.reshape(h, s, w, s, 3).mean(axis=(1, 3))


def _look(position: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """OpenGL camera-to-world looking from `position` at `target`, world z up, rolled by `roll` radians."""
    forward = target - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c, s = math.cos(roll), math.sin(roll)
    right, up = c * right + s * up, -s * right + c * up
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, position
    return c2w


def camera_path(spec: VideoSpec) -> List[np.ndarray]:
    """The hand-held camera's OpenGL camera-to-world [4, 4] per frame: an arc around the scene's centre at
    about head height, with slow drift in distance and height, a little shake and roll."""
    rng = np.random.default_rng(spec.seed + 1)
    phases = rng.uniform(0, 2 * math.pi, 8)
    start = rng.uniform(0, 2 * math.pi)
    poses = []
    for i in range(spec.frames):
        t = i / (spec.frames - 1)
        ease = 0.5 - 0.5 * math.cos(math.pi * t)  # starts and ends slowly, as a person pans
        azimuth = start + math.radians(spec.sweep_degrees) * ease
        radius = 2.6 + 0.12 * math.sin(2 * math.pi * 0.8 * t + phases[0])
        height = 0.55 + 0.12 * math.sin(2 * math.pi * 0.6 * t + phases[1])
        shake = 0.012 * np.array([math.sin(2 * math.pi * 7.0 * t + phases[k]) for k in (2, 3, 4)])
        position = np.array([radius * math.cos(azimuth), radius * math.sin(azimuth), height]) + shake
        target = np.array([0.0, 0.0, -0.3]) + 0.06 * np.array(
            [math.sin(2 * math.pi * 0.9 * t + phases[5]), math.sin(2 * math.pi * 1.1 * t + phases[6]), 0.0]
        )
        roll = math.radians(2.0) * math.sin(2 * math.pi * 1.3 * t + phases[7])
        poses.append(_look(position, target, roll))
    return poses


def true_path_file(video: Path) -> Path:
    """Where `write_video` puts the true camera path of `video`."""
    return video.with_name(f"{video.stem}_true.json")


def write_video(video: Path | str, spec: VideoSpec = VideoSpec()) -> Path:
    """Render the scene along the camera path, encode it to `video` (H.264, needs ffmpeg) and write the true
    path next to it (`true_path_file`). Returns the video's path."""
    spec.validate()
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise RuntimeError("ffmpeg not found: install it (Debian/Ubuntu: apt-get install ffmpeg)")
    video = Path(video)
    video.parent.mkdir(parents=True, exist_ok=True)
    texture = room_texture(spec.seed)
    poses = camera_path(spec)
    frames: List[Dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        import imageio.v2 as imageio

        for i, c2w in enumerate(poses):
            t = i / (spec.frames - 1)
            rgb = render_video_frame(c2w, t, spec, texture)
            imageio.imwrite(Path(tmp) / f"{i:05d}.png", (rgb * 255 + 0.5).astype(np.uint8))
            frames.append({"index": i, "time": t, "transform_matrix": c2w.tolist()})
        command = [ffmpeg, "-y", "-loglevel", "error", "-framerate", str(spec.fps), "-i", f"{tmp}/%05d.png"]
        command += ["-c:v", "libx264", "-crf", "16", "-pix_fmt", "yuv420p", str(video)]
        subprocess.run(command, check=True)
    truth = {"fl_x": spec.focal, "fl_y": spec.focal, "w": spec.width, "h": spec.height, "frames": frames}
    true_path_file(video).write_text(json.dumps(truth, indent=1))
    return video


def align_similarity(source: np.ndarray, target: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale s, rotation R, translation t) that best maps points `source` [N, 3] onto `target`
    [N, 3] in the least-squares sense (Umeyama's closed form): target ~ s * R @ source + t."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(xt.T @ xs / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])  # a rotation, not a reflection
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(sigma) @ sign) / xs.var(0).sum())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def path_error(true_c2w: np.ndarray, recovered_c2w: np.ndarray) -> Dict[str, float]:
    """How far a recovered camera path [N, 3+, 4] lies from the true one [N, 3+, 4] (OpenGL camera-to-world, the
    same frames in the same order) once the best similarity maps it onto the truth: RMS and largest camera
    position error as shares of the true path's extent (its bounding box diagonal), and the mean and largest
    angle between true and mapped camera orientations, in degrees."""
    scale, rotation, shift = align_similarity(recovered_c2w[:, :3, 3], true_c2w[:, :3, 3])
    mapped = scale * recovered_c2w[:, :3, 3] @ rotation.T + shift
    extent = float(np.linalg.norm(true_c2w[:, :3, 3].max(0) - true_c2w[:, :3, 3].min(0)))
    distance = np.linalg.norm(mapped - true_c2w[:, :3, 3], axis=-1)
    relative = np.einsum("nij,nik->njk", true_c2w[:, :3, :3], rotation @ recovered_c2w[:, :3, :3])
    cos = ((np.trace(relative, axis1=1, axis2=2) - 1) / 2).clip(-1, 1)
    angle = np.degrees(np.arccos(cos))
    return {
        "position_rms": float(np.sqrt((distance**2).mean()) / extent),
        "position_max": float(distance.max() / extent),
        "rotation_mean_deg": float(angle.mean()),
        "rotation_max_deg": float(angle.max()),
        "extent": extent,
    }
