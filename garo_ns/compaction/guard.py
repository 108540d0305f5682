"""The quality guard of compaction: a fixed set of training views, each at its own time, on which a round
measures what leaving its candidates out of the render would cost.

Only the training split is read (the datamanager's training dataset and its cached images): the
split that is scored is never looked at while training. Views are chosen once, evenly spread over
the training times, so every round is judged on the same pixels. Renders are the trained field as
training renders it (fp32, every Gaussian, no time noise), whatever the render switches.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Optional

import torch
from torch import Tensor

from garo_ns.compaction.decision import CostFn, view_costs
from garo_ns.render.frame import FrameSettings, render_splats


def spread_indices(times: Optional[Tensor], n_views: int, count: int) -> List[int]:
    """Indices of `count` of `n_views` views evenly spread over their times (by index without times)."""
    if n_views <= 0 or count <= 0:
        return []
    order = torch.arange(n_views)
    if times is not None and times.numel() == n_views:
        order = torch.sort(times.reshape(-1).float().cpu(), stable=True).indices
    picks = torch.linspace(0, n_views - 1, min(count, n_views)).round().long().unique()
    return order[picks].tolist()


def psnr(pred: Tensor, gt: Tensor) -> float:
    """PSNR in dB of two images in [0, 1] (as garo-eval computes it)."""
    mse = torch.mean((pred.float() - gt.float()) ** 2)
    return float(-10.0 * torch.log10(mse.clamp_min(1e-12)))


@dataclass
class TrainingViewGuard:
    """Training views: the training cameras, which of them the guard uses, and those views' ground-truth
    images as the datamanager holds them."""

    cameras: Any
    images: List[Tensor]
    indices: List[int]

    @classmethod
    def from_datamanager(cls, datamanager: Any, count: int) -> Optional["TrainingViewGuard"]:
        """Up to `count` views of the datamanager's training split (None when it has none)."""
        dataset = getattr(datamanager, "train_dataset", None)
        if dataset is None or len(dataset) == 0:
            return None
        cameras = dataset.cameras
        indices = spread_indices(cameras.times, len(dataset), count)
        # Full-image datamanagers cache the training images (on the model's device); others load them.
        cached = getattr(datamanager, "cached_train", None)
        images = [(cached[i] if cached is not None else dataset[i])["image"] for i in indices]
        return cls(cameras=cameras, images=images, indices=indices)

    def render(
        self, model: Any, i: int, settings: Optional[FrameSettings] = None, without: Optional[Tensor] = None
    ) -> Tensor:
        """The guard's view `i` [H, W, 3] on the model's background, clamped: the trained field (fp32,
        every Gaussian), or with `settings` the frame path with those switches; `without` [N]: those
        Gaussians left out of this render only (the model is not changed). Call in eval mode."""
        view = model.camera_view(self.cameras[self.indices[i] : self.indices[i] + 1].to(model.device))
        splats = model.gaussians_at(view.time, exact=settings is None, settings=settings)
        if without is not None:
            splats = splats.select(~without.to(splats.means.device))
        degree = min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
        render, alpha, _ = render_splats(splats, view, degree, None, "RGB", model.config.rasterizer)
        return (render[0, ..., :3] + (1 - alpha[0]) * model.background_color.to(model.device)).clamp(0, 1)

    def targets(self, model: Any) -> List[Tensor]:
        """The views' ground truth on the model's background."""
        background = model.background_color.to(model.device)
        return [model.composite_with_background(model.get_gt_img(image), background) for image in self.images]

    @torch.no_grad()
    def psnrs(self, model: Any, without: Optional[Tensor] = None) -> Tensor:
        """PSNR [V] of each guard view of `model` as it is now (`without`: as in `render`)."""
        was_training = model.training
        model.eval()  # no time noise: the same Gaussians every time they are measured
        try:
            values = [psnr(self.render(model, i, without=without), gt) for i, gt in enumerate(self.targets(model))]
        finally:
            model.train(was_training)
        return torch.tensor(values, dtype=torch.float64)


def removal_cost(model: Any, guard: Any) -> CostFn:
    """`cost(mask)` of a round on `model` now: each guard view's PSNR as rendered minus its PSNR with the
    Gaussians of `mask` left out of the render (same step, same field; nothing removed). The plain renders
    are measured once per round, at its first try."""
    plain: List[Tensor] = []

    def cost(mask: Tensor) -> Tensor:
        if not plain:
            plain.append(guard.psnrs(model))
        return view_costs(plain[0], guard.psnrs(model, without=mask))

    return cost
