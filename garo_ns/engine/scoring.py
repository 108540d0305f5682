"""What the model reports of a render against its image, for nerfstudio's loop and its evaluation: the loss dict a
training step back-propagates, the metrics the trainer logs, and an eval image's metrics with the image pair."""

from __future__ import annotations

from typing import Any, Dict, Tuple

import torch
from torch import Tensor

from garo_ns.engine.losses import psnr, step_losses
from garo_ns.engine.metrics import image_metrics


def metrics_dict(model: Any, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Any]:
    """PSNR (and the camera optimizer's metrics) against the batch; in training only on the steps the trainer logs
    (its `steps_per_log`: it writes the metrics on those alone), for the host time of the rest."""
    if model.training and model.step % model.metrics_every:
        return {"gaussian_count": model.num_points}
    metrics: Dict[str, Any] = {"psnr": psnr(outputs["rgb"], model.ground_truth(outputs, batch))}
    if model.training:
        model.camera_optimizer.get_metrics_dict(metrics)
    metrics["gaussian_count"] = model.num_points
    return metrics


def loss_dict(model: Any, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """Splatfacto's losses (garo_ns.engine.losses: the same terms, no wait for the GPU); a non-finite loss stops
    training (`model.loss_watch`)."""
    cfg = model.config
    mask = model._downscale_if_required(batch["mask"]).to(model.device) if "mask" in batch else None
    regularise = cfg.use_scale_regularization and model.step % 10 == 0
    losses = step_losses(
        model.ground_truth(outputs, batch),
        outputs["rgb"],
        model.image_loss,
        mask,
        model.scales if regularise else None,
        cfg.max_gauss_ratio,
    )
    if model.training:
        model.camera_optimizer.get_loss_dict(losses)
        model.loss_watch.observe(losses["main_loss"], model.step)
    return losses


def image_metrics_and_images(
    model: Any, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
    """An eval image's PSNR, SSIM, LPIPS (where its weights are on disk) and the Gaussian count, with the ground
    truth and the render side by side."""
    gt = model.ground_truth(outputs, batch)
    metrics = image_metrics(gt, outputs["rgb"], model.psnr, model.ssim, model._lpips[0])
    metrics["num_gaussians"] = float(model.num_points)
    return metrics, {"img": torch.cat([gt, outputs["rgb"]], dim=1)}
