"""A training step without host waits keeps splatfacto's and torch's numbers: the SSIM in grouped convolutions, the
loss and PSNR without host tensors, the non-finite-loss watch read later, the step cameras read from the host copy,
fused Adam where it can run, and TF32 products only inside a training step (emulated here: the CPU has no TF32).
The densification record's dense update is tested with the strategy (tests/test_garo_strategy.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.models.splatfacto import SSIM as SplatfactoSSIM

from garo_ns.engine.losses import ImageLoss, NonFiniteWatch, psnr, scale_regularisation, step_losses
from garo_ns.engine.ssim import SSIM
from garo_ns.errors import GaroTrainingError


def _pair(shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g)
    return x, (x + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)


@pytest.mark.parametrize("shape", [(1, 3, 64, 80), (2, 3, 33, 17), (1, 3, 9, 40), (1, 1, 12, 12)])
def test_ssim_is_splatfactos_value_and_gradient(shape):
    """Splatfacto's SSIM (pytorch_msssim) to float rounding: value within 1e-6, gradient within 1e-6 of its
    largest entry; a height under the window (9 < 11) is blurred along the width only, as pytorch_msssim does."""
    x, y = _pair(shape)
    x.requires_grad_(True)
    ref = SplatfactoSSIM(data_range=1.0, size_average=True, channel=shape[1])
    with pytest.warns(UserWarning) if shape[2] < 11 else _no_warning():
        want = ref(x, y)
    got = SSIM(data_range=1.0)(x, y)
    assert abs(float(got) - float(want)) < 1e-6
    (g_want,) = torch.autograd.grad(want, x)
    (g_got,) = torch.autograd.grad(got, x)
    assert (g_got - g_want).abs().max() <= 1e-6 * g_want.abs().max() + 1e-12


class _no_warning:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_ssim_refuses_images_of_two_shapes():
    with pytest.raises(ValueError, match="one shape"):
        SSIM()(torch.rand(1, 3, 20, 20), torch.rand(1, 3, 20, 21))


def test_step_losses_are_splatfactos_terms():
    gt, pred = (t[0].permute(1, 2, 0) for t in _pair((1, 3, 40, 48), seed=1))
    mask = (torch.rand(40, 48, 1, generator=torch.Generator().manual_seed(2)) > 0.3).float()
    lam = 0.2
    losses = step_losses(gt, pred, ImageLoss(SSIM(), lam, graphed=True), mask)  # graphed: on CUDA only
    gm, pm = gt * mask, pred * mask
    ssim = SplatfactoSSIM(data_range=1.0, size_average=True, channel=3)(
        gm.permute(2, 0, 1)[None], pm.permute(2, 0, 1)[None]
    )
    want = (1 - lam) * (gm - pm).abs().mean() + lam * (1 - ssim)
    assert abs(float(losses["main_loss"]) - float(want)) < 1e-6
    assert float(losses["scale_reg"]) == 0.0


def test_scale_regularisation_is_splatfactos():
    log_scales = torch.log(torch.tensor([[1.0, 1.0, 1.0], [1.0, 20.0, 1.0], [0.1, 0.1, 3.0]]))
    # splatfacto: 0.1 * mean(max(ratio, r) - r) with ratio = largest / smallest scale
    ratio = torch.tensor([1.0, 20.0, 30.0])
    want = 0.1 * (torch.maximum(ratio, torch.tensor(10.0)) - 10.0).mean()
    assert torch.allclose(scale_regularisation(log_scales, 10.0), want, rtol=1e-5)


def test_psnr_is_torchmetrics():
    from torchmetrics.image import PeakSignalNoiseRatio

    pred, gt = _pair((24, 30, 3), seed=3)
    assert abs(float(psnr(pred, gt)) - float(PeakSignalNoiseRatio(data_range=1.0)(pred, gt))) < 1e-4


def test_the_watch_stops_at_the_step_itself_on_the_cpu():
    watch = NonFiniteWatch(every=50)
    watch.observe(torch.tensor(0.5), 24)
    with pytest.raises(GaroTrainingError, match="non-finite loss at step 25"):
        watch.observe(torch.tensor(math.nan), 25)


def test_the_deferred_watch_names_the_first_bad_step_when_it_reads():
    watch = NonFiniteWatch(every=10, defer=True)
    for step in range(1, 7):
        watch.observe(torch.tensor(1.0), step)
    watch.observe(torch.tensor(math.inf), 7)  # not read yet: no step waits for the device
    watch.observe(torch.tensor(math.nan), 8)
    watch.observe(torch.tensor(1.0), 9)
    with pytest.raises(GaroTrainingError, match="non-finite loss at step 7;"):
        watch.observe(torch.tensor(1.0), 10)
    watch.observe(torch.tensor(1.0), 11)
    watch.check()  # a fresh window: nothing since


def test_a_checkpoint_is_not_written_after_an_unread_non_finite_loss(tmp_path):
    from garo_ns.state.checkpoints import _trainer_save_checkpoint

    watch = NonFiniteWatch(every=1000, defer=True)
    watch.observe(torch.tensor(math.nan), 3)
    model = torch.nn.Linear(2, 2)
    model.loss_watch = watch
    trainer = SimpleNamespace(
        pipeline=SimpleNamespace(model=model, state_dict=model.state_dict),
        optimizers=SimpleNamespace(optimizers={}, schedulers={}),
        grad_scaler=torch.amp.GradScaler("cpu", enabled=False),
        checkpoint_dir=tmp_path,
        config=SimpleNamespace(save_only_latest_checkpoint=True),
    )
    with pytest.raises(GaroTrainingError, match="step 3"):
        _trainer_save_checkpoint(trainer, 4)
    assert list(tmp_path.iterdir()) == []
    _trainer_save_checkpoint(trainer, 5)  # read and cleared: the next checkpoint is written
    assert len(list(tmp_path.iterdir())) == 1


def test_adam_is_fused_only_on_cuda_and_updates_as_torchs():
    from garo_ns.config import AdamConfig

    p = torch.nn.Parameter(torch.randn(30, 3))
    q = torch.nn.Parameter(p.detach().clone())
    ours = AdamConfig(lr=1e-2, eps=1e-15).setup([p])
    ref = torch.optim.Adam([q], lr=1e-2, eps=1e-15)
    assert not ours.defaults["fused"]
    for _ in range(3):
        for param, opt in ((p, ours), (q, ref)):
            opt.zero_grad()
            (param**2).sum().backward()
            opt.step()
    assert torch.equal(p, q)


def _model(**settings):
    from nerfstudio.data.scene_box import SceneBox

    from garo_ns.garo_model import GaroModelConfig

    cfg = GaroModelConfig(
        num_random=200, deform_width=16, deform_depth=2, deform_skip=0, deform_warmup=0, sh_degree=0,
        rasterizer="reference", **settings,
    )  # fmt: skip
    return cfg.setup(scene_box=SceneBox(torch.tensor([[-1.5] * 3, [1.5] * 3])), num_train_data=3, metadata={})


def _cameras(fx):
    from nerfstudio.cameras.cameras import Cameras

    c2w = torch.eye(4)[:3].expand(len(fx), 3, 4).clone()
    c2w[:, 2, 3] = 4.0
    return Cameras(
        camera_to_worlds=c2w, fx=torch.tensor(fx)[:, None], fy=torch.tensor(fx)[:, None], cx=16.0, cy=12.0,
        width=32, height=24, times=torch.tensor([[0.1], [0.5], [0.9]]),
    )  # fmt: skip


def test_a_training_step_reads_its_camera_from_the_host_copy():
    model = _model()
    from garo_ns.render.view import HostCameras

    model.step_cameras = HostCameras(_cameras([30.0, 40.0, 50.0]))
    cam = _cameras([99.0, 99.0, 99.0])[1:2]
    cam.metadata = {"cam_idx": 2}
    model.train()
    assert model.camera_view(cam).K[0, 0, 0] == 50.0  # the host copy's camera 2
    model.eval()
    assert model.camera_view(cam).K[0, 0, 0] == 99.0  # outside training: the camera given
    model.train()
    cam.metadata = {}
    assert model.camera_view(cam).K[0, 0, 0] == 99.0  # no index: the camera given
    cam.metadata = {"cam_idx": 7}
    assert model.camera_view(cam).K[0, 0, 0] == 99.0  # no such host camera: the camera given


@pytest.mark.parametrize("tf32", [True, False])
def test_tf32_products_only_inside_a_training_step(tf32):
    model = _model(deform_train_tf32=tf32)
    model.step_cb(SimpleNamespace(optimizers={}), 1)
    cam = _cameras([30.0, 30.0, 30.0])[0:1]
    model.eval()
    model.get_outputs(cam)
    assert torch.backends.cuda.matmul.allow_tf32 is False
    model.train()
    out = model.get_outputs(cam)
    assert torch.backends.cuda.matmul.allow_tf32 is tf32  # the forward and the backward that follows
    out["rgb"].mean().backward()
    torch.backends.cuda.matmul.allow_tf32 = True
    model.after_iteration(1)  # the step's update is done: exact products for whatever comes next
    assert torch.backends.cuda.matmul.allow_tf32 is False


def _tf32(x: torch.Tensor) -> torch.Tensor:
    """x rounded to TF32 (10 explicit mantissa bits, round to nearest even), as tensor cores read fp32 inputs."""
    bits = x.contiguous().view(torch.int32)
    rounded = (bits + 0x0FFF + ((bits >> 13) & 1)) & ~0x1FFF
    return rounded.view(torch.float32)


def test_the_fields_offsets_under_tf32_inputs_move_by_under_1e4_scene_units():
    """What TF32 does to the field's numbers (inputs of every product rounded to 10 mantissa bits, fp32 sums), on
    the D-3DGS-sized field: the offsets move by under 1e-4 scene units, far below what a training step resolves
    (the model is scored and rendered in fp32)."""
    from garo_ns.deformation import DeformationField

    torch.manual_seed(0)
    field = DeformationField(time_net=30)
    xyz = torch.rand(2000, 3) * 2 - 1

    def rounded(module, args):
        return (_tf32(args[0]),)

    want = torch.cat(field(xyz, 0.37), dim=-1)
    saved = {}
    hooks = []
    for m in field.modules():
        if isinstance(m, torch.nn.Linear):
            saved[m] = m.weight.detach().clone()
            m.weight.data = _tf32(m.weight.data)
            hooks.append(m.register_forward_pre_hook(rounded))
    got = torch.cat(field(xyz, 0.37), dim=-1)
    for h in hooks:
        h.remove()
    for m, w in saved.items():
        m.weight.data = w
    err = (got - want).abs().amax(0)  # per channel, the largest over 2,000 Gaussians
    assert 0 < float(err.max()) < 1e-4  # scene units: a 200,000th of the D-NeRF extent (about 5), 0.01 px at 800 px
    assert (err / want.pow(2).mean(0).sqrt()).max() < 5e-3  # and within 0.5% of each channel's RMS offset
    assert float(_tf32(torch.tensor([1.0 + 2**-11]))) == 1.0 and float(_tf32(torch.tensor([1.0 + 2**-10]))) > 1.0


def test_a_training_run_reuses_one_device_camera_per_view_in_the_datamanagers_order(scene_dir, tmp_path):
    import copy

    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager

    from garo_ns.tools.train import QuickSchedule, make_config

    config = make_config("garo-deform", scene_dir, tmp_path, schedule=QuickSchedule(steps=10), experiment_name="x")
    config.set_timestamp()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    dm = trainer.pipeline.datamanager
    assert dm._step_cameras_reused and dm.next_train is not FullImageDatamanager.next_train
    steps = 2 * len(dm.train_dataset) + 3  # across two epochs' orders
    start = (list(dm.train_unseen_cameras), copy.deepcopy(getattr(dm, "random_generator", None)))
    ours = [dm.next_train(s) for s in range(steps)]
    dm.train_unseen_cameras, dm.random_generator = list(start[0]), start[1]
    theirs = [FullImageDatamanager.next_train(dm, s) for s in range(steps)]
    for (cam, data), (ref_cam, ref_data) in zip(ours, theirs):
        assert cam.metadata["cam_idx"] == ref_cam.metadata["cam_idx"]
        assert torch.equal(cam.camera_to_worlds, ref_cam.camera_to_worlds) and torch.equal(cam.times, ref_cam.times)
        assert torch.equal(cam.fx, ref_cam.fx) and torch.equal(data["image"], ref_data["image"])
        assert set(data) == set(ref_data)
    indices = [cam.metadata["cam_idx"] for cam, _ in ours]
    assert len(set(indices)) == len(dm.train_dataset)  # every view came, and each view's camera is one object
    assert all(ours[i][0] is ours[j][0] for i in range(steps) for j in range(steps) if indices[i] == indices[j])


def test_a_datamanager_of_another_kind_keeps_its_own_next_train():
    from types import SimpleNamespace

    from garo_ns.engine.training_data import reuse_step_cameras

    other = SimpleNamespace(next_train=lambda step: ("camera", {}))
    assert not reuse_step_cameras(other) and not reuse_step_cameras(SimpleNamespace())
    assert other.next_train(0) == ("camera", {})


def test_graphed_splats_off_the_gpu_are_the_composed_gaussians():
    """CPU runs (and CI) take the eager composition whatever the setting: the same tensors, bit for bit."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats
    from garo_ns.render.frame import Canonical, activate, compose

    torch.manual_seed(0)
    field = DeformationField(time_net=30).train()
    canonical = Canonical(
        *(torch.randn(*s).requires_grad_(True) for s in ((50, 3), (50, 4), (50, 3), (50, 1), (50, 3), (50, 15, 3)))
    )
    graphed = GraphedSplats(lambda: field, enabled=True)
    got = graphed(canonical, 0.3, "log")
    want = activate(canonical, compose(field, canonical, 0.3, "log"))
    assert graphed.captures == 0 and all(torch.equal(a, b) for a, b in zip(got[:5], want[:5]))


