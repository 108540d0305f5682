"""Render-time speed techniques: static Gaussians, the viewer cache, and contribution pruning (the time table:
tests/test_time_table.py). Each must be exact or measurably close to the plain path."""

from __future__ import annotations

import math

import pytest
import torch

from garo_ns.redundancy.select import least_contributing
from garo_ns.render.contribution import view_contribution
from garo_ns.render.frame import FrameSettings, versions
from garo_ns.render.static import classify_static, displacement, motion_statistics


def test_motion_statistics_find_the_moving_half():
    means = torch.randn(1000, 3)

    def offsets(xyz, t):
        moving = (xyz[:, :1] > 0).float()
        return moving * torch.tensor([[t, 0.0, 0.0]]), torch.zeros(len(xyz), 4), torch.full((len(xyz), 3), 1e-5)

    deviation, mean = motion_statistics(offsets, means, torch.linspace(0, 1, 5), chunk=300)
    static = classify_static(deviation, torch.ones(1000), 1e-3)
    assert torch.equal(static, means[:, 0] <= 0)  # a constant offset (the scale's) is static
    assert torch.allclose(deviation[means[:, 0] > 0, 0], torch.tensor(0.5))
    assert torch.allclose(mean[means[:, 0] > 0, 0], torch.full(((means[:, 0] > 0).sum(),), 0.5))
    assert torch.allclose(mean[:, 7:], torch.full((1000, 3), 1e-5))
    nan_offsets = lambda xyz, t: (torch.full_like(xyz, float("nan")), torch.zeros(len(xyz), 4), torch.zeros_like(xyz))  # noqa: E731
    deviation, _ = motion_statistics(nan_offsets, means[:10], torch.tensor([0.5]))
    assert not classify_static(deviation, torch.ones(10), 1e-3).any()  # a NaN offset is never "static"
    with pytest.raises(ValueError, match="at least one time"):
        motion_statistics(offsets, means, torch.tensor([]))
    with pytest.raises(ValueError, match="threshold"):
        classify_static(deviation, torch.ones(10), float("nan"))


def test_displacement_weighs_rotation_and_scale_by_size():
    deviation = torch.tensor([[0.0, 0.01, 0.0], [0.0, 0.0, 0.01], [0.002, 0.0, 0.0]])
    small, large = displacement(deviation, torch.full((3,), 0.01)), displacement(deviation, torch.full((3,), 1.0))
    assert torch.allclose(small, torch.tensor([2e-4, 1e-4, 2e-3]))
    assert torch.allclose(large, torch.tensor([2e-2, 1e-2, 2e-3]))
    # A wobble of a large Gaussian disqualifies it; the same wobble of a tiny one does not.
    assert classify_static(deviation, torch.full((3,), 0.01), 1e-3).tolist() == [True, True, False]
    assert classify_static(deviation, torch.full((3,), 1.0), 1e-3).tolist() == [False, False, False]


def _camera():
    view = torch.eye(4)[None]
    view[0, 2, 3] = 4.0  # camera 4 units in front of the origin, looking along +z
    K = torch.tensor([[[60.0, 0.0, 32.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]]])
    return view, K


