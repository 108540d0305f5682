"""Normals of Gaussians: the axis of the smallest scale, carried through the deformation."""

from __future__ import annotations

import torch
from torch import Tensor

from garo_ns.ops.quaternions import quat_to_rotmat


def shortest_axis(scales: Tensor) -> Tensor:
    """Index of the smallest scale per Gaussian; ties resolve to the first axis (deterministic).

    Non-finite scales count as infinitely large, so a finite axis wins when there is one.
    """
    s = torch.where(torch.isfinite(scales), scales.abs(), torch.full_like(scales, float("inf")))
    # argmin's tie-breaking is unspecified on some devices: break ties by axis explicitly.
    best = s.min(dim=-1, keepdim=True).values
    first = torch.arange(3, device=s.device).expand_as(s)
    return torch.where(s == best, first, torch.full_like(first, 3)).min(dim=-1).values.clamp(max=2)


def normals(quats: Tensor, canonical_scales: Tensor) -> Tensor:
    """Unit normals [N, 3] of Gaussians whose deformed rotation is `quats`.

    GARO's normal is the rotation column of the smallest canonical scale axis; the deformation
    carries it by n' = V U^T n with U, V the canonical and deformed rotations. Since
    n = U e_k, that is n' = V e_k: the k-th column of the deformed rotation, with k chosen from
    the canonical scales. Zero or non-finite quaternions give the identity rotation.
    """
    q = torch.where(torch.isfinite(quats).all(-1, keepdim=True), quats, torch.zeros_like(quats))
    rot = quat_to_rotmat(q)
    k = shortest_axis(canonical_scales)
    return torch.gather(rot, 2, k[:, None, None].expand(-1, 3, 1)).squeeze(-1)
