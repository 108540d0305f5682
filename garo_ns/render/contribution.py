"""Contribution of each Gaussian to the training views, for pruning those that barely show.

A Gaussian's contribution to a view is the sum over pixels of its blending weight T * alpha, the
share of those pixels' colour it provides. It is read off the rasterizer's backward pass: rendering
a one-channel colour m_i = 1 gives d(sum of pixels) / d m_i = sum of its weights, so one render
and one backward per view give every Gaussian's contribution, on either backend.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Iterable, Union

import torch
from torch import Tensor

from garo_ns.render.backend import Backend, rasterize
from garo_ns.render.view import RenderView

if TYPE_CHECKING:
    from garo_ns.render.frame import Splats


def view_contribution(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    backend: Backend = "auto",
) -> Tensor:
    """Sum over the pixels of one view of each Gaussian's blending weight [N] (no gradient kept).

    Args: Gaussians as `rendering.rasterize` takes them (activated scales and opacities), one
    world-to-camera matrix [1, 4, 4] and intrinsics [1, 3, 3].
    """
    ones = torch.ones(means.shape[0], 1, device=means.device, dtype=means.dtype, requires_grad=True)
    with torch.enable_grad():
        render, _, _ = rasterize(
            means=means.detach(),
            quats=quats.detach(),
            scales=scales.detach(),
            opacities=opacities.detach(),
            colors=ones,
            viewmats=viewmat,
            Ks=K,
            width=width,
            height=height,
            sh_degree=None,
            backend=backend,
        )
        if not render.requires_grad:  # nothing visible in this view
            return torch.zeros(means.shape[0], device=means.device)
        render.sum().backward()
    grad = ones.grad
    if grad is None:
        return torch.zeros(means.shape[0], device=means.device)
    return torch.nan_to_num(grad[:, 0].detach().float(), nan=0.0, posinf=0.0, neginf=0.0)


@torch.no_grad()
def summed_contribution(
    views: Iterable[RenderView],
    gaussians_at: Callable[[float], "Splats"],
    n: int,
    device: Union[str, torch.device],
    backend: Backend = "auto",
) -> Tensor:
    """Each of the `n` Gaussians' blending weight summed over `views` [n], every view rendering the
    Gaussians at its own time (`gaussians_at`)."""
    total = torch.zeros(n, device=device)
    for view in views:
        gaussians = gaussians_at(view.time)[:4]  # means, quats, scales, opacities
        total += view_contribution(*gaussians, view.viewmat, view.K, view.width, view.height, backend)
    return total