def test_contribution_sees_occlusion_and_the_frustum():
    view, K = _camera()
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.0, -1.0], [50.0, 0.0, 0.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(4, 1)
    scales = torch.tensor([[1.0, 1.0, 1.0], [0.1, 0.1, 0.1], [0.05, 0.05, 0.05], [0.1, 0.1, 0.1]])
    opacities = torch.tensor([0.999, 0.9, 0.9, 0.9])
    w = view_contribution(means, quats, scales, opacities, view, K, 64, 64, backend="reference")
    # 0: large and in front; 1: hidden behind 0; 2: small, visible; 3: outside the view.
    assert w[0] > w[2] > 0
    assert w[1] < 0.05 * w[2]
    assert w[3] == 0
    assert torch.equal(least_contributing(w, 0.5), torch.tensor([False, True, False, True]))
    assert not least_contributing(w, 0.0).any()
    with pytest.raises(ValueError, match="ratio"):
        least_contributing(w, 1.0)


def test_contribution_is_the_sum_of_blending_weights():
    """One Gaussian alone: its summed weight equals the rendered alpha summed over pixels."""
    from garo_ns.render.backend import rasterize

    view, K = _camera()
    args = dict(
        means=torch.zeros(1, 3),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        scales=torch.full((1, 3), 0.2),
        opacities=torch.tensor([0.7]),
    )
    w = view_contribution(**args, viewmat=view, K=K, width=64, height=64, backend="reference")
    _, alpha, _ = rasterize(
        **args, colors=torch.ones(1, 3), viewmats=view, Ks=K, width=64, height=64, backend="reference"
    )
    assert math.isclose(float(w[0]), float(alpha.sum()), rel_tol=1e-4)


def _eval_model(run):
    model = run["trainer"].pipeline.model
    model.eval()
    return model


@pytest.mark.slow
def test_static_gaussians_render_like_the_full_field(garo_run):
    model = _eval_model(garo_run)
    assert model.static_fraction() is not None  # classified during training, last at the last step
    assert model.strategy_state["static_step"] == model.step
    # The quick CPU schedule's field wobbles everywhere (its learning rate is 6x D-3DGS's), so the
    # default threshold finds few static Gaussians here; take the median movement as threshold
    # (about a third of a pixel at 64 px) to split the scene in two and test the mechanism.
    from garo_ns.render.static import motion_statistics as stats

    times = model.train_times
    # The method's scale composition (`linear` since garo-deform took it): the statistics in log-scale offsets.
    log_scales, composition = model.scales.detach(), model.config.deform_scale_offset
    deviation, mean = stats(
        model.deformation, model.means.detach(), times, log_scales=log_scales, scale_offset=composition
    )
    size = torch.exp(log_scales + mean[:, 7:]).amax(-1)
    move = displacement(deviation, size)
    threshold = float(move.median()) / model.scene_extent
    saved = model.config.static_threshold
    calls = []
    hook = model.deformation.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    try:  # from here on the shared run's classification is changed: restored below, even when an assertion fails
        model.config.static_threshold = threshold
        model.refresh_static(times)
        fraction = model.static_fraction()
        # The classification is the measured movement against the threshold in scene units (the
        # threshold is relative to the scene extent): exactly, Gaussian by Gaussian.
        static = model.strategy_state["static"]
        assert torch.equal(static, move < threshold * model.scene_extent)
        assert fraction == static.float().mean().item() and 0 < fraction < 1
        cams = garo_run["trainer"].pipeline.datamanager.train_dataset.cameras
        calls.clear()
        with torch.no_grad():
            for i in (0, 7, 15):
                cam = cams[i : i + 1].to(model.device)
                model.config.static_skip = False
                full = model.get_outputs(cam)["rgb"]
                model.config.static_skip = True
                skip = model.get_outputs(cam)["rgb"]
                # A third of a pixel of movement: edges of the checker and stripes shift a little
                # (measured: max 0.07-0.09, PSNR between the renders 43-46 dB).
                assert (full - skip).abs().max() < 0.2
                psnr = -10 * torch.log10(((full - skip) ** 2).mean().clamp_min(1e-12))
                assert psnr > 38, float(psnr)
    finally:
        hook.remove()
        model.config.static_skip = False
        model.config.static_threshold = saved
        model.refresh_static()  # back to what training decided
    n = model.num_points
    assert calls[0] == n and calls[1] == round(n * (1 - fraction))  # the MLP ran on dynamic Gaussians only


@pytest.mark.slow
def test_in_place_static_composition_matches_the_copying_one(garo_run):
    # CUDA graphs write the dynamic rows into the cached frozen tensors; the copying path (viewer
    # cache, export) must give the same values and stay right after such writes.
    model = _eval_model(garo_run)
    model.refresh_static()
    static = torch.zeros(model.num_points, dtype=torch.bool)
    static[::2] = True  # half static, half dynamic, whatever the field does
    model.strategy_state["static"] = static
    model.config.static_skip = True
    try:
        with torch.no_grad():
            canonical = model.canonical()
            offset = model.strategy_state["static_offset"]
            key = versions(list(canonical) + list(model.deformation.parameters()) + [offset])
            settings = FrameSettings(static_skip=True)

            def deform(t, in_place=False):
                return model.frame.deform(model.deformation, canonical, static, offset, t, settings, key, in_place)

            copied = [x.clone() for x in deform(0.2)]
            placed = deform(0.2, in_place=True)
            for a, b in zip(copied, placed):
                assert torch.equal(a, b)
            deform(0.9, in_place=True)  # other values in the dynamic rows
            for a, b in zip(copied, deform(0.2)):
                assert torch.equal(a, b)
            moved = deform(0.9)[0]
            assert not torch.equal(moved[~static], copied[0][~static])  # the dynamic rows do move
            assert torch.equal(moved[static], copied[0][static])  # the static ones do not
    finally:
        model.config.static_skip = False
        model.refresh_static()


@pytest.mark.slow
def test_static_classification_survives_a_checkpoint(garo_run):
    from garo_ns.tools.eval import load_run

    model = _eval_model(garo_run)
    _, pipeline, _, _ = load_run(garo_run["config_path"])
    loaded = pipeline.model
    assert torch.equal(loaded.strategy_state["static"].cpu(), model.strategy_state["static"].cpu())
    assert loaded.static_fraction() == model.static_fraction()


@pytest.mark.slow
def test_viewer_cache_is_exact_and_invalidated(garo_run):
    model = _eval_model(garo_run)
    cam = garo_run["trainer"].pipeline.datamanager.train_dataset.cameras[3:4].to(model.device)
    calls = []
    hook = model.deformation.register_forward_hook(lambda m, i, o: calls.append(1))
    try:
        with torch.no_grad():
            first = model.get_outputs(cam)["rgb"]
            second = model.get_outputs(cam)["rgb"]
            assert len(calls) == 1 and torch.equal(first, second)  # same time: no MLP
            other = cam.to(model.device)
            other.times = torch.full_like(cam.times, 0.9)
            model.get_outputs(other)
            assert len(calls) == 2  # another time: recomputed
            model.get_outputs(cam)
            model.get_outputs(cam)
            assert len(calls) == 3
            model.means.add_(0.0)  # an in-place parameter update (what an optimizer step does)
            model.get_outputs(cam)
            assert len(calls) == 4
    finally:
        hook.remove()


@pytest.mark.slow
def test_contribution_pruning_during_training(scene_dir, tmp_path):
    from garo_ns.tools.train import QuickSchedule, make_config

    steps = 60
    config = make_config(
        "garo-deform",
        scene_dir,
        tmp_path,
        schedule=QuickSchedule(
            steps=steps,
            num_random=1500,
            deform_width=32,
            deform_depth=2,
            deform_skip=0,
            extra={"prune_contribution_ratio": 0.5, "garo_mode": "off"},
        ),
    )
    counts = {}
    trainer = None

    def record(step):
        counts[step] = trainer.pipeline.model.num_points

    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    prune_step = config.pipeline.model.prune_contribution_steps[0]
    trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record))
    trainer.train()
    # The recording callback runs before the model's own callbacks of the same step.
    assert counts[prune_step + 1] == counts[prune_step] - math.floor(0.5 * counts[prune_step])
    assert torch.isfinite(trainer.pipeline.model.means).all()


