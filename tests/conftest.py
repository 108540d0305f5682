"""Shared fixtures: the built-in scene and short CPU trainings of both methods, trained once per session."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict

import pytest
import torch

os.environ.setdefault("TORCHDYNAMO_DISABLE", "1")

TRAIN_STEPS = 300
RESOLUTION = 64


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory) -> Path:
    from garo_ns.tools.scene import SceneSpec, generate_scene

    return generate_scene(
        tmp_path_factory.mktemp("scene"), SceneSpec(resolution=RESOLUTION, n_train=30, n_val=4, n_test=6)
    )


def train_views_l1(pipeline: Any, n: int = 6) -> float:
    """Mean L1 between renders and ground truth on the first n training views (model in eval mode)."""
    model = pipeline.model
    was_training = model.training
    model.eval()
    dm = pipeline.datamanager
    errs = []
    with torch.no_grad():
        for i in range(n):
            cam = dm.train_dataset.cameras[i : i + 1].to(model.device)
            gt = model.composite_with_background(
                model.get_gt_img(dm.cached_train[i]["image"]), model.background_color.to(model.device)
            )
            errs.append(float((model.get_outputs(cam)["rgb"] - gt).abs().mean()))
    model.train(was_training)
    return sum(errs) / len(errs)


@torch.no_grad()
def render_view(model: Any, camera: Any) -> torch.Tensor:
    """Deform and rasterize one camera's view, nothing else; returns the RGB render [1, H, W, 3]."""
    from garo_ns.tools.fps import model_background

    return model.render(model.camera_view(camera.to(model.device)), backgrounds=model_background(model))[0]


def _train(method: str, scene: Path, out: Path, **model_settings: Any) -> Dict[str, Any]:
    from garo_ns.tools.eval import evaluate
    from garo_ns.tools.train import QuickSchedule, make_config, seed_everything

    config = make_config(
        method,  # type: ignore[arg-type]
        scene,
        out,
        schedule=QuickSchedule(steps=TRAIN_STEPS, num_random=3000, deform_width=64, deform_depth=4, deform_skip=2),
        experiment_name=method,
    )
    for name, value in model_settings.items():
        setattr(config.pipeline.model, name, value)
    config.set_timestamp()
    seed_everything(config.machine.seed)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    l1_before = train_views_l1(trainer.pipeline)
    trainer.train()
    l1_after = train_views_l1(trainer.pipeline)
    return {
        "trainer": trainer,
        "config": config,
        "config_path": config.get_base_dir() / "config.yml",
        "l1_before": l1_before,
        "l1_after": l1_after,
        "eval": evaluate(trainer.pipeline, scene, "test"),
    }


@pytest.fixture(scope="session")
def garo_run(scene_dir, tmp_path_factory) -> Dict[str, Any]:
    return _train("garo-deform", scene_dir, tmp_path_factory.mktemp("runs"))


@pytest.fixture(scope="session")
def baseline_run(scene_dir, tmp_path_factory) -> Dict[str, Any]:
    return _train("deform-splatfacto", scene_dir, tmp_path_factory.mktemp("runs"))
