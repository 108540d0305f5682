"""What a model takes from its training data, whatever the dataparser: the training cameras and their times,
the background (the data's alpha colour), the scene extent that densification scales by, and the training
views that compaction and the render switches are measured on (the training split only)."""

from __future__ import annotations

from typing import Any

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from garo_ns.compaction.guard import TrainingViewGuard
from garo_ns.render.view import HostCameras, camera_extent


def adopt_training_data(model: Any, pipeline: Any) -> None:
    """Make `model` (a GaroModel) agree with `pipeline`'s training data: render on the data's alpha colour,
    and (unless the config or the dataparser set it) scale densification by the 3DGS camera extent. Nothing
    changes when the pipeline has no dataparser outputs."""
    outputs = getattr(getattr(pipeline, "datamanager", None), "train_dataparser_outputs", None)
    if outputs is None:
        return
    model.train_cameras = outputs.cameras
    # Each training step's camera is a device copy of one of the dataset's cameras, which stay on the host (the
    # datamanager's own `train_cameras` may be on the device already).
    step_cameras = getattr(getattr(pipeline.datamanager, "train_dataset", None), "cameras", None)
    if step_cameras is not None and step_cameras.camera_to_worlds.device.type == "cpu":
        model.step_cameras = HostCameras(step_cameras)
    if outputs.cameras.times is not None:
        model.train_times = torch.unique(outputs.cameras.times.detach().reshape(-1).float().cpu())
    alpha = outputs.alpha_color
    if alpha is not None and not torch.allclose(alpha.float().cpu(), model.background_rgb.cpu()):
        CONSOLE.print(f"[yellow]Background set to the data's alpha colour {alpha.tolist()}[/yellow]")
        model.background_color = alpha
    if not model.extent_fixed:
        model.scene_extent = camera_extent(outputs.cameras.camera_to_worlds.detach().cpu().numpy())
        model.strategy_state["scene_scale"] = model.scene_extent
    model.compaction_guard = TrainingViewGuard.from_datamanager(pipeline.datamanager, model.config.compact_guard_views)
    model.switch_guard = TrainingViewGuard.from_datamanager(pipeline.datamanager, model.config.switch_views)


def reuse_step_cameras(datamanager: Any) -> bool:
    """Serve each training step's camera from one device copy per training view: nerfstudio's full-image
    datamanager slices its cameras anew at every step (a dozen small tensors, a few hundred microseconds of host
    time in a step of a few milliseconds). The views come in the datamanager's own order, with the same images and
    the same `cam_idx`; a datamanager that overrides `next_train` is left alone. Returns whether it was installed.

    The cameras handed out are shared between the steps of one view: a step must not change them (the model's
    training step reads them only)."""
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager

    own = getattr(type(datamanager), "next_train", None) is FullImageDatamanager.next_train  # any other: as it is
    if not own or getattr(datamanager, "_step_cameras_reused", False):
        return False
    dm, cameras = datamanager, {}

    def next_train(step: int) -> Any:
        index = dm.train_unseen_cameras.pop(0)
        if not dm.train_unseen_cameras:  # an epoch is over: the datamanager's next order
            dm.train_unseen_cameras = dm.sample_train_cameras()
        data = dict(dm.cached_train[index])  # a new dict each step: the cached one stays as it is
        data["image"] = data["image"].to(dm.device)
        camera = cameras.get(index)
        if camera is None:
            camera = cameras[index] = dm.train_cameras[index : index + 1].to(dm.device)
            camera.metadata = {**(camera.metadata or {}), "cam_idx": index}
        return camera, data

    dm.next_train = next_train
    dm._step_cameras_reused = True
    return True