@pytest.mark.slow
def test_compact_storage_halves_the_model_and_renders_alike(garo_run, tmp_path):
    from conftest import render_view

    from garo_ns.state import storage
    from garo_ns.tools.fps import model_size_mb

    model = _eval_model(garo_run)
    cam = garo_run["trainer"].pipeline.datamanager.train_dataset.cameras[2:3].to(model.device)
    before = render_view(model, cam)
    saved = storage.snapshot(model)
    means = model.means.detach().clone()
    try:
        size = storage.save_compact(model, tmp_path / "model.pt")
        assert size == (tmp_path / "model.pt").stat().st_size
        assert size < 0.56 * model_size_mb(model) * 2**20  # half precision except positions
        storage.load_compact(model, tmp_path / "model.pt")
        assert torch.equal(model.means, means)  # positions kept exactly
        for key in ("scales", "quats", "features_dc", "opacities"):
            ref = saved[f"g.{key}"]
            assert (model.gauss_params[key] - ref).abs().max() <= 1e-3 * ref.abs().max() + 1e-6
        after = render_view(model, cam)
        assert (after - before).abs().mean() < 2e-3  # far below what training resolves
        assert not torch.equal(after, before)  # the rounding did reach the render
        assert storage.round_to_storage(model) == size  # rounding twice changes nothing
    finally:
        storage.restore(model, saved)
    assert torch.equal(render_view(model, cam), before)

    bad = storage.compact_state(model)
    bad["gauss_params.means"] = bad["gauss_params.means"][:-1]
    torch.save(bad, tmp_path / "short.pt")
    with pytest.raises(ValueError, match="gauss_params.means: file shape"):
        storage.load_compact(model, tmp_path / "short.pt")
    assert torch.equal(render_view(model, cam), before)  # a refused file leaves the model as it was


@pytest.mark.slow
def test_compact_storage_refuses_non_finite_models(garo_run, tmp_path):
    from garo_ns.state import storage

    model = _eval_model(garo_run)
    saved = storage.snapshot(model)
    try:
        with torch.no_grad():
            model.opacities[0] = float("nan")
        with pytest.raises(ValueError, match="gauss_params.opacities holds non-finite"):
            storage.save_compact(model, tmp_path / "broken.pt")
        assert not (tmp_path / "broken.pt").exists()
    finally:
        storage.restore(model, saved)


@pytest.mark.slow
def test_cuda_graph_switch_is_a_no_op_off_cuda(garo_run):
    model = _eval_model(garo_run)  # trained on the CPU, on any machine: graphs do not apply
    assert model.device.type == "cpu"
    t = 0.4
    with torch.no_grad():
        plain = model.gaussians_at(t)
        model.config.cuda_graph = True
        try:
            graphed = model.gaussians_at(t)
        finally:
            model.config.cuda_graph = False
    assert graphed.graph is None  # ordinary tensors, not a graph's buffers
    for a, b in zip(plain[:5], graphed[:5]):
        assert torch.equal(a, b)
