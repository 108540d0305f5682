"""What both real-capture layouts are read into (`garo_ns.data.nerfds` and `garo_ns.data.video`): one
`Capture`, so that the cameras and the dataparser's outputs are built alike whichever layout a folder has."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np


@dataclass
class Capture:
    """A real capture read and checked (NeRF-DS / HyperNeRF or a processed video): ids per split, times, cameras
    and image paths."""

    ids: List[str]
    times: Dict[str, float]
    c2w: Dict[str, np.ndarray]  # OpenGL camera-to-world [3, 4], normalised frame
    intrinsics: Dict[str, np.ndarray]  # fx, fy, cx, cy at the chosen downscale
    distortion: Dict[str, np.ndarray]  # k1, k2, k3, p1, p2
    images: Dict[str, Path]
    size: Tuple[int, int]  # (height, width) at the chosen downscale
    splits: Dict[str, List[str]]
    scale: float
    center: np.ndarray
    near: Optional[float]
    far: Optional[float]
    points: Optional[np.ndarray] = None
    """Seed points in the normalised frame, when the layout gives them with its cameras (a video's)."""
    point_colors: Optional[np.ndarray] = None
    """Colours [N, 3] (uint8) of `points`, when the layout has them."""
    unposed: Tuple[str, ...] = ()
    """Frames of a video that have no pose (COLMAP could not register them), left out."""
