"""Static Gaussians: those the deformation field barely moves over the training times.

A Gaussian whose offsets (position, rotation, log-scale) stay within a threshold of their time
average at every training time renders the same with its offsets frozen at that average, so at
render time it needs no MLP evaluation. What matters is the variation over time, not the size of
the offset: a constant offset is static. Which Gaussians are static is decided from the current
field and re-decided during training (the field keeps learning on every Gaussian), so a Gaussian
that starts to move becomes dynamic again at the next decision.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.deformation import ScaleOffset, as_log_offsets

OFFSET_DIM = 10  # xyz 3, quaternion 4, log-scale 3

OffsetFn = Callable[[Tensor, float], Tuple[Tensor, Tensor, Tensor]]


@torch.no_grad()
def motion_statistics(
    offsets: OffsetFn,
    means: Tensor,
    times: Tensor,
    chunk: int = 65_536,
    log_scales: Optional[Tensor] = None,
    scale_offset: ScaleOffset = "log",
) -> Tuple[Tensor, Tensor]:
    """How far each Gaussian's offsets stray from their time average, and that average.

    Args:
        offsets: the deformation field, (canonical means [n, 3], time) -> (d_xyz, d_rot, d_scale).
        means: canonical positions [N, 3].
        times: the times to sample [T] (the training times).
        chunk: Gaussians per MLP call, to bound memory (T x chunk x 10 floats at once).
        log_scales, scale_offset: where the field's scale offsets are not log-scale offsets (`linear`), the
            Gaussians' log-scales [N, 3] to make them so (garo_ns.deformation.log_scale_offset).

    Returns:
        deviation [N, 3]: per Gaussian, the largest norm over times of offset minus mean offset,
        for position, rotation and log-scale (non-finite offsets count as infinite);
        mean_offset [N, 10]: offsets averaged over times (xyz, quaternion, log-scale).
    """
    if times.numel() == 0:
        raise ValueError("motion statistics need at least one time")
    n = means.shape[0]
    deviation = torch.zeros(n, 3, device=means.device)
    mean = torch.zeros(n, OFFSET_DIM, device=means.device)
    for start in range(0, n, chunk):
        xyz = means[start : start + chunk]
        d = torch.stack([torch.cat(offsets(xyz, t), dim=-1).float() for t in times.tolist()])  # [T, n, 10]
        part = None if log_scales is None else log_scales[start : start + chunk]
        d = as_log_offsets(d, part, scale_offset)
        avg = d.mean(dim=0)
        dev = d - avg
        norms = torch.stack([dev[..., :3].norm(dim=-1), dev[..., 3:7].norm(dim=-1), dev[..., 7:].norm(dim=-1)], -1)
        deviation[start : start + chunk] = torch.nan_to_num(norms.amax(dim=0), nan=float("inf"))
        mean[start : start + chunk] = torch.nan_to_num(avg)
    return deviation, mean


def displacement(deviation: Tensor, size: Tensor) -> Tensor:
    """Worst-case movement of a Gaussian's surface [N] if its offsets are frozen: the position
    deviation plus its largest axis `size` times the rotation (a quaternion deviation d turns it by
    about 2d radians) and relative-scale deviations."""
    return deviation[:, 0] + size * (2.0 * deviation[:, 1] + deviation[:, 2])


def classify_static(deviation: Tensor, size: Tensor, threshold: float) -> Tensor:
    """Boolean [N]: Gaussians whose frozen offsets would move them less than `threshold` (scene units)."""
    if not threshold >= 0:
        raise ValueError(f"static threshold must be >= 0, got {threshold}")
    move = displacement(deviation, torch.nan_to_num(size.float(), nan=float("inf")))
    return move < threshold


def sample_times(times: Optional[Tensor], n: int) -> Tensor:
    """Up to `n` of `times`, evenly spread; an even grid of `n` over [0, 1] when no times are known."""
    if times is None or times.numel() == 0:
        return torch.linspace(0.0, 1.0, n)
    if times.numel() > n:
        return times[torch.linspace(0, times.numel() - 1, n).round().long()]
    return times


@torch.no_grad()
def classify(
    offsets: OffsetFn,
    means: Tensor,
    log_scales: Tensor,
    times: Tensor,
    threshold: float,
    scale_offset: ScaleOffset = "log",
) -> Tuple[Tensor, Tensor]:
    """Which Gaussians are static [N] (bool) and their time-averaged offsets [N, 10] (scale offsets of the
    log-scales), from the field `offsets` sampled at `times`; `threshold` in scene units (see `classify_static`)."""
    deviation, mean = motion_statistics(
        offsets, means.detach(), times.reshape(-1), log_scales=log_scales, scale_offset=scale_offset
    )
    size = torch.exp(log_scales.detach() + mean[:, 7:]).amax(dim=-1)
    return classify_static(deviation, size, threshold), mean


def classification_due(step: int, warmup: int, every: int, last_step: Optional[int]) -> bool:
    """Whether to re-decide the static Gaussians after `step` (the caller checks that the field is on):
    every `every` steps counted from its switch-on at `warmup`, and at the `last_step` of training;
    never when `every` <= 0."""
    return every > 0 and ((step - warmup) % every == 0 or step == last_step)


def static_fraction(static: object, n: int) -> Optional[float]:
    """Share of the `n` Gaussians that the mask `static` [n] marks static; None when there is no
    classification of these `n` Gaussians (none made yet, or one made for another count)."""
    if not isinstance(static, Tensor) or static.shape[0] != n or static.numel() == 0:
        return None
    return float(static.float().mean())


@dataclass
class StaticSettings:
    """How the static classification decides, part of the model config (rendering with it is the
    `static_skip` render switch)."""

    static_threshold: float = 2.5e-4
    """Static: freezing its offsets at their time average moves no part of the Gaussian by more than
    this fraction of the scene extent at any sampled training time (position deviation plus size
    times rotation and scale deviations; on D-NeRF at 800 px, 2.5e-4 is about a third of a pixel)."""
    static_every: int = 1000
    """Re-decide which Gaussians are static every this many steps once the deformation is on, and at
    the last step; a Gaussian that starts moving becomes dynamic again."""
    static_times: int = 32
    """Training times sampled for the static classification (evenly spread over the dataset's times)."""
