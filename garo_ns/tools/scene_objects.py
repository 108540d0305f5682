"""The built-in scene's objects, shared by its D-NeRF / NeRF-DS renders (`garo_ns.tools.scene`) and its video
(`garo_ns.tools.scene_video`): a checkered ground square, a striped ball that travels and hops, a box with coloured
faces that turns (and may slide); where each is at a time, and where a ray meets it.

Each `hit_*` takes ray origins and unit directions [..., 3] and gives the distance along each ray (inf for a miss),
the albedo and the unit normal at the hit.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np

GROUND_Z = -0.6
GROUND_HALF = 1.2
SPHERE_RADIUS = 0.35
BOX_HALF = 0.25
BOX_CENTER_XY = (0.35, -0.55)

Hit = Tuple[np.ndarray, np.ndarray, np.ndarray]


def sphere_center(t: float) -> np.ndarray:
    """Centre of the sphere at time t in [0, 1]: it crosses the ground and hops once."""
    x = -0.7 + 1.2 * t
    y = 0.45 * math.sin(math.pi * t)
    z = GROUND_Z + SPHERE_RADIUS + 0.35 * math.sin(math.pi * t)
    return np.array([x, y, z])


def box_angle(t: float, turns: float = 0.5) -> float:
    """Yaw of the box at time t: `turns` turns over the sequence (half a turn by default)."""
    return 2 * math.pi * turns * t


def box_center(t: float, slide: float = 0.0) -> np.ndarray:
    """Centre of the box at time t: on the floor, `slide` scene units along -y over the sequence, centred on
    BOX_CENTER_XY (away from the ball's path, which bends towards +y)."""
    return np.array([BOX_CENTER_XY[0], BOX_CENTER_XY[1] + slide * (0.5 - t), GROUND_Z + BOX_HALF])


def hit_ground(o: np.ndarray, d: np.ndarray, checks: float = 4.0) -> Hit:
    """Where rays (origins `o`, unit directions `d`) meet the checkered ground square, `checks` squares a unit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (GROUND_Z - o[..., 2]) / d[..., 2]
    p = o + t[..., None] * d
    ok = (t > 1e-6) & (np.abs(p[..., 0]) <= GROUND_HALF) & (np.abs(p[..., 1]) <= GROUND_HALF)
    checker = (np.floor(p[..., 0] * checks) + np.floor(p[..., 1] * checks)) % 2
    albedo = np.where(checker[..., None] > 0, [0.85, 0.82, 0.75], [0.25, 0.45, 0.65])
    normal = np.broadcast_to([0.0, 0.0, 1.0], p.shape)
    return np.where(ok, t, np.inf), albedo, normal


def hit_sphere(o: np.ndarray, d: np.ndarray, time: float, stripes: int = 8, turns: float = 1.25) -> Hit:
    """Where rays meet the ball at `time`: `stripes` meridian stripes that turn `turns` times over the sequence."""
    c = sphere_center(time)
    oc = o - c
    b = np.sum(oc * d, -1)
    disc = b * b - (np.sum(oc * oc, -1) - SPHERE_RADIUS**2)
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = -b - sq
    ok = (disc >= 0) & (t > 1e-6)
    p = o + t[..., None] * d
    n = (p - c) / SPHERE_RADIUS
    # Meridian stripes in a frame that turns `turns` times over the sequence, so the texture moves too.
    lon = np.arctan2(n[..., 1], n[..., 0]) + 2 * math.pi * turns * time
    stripe = (np.floor(lon / (2 * math.pi / stripes)) % 2)[..., None]
    albedo = np.where(stripe > 0, [0.9, 0.25, 0.2], [0.95, 0.8, 0.2])
    return np.where(ok, t, np.inf), albedo, n


def hit_box(o: np.ndarray, d: np.ndarray, time: float, turns: float = 0.5, slide: float = 0.0) -> Hit:
    """Where rays meet the box at `time`, which turns `turns` times and slides `slide` units over the sequence."""
    ang = box_angle(time, turns)
    ca, sa = math.cos(ang), math.sin(ang)
    rot = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])  # box -> world
    center = box_center(time, slide)
    ol = (o - center) @ rot  # world -> box frame (rot is orthonormal)
    dl = d @ rot
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dl
        t0 = (-BOX_HALF - ol) * inv
        t1 = (BOX_HALF - ol) * inv
    tmin = np.minimum(t0, t1)
    tmax = np.maximum(t0, t1)
    tnear = np.max(tmin, -1)
    tfar = np.min(tmax, -1)
    ok = (tnear <= tfar) & (tnear > 1e-6)
    axis = np.argmax(tmin, -1)
    sign = -np.sign(np.take_along_axis(dl, axis[..., None], -1))[..., 0]
    nl = np.zeros_like(dl)
    np.put_along_axis(nl, axis[..., None], sign[..., None], -1)
    face = axis * 2 + (sign > 0)
    palette = np.array(
        [[0.2, 0.7, 0.3], [0.6, 0.2, 0.7], [0.95, 0.55, 0.1], [0.1, 0.6, 0.8], [0.8, 0.8, 0.8], [0.3, 0.3, 0.3]]
    )
    return np.where(ok, tnear, np.inf), palette[face], nl @ rot.T