@pytest.mark.parametrize("fused", [False, True])
def test_the_functional_splats_are_the_modules_and_send_gradients_to_the_tensors_passed(fused):
    """`functional_splats`: the step's Gaussians with the field's parameters as arguments are the module's call, to
    the bit; gradients reach the tensors passed (the real parameters at a step, stand-ins at a capture) and nothing
    else, stand-ins reading their parameters' storage."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import _SplatsCall, functional_splats
    from garo_ns.render.frame import Canonical

    torch.manual_seed(3)
    field = DeformationField(depth=3, width=16, time_net=8, fused_layers=fused)
    call = _SplatsCall(field, "log")
    function, params = functional_splats(call)
    assert [id(p) for p in params] == [id(p) for p in field.parameters()]
    n = 50
    canonical = Canonical(
        torch.rand(n, 3),
        torch.randn(n, 4),
        -3 + 0.3 * torch.randn(n, 3),
        torch.randn(n, 1),
        torch.randn(n, 3),
        0.1 * torch.randn(n, 15, 3),
    )
    t = torch.full((1, 1), 0.6)
    want = call(*canonical, t)
    got = function(*canonical, t, *params)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    stand_ins = [p.detach().requires_grad_(True) for p in params]
    sum(o.square().sum() for o in function(*canonical, t, *stand_ins)).backward()
    assert all(p.grad is None for p in params) and all(s.grad is not None for s in stand_ins)
    sum(o.square().sum() for o in want).backward()
    assert all(torch.equal(p.grad, s.grad) for p, s in zip(params, stand_ins))
    with torch.no_grad():
        params[0].add_(1.0)  # an optimizer's in-place update
    assert torch.equal(stand_ins[0], params[0])


def test_attached_gradient_buffers_hold_what_grad_held():
    """`attach_gradients`: each buffer becomes its parameter's `.grad` holding what that held (zero for None,
    a copy of another tensor, itself untouched when already attached), so adding into the buffers accumulates."""
    from garo_ns.engine.train_graphs import attach_gradients

    params = [torch.zeros(3, requires_grad=True) for _ in range(3)]
    buffers = [torch.full((3,), 9.0) for _ in range(3)]
    params[1].grad = torch.tensor([1.0, 2.0, 3.0])
    params[2].grad = buffers[2]
    buffers[2].fill_(5.0)
    attach_gradients(params, buffers)
    assert all(p.grad is b for p, b in zip(params, buffers))
    assert buffers[0].tolist() == [0.0, 0.0, 0.0]
    assert buffers[1].tolist() == [1.0, 2.0, 3.0]
    assert buffers[2].tolist() == [5.0, 5.0, 5.0]
    for b in buffers:
        b.add_(1.0)  # what the graph's backward does
    params[0].grad = None  # an optimizer's zero_grad
    attach_gradients(params, buffers)
    assert [b.tolist()[0] for b in buffers] == [0.0, 2.0, 6.0]


def test_training_metrics_are_computed_on_the_trainers_log_steps_only(scene_dir, tmp_path):
    from garo_ns.tools.train import QuickSchedule, make_config

    config = make_config("garo-deform", scene_dir, tmp_path, schedule=QuickSchedule(steps=10), experiment_name="x")
    config.set_timestamp()
    config.logging.steps_per_log = 3
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    logged = []
    for step in range(7):
        model.step_cb(trainer.optimizers, step)  # what the trainer runs before each step
        _, _, metrics = trainer.pipeline.get_train_loss_dict(step=step)
        assert metrics["gaussian_count"] == model.num_points
        if "psnr" in metrics:
            assert math.isfinite(float(metrics["psnr"]))
            logged.append(step)
    assert logged == [0, 3, 6]  # the steps the trainer writes metrics on (step_check with run_at_zero)
    model.eval()  # outside training: always
    assert "psnr" in model.get_metrics_dict(*_outputs_and_batch(trainer))
    assert model.train_splats.enabled and model.train_splats.bf16  # garo-deform's recipe: graphed, bf16 products
    from garo_ns.config import METHODS

    # Each measured at 40k on three scenes; the methods without their own A/B keep fp32 and the plain layers.
    assert model.deformation.fused_layers
    assert model.deformation.fp32_heads and model.config.deform_scale_offset == "linear"  # ab_fp32_heads_H200
    baseline = METHODS["deform-splatfacto"].config.pipeline.model  # the official composition, in fp32
    assert not baseline.deform_train_bf16 and baseline.deform_scale_offset == "linear"
    assert not baseline.deform_fused_layers
    compact = METHODS["garo-compact"].config.pipeline.model
    assert not compact.deform_train_bf16 and not compact.deform_fused_layers and compact.deform_scale_offset == "log"

    assert model.train_splats.own_grads  # deform_graph_grads: our own capture, on one stream
    config.pipeline.model.deform_train_bf16 = False
    config.pipeline.model.deform_cuda_graph = False
    config.pipeline.model.deform_graph_grads = False
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    splats = trainer.pipeline.model.train_splats
    assert not splats.bf16 and not splats.enabled and not splats.own_grads


def _outputs_and_batch(trainer):
    camera, batch = trainer.pipeline.datamanager.next_train(0)
    with torch.no_grad():
        return trainer.pipeline.model.get_outputs(camera), batch


@pytest.mark.parametrize("fused", [False, True])
def test_the_bf16_field_stays_near_the_fp32_field_and_keeps_fp32_weights(fused):
    """`deform_train_bf16`'s numerics against the fp32 reference, here under the CPU's bf16 autocast (the same
    rounding of the products' inputs as CUDA's): on the recipe's field at its initialisation the offsets differ by
    about 0.3% of their norm (bound 1%), each parameter's gradient points the same way (cosine >= 0.98; the
    smallest is about 0.992); the weights the optimizer steps stay fp32 and the offsets come back in fp32. The same
    with the fused layers (garo_ns.ops.dense), whose casts are their own."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import Bf16Field

    torch.manual_seed(0)
    field = DeformationField(fused_layers=fused).train()
    xyz, t = torch.rand(4000, 3) * 2 - 1, 0.37
    weights = [torch.randn(4000, k) for k in (3, 4, 3)]

    def run(module):
        out = module(xyz, t)
        loss = sum((o * w).sum() for o, w in zip(out, weights))
        return out, torch.autograd.grad(loss, list(field.parameters()))

    (want, want_grads), (got, got_grads) = run(field), run(Bf16Field(field))
    assert all(o.dtype == torch.float32 for o in got) and all(p.dtype == torch.float32 for p in field.parameters())
    for a, b in zip(got, want):
        assert float((a - b).norm() / b.norm()) < 1e-2 and not torch.equal(a, b)  # bf16 did run
    for a, b in zip(got_grads, want_grads):
        assert float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)) >= 0.98


def test_bf16_training_leaves_a_cpu_step_in_fp32():
    """The setting is for CUDA's tensor cores: off the GPU the step's Gaussians are the fp32 composition."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats
    from garo_ns.render.frame import Canonical, activate, compose

    torch.manual_seed(0)
    field = DeformationField(time_net=30).train()
    canonical = Canonical(
        *(torch.randn(*s).requires_grad_(True) for s in ((50, 3), (50, 4), (50, 3), (50, 1), (50, 3), (50, 15, 3)))
    )
    graphed = GraphedSplats(lambda: field, enabled=True, bf16=True)
    got = graphed(canonical, 0.3, "log")
    want = activate(canonical, compose(field, canonical, 0.3, "log"))
    assert all(torch.equal(a, b) for a, b in zip(got[:5], want[:5]))
