"""Deformable Gaussian splatting model: splatfacto plus D-3DGS's deformation field (nerfstudio glue).

Canonical Gaussians live in `gauss_params` as in splatfacto; `gaussians_at` moves them to a time (the one way
to get the Gaussians at a time). Elsewhere: the settings (`recipe` and the modules they configure), the starting
Gaussians (`initialisation`), what it takes from its training data (`training_data`), every change of their
count (`GaroStrategy`), rendering (`render`, the outputs of a camera in `render.outputs`), the static
classification (`static`), the field (`deformation`) and checkpoints of earlier versions (`checkpoints`).
Changes to splatfacto a user may notice are documented on the settings they come from.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.models.splatfacto import SplatfactoModel
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.nn import Parameter

from garo_ns.compaction.guard import TrainingViewGuard
from garo_ns.compaction.schedule import CompactionSettings
from garo_ns.compaction.training import fixed_ratio_round, run_round
from garo_ns.deformation import DeformationSettings, time_noise
from garo_ns.engine import scoring
from garo_ns.engine.callbacks import after_strategy, check_health, refresh_static, training_callbacks
from garo_ns.engine.initialisation import initial_gaussians
from garo_ns.engine.losses import ImageLoss, NonFiniteWatch
from garo_ns.engine.metrics import metric_modules
from garo_ns.engine.recipe import D3dgsRecipe
from garo_ns.engine.ssim import SSIM
from garo_ns.engine.train_graphs import GraphedSplats
from garo_ns.engine.training_data import adopt_training_data
from garo_ns.garo_strategy import GaroSettings, GaroStrategy, garo_scalars
from garo_ns.ops.collector import TrainingCollector
from garo_ns.render.backend import Backend
from garo_ns.render.contribution import summed_contribution
from garo_ns.render.frame import Canonical, FramePath, FrameSettings, Splats, activate, compose, render_splats
from garo_ns.render.graphs import parameter_list
from garo_ns.render.outputs import camera_outputs
from garo_ns.render.static import StaticSettings, static_fraction
from garo_ns.render.switches import RenderSettings, SwitchDecision
from garo_ns.render.view import HostCameras, RenderView, camera_numbers, camera_view
from garo_ns.state import checkpoints


@dataclass
class GaroModelConfig(
    D3dgsRecipe, DeformationSettings, StaticSettings, RenderSettings, CompactionSettings, GaroSettings
):
    """Deformable splatfacto with D-3DGS's training recipe and optional GARO pruning. Each group of
    settings is declared with what it configures: D-3DGS's schedule (garo_ns.engine.recipe), the deformation
    field (garo_ns.deformation), the static classification (garo_ns.render.static), rendering and its speed
    switches (garo_ns.render.switches), compaction (garo_ns.compaction.schedule) and GARO
    (garo_ns.garo_strategy); the flags are flat (`--pipeline.model.<setting>`)."""

    _target: Type = field(default_factory=lambda: GaroModel)

    def __post_init__(self) -> None:
        # A recipe, compaction or GARO setting out of range fails here, before any training.
        self.validate_recipe()
        self.validate_deformation()
        self.compaction()
        self.validate_garo()

    def make_strategy(self) -> GaroStrategy:
        """The densification and GARO strategy these settings describe."""
        compaction = self.compaction() if self.compact else None
        return GaroStrategy(**self.densification_arguments(), **self.garo_arguments(), compaction=compaction)


class GaroModel(SplatfactoModel):
    """Splatfacto with a D-3DGS deformation field and a GARO-capable densification strategy."""

    config: GaroModelConfig

    # ------------------------------------------------------------------ set-up
    def populate_modules(self) -> None:
        checkpoints.install()  # ns-viewer's checkpoint loader exists only now (see checkpoints.install)
        cfg = self.config
        metadata: Dict[str, Any] = dict(self.kwargs.get("metadata") or {})
        self.scene_extent = cfg.extent_for(metadata)
        start = initial_gaussians(self.seed_points, cfg.random_init, cfg.num_random, cfg.random_scale, cfg.sh_degree)
        self.gauss_params = torch.nn.ParameterDict({k: Parameter(v) for k, v in start.items()})
        self.deformation = cfg.make_deformation()
        self.camera_optimizer = cfg.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        self.psnr, self.ssim, lpips = metric_modules()
        self.loss_watch = NonFiniteWatch()
        # The loss's own SSIM (a module, so its window moves with the model): fused kernels where they run.
        self.loss_ssim = SSIM(data_range=1.0, fused=cfg.fused_ssim)
        self.image_loss = ImageLoss(self.loss_ssim, cfg.ssim_lambda, cfg.loss_cuda_graph)
        self.train_splats = GraphedSplats(
            lambda: self.deformation, cfg.deform_cuda_graph, cfg.deform_train_bf16, cfg.deform_graph_grads
        )
        self.collector = TrainingCollector(cfg.gc_threshold)  # Python's collector paced to training (set on step 1)
        # The dataset's cameras on the host: a training step reads its camera's numbers there
        # (garo_ns.engine.training_data).
        self.step_cameras: Optional[HostCameras] = None
        self._lpips = [lpips]  # out of the module tree: LPIPS may be absent, checkpoints must not need it
        self.step = 0
        self.crop_box = None
        self._warned_no_time = False
        # A buffer, so the background the model was trained on travels with its checkpoints.
        self.register_buffer("background_rgb", cfg.background_for(metadata).clone())
        # Set by the config or the dataparser: the training cameras do not replace it (garo_ns.engine.training_data).
        self.extent_fixed = cfg.scene_extent is not None or "camera_extent" in metadata
        self.strategy = cfg.make_strategy()
        self.compaction_guard: Optional[TrainingViewGuard] = None  # training views compaction is judged on
        self.switch_guard: Optional[TrainingViewGuard] = None  # training views the render switches are measured on
        self.training_run = False  # set when the model gets training callbacks
        # What each approximate switch cost, and what that decides, for these Gaussians and this field.
        self.switches = SwitchDecision(
            lambda: self.step, lambda: [*self.canonical(), *parameter_list(self.deformation)]
        )
        self.frame = FramePath()
        self.switches.table_failure, self.switches.table_built = self.frame.table_failures.get, self.frame.built_info
        for warning in checkpoints.upgrade_render_settings(cfg):  # an old config.yml naming a deleted setting
            CONSOLE.print(f"[yellow]{warning}[/yellow]")
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.scene_extent)
        self.train_times: Optional[Tensor] = None
        self.train_cameras: Optional[Cameras] = None
        self.last_step: Optional[int] = None
        self.metrics_every = 1  # the trainer's steps_per_log, once training starts
        self.frame.configure(cfg)
        self.health_log: List[Dict[str, Any]] = []

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = self.get_gaussian_param_groups()
        groups["deformation"] = list(self.deformation.parameters())
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    @property
    def background_color(self) -> Tensor:  # type: ignore[override]
        """The render background (the data's alpha colour); stored in checkpoints."""
        return self.background_rgb

    @background_color.setter
    def background_color(self, value: Tensor) -> None:
        self.background_rgb.copy_(torch.as_tensor(value, dtype=torch.float32).reshape(3))

    def adopt_training_data(self, pipeline: Any) -> None:
        """Make the model agree with its training data whatever the dataparser (garo_ns.engine.training_data)."""
        adopt_training_data(self, pipeline)

    # ------------------------------------------------------------------ training callbacks
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        return training_callbacks(self, training_callback_attributes)

    def step_cb(self, optimizers: Optimizers, step: int) -> None:
        self.collector.start()  # from the first step on (a no-op after it); given back after the last
        self.step = step
        self.optimizers = optimizers.optimizers

    def after_iteration(self, step: int) -> None:
        """The strategy (densification, GARO, contribution pruning, compaction), then the static
        classification, then the deformation field's health check."""
        torch.backends.cuda.matmul.allow_tf32 = False  # the step's products are done (see get_outputs)
        self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step, self.info)
        for name, value in garo_scalars(self.strategy_state, step).items():
            writer.put_scalar(name=name, scalar=value, step=step)
        fixed_ratio_round(self, step)  # the expert knob prune_contribution_ratio, when set
        run_round(self, step, self.last_step)  # compaction (garo_ns.compaction), when configured
        after_strategy(self, step)

    def check_health(self, step: int) -> None:
        """The deformation field's health check when due (garo_ns.engine.callbacks.check_health)."""
        check_health(self, step)

    # ------------------------------------------------------------------ the Gaussians at a time
    def deformation_active(self) -> bool:
        """Whether the deformation field is applied at the current step (after the static warm-up)."""
        return self.step >= self.config.deform_warmup

    def canonical(self) -> Canonical:
        """The parameters as stored (canonical geometry, log-scales, opacity logits, SH)."""
        p = self.gauss_params._parameters  # the dict itself: through the properties, a third of a frame's host time
        return Canonical(p["means"], p["quats"], p["scales"], p["opacities"], p["features_dc"], p["features_rest"])

    def gaussians_at(self, time: float, exact: bool = False, settings: Optional[FrameSettings] = None) -> Splats:
        """The Gaussians at `time`, as the rasterizer takes them: the one way to get them (training,
        rendering, export, timing). Training: the D-3DGS composition in fp32 (with the time noise, if
        set). Otherwise the frame path with the render switches, or with `exact` the field as trained
        (fp32, every Gaussian), whatever the switches; `settings` replaces the config's switches."""
        cfg, canonical = self.config, self.canonical()
        if not self.deformation_active():
            return activate(canonical, (canonical.means, canonical.quats, canonical.log_scales))
        if self.training or exact:
            frames = len(self.train_times) if self.train_times is not None else 1
            time = time + time_noise(cfg.time_noise, cfg.time_noise_steps, self.step, frames, self.training)
            if self.training:  # the step's CUDA graph where it applies, else the eager composition
                return self.train_splats(canonical, time, cfg.deform_scale_offset)
            return activate(canonical, compose(self.deformation, canonical, time, cfg.deform_scale_offset))
        state = self.strategy_state
        with self.switches.one_frame([*canonical, *parameter_list(self.deformation)]) as params:
            settings = self.render_settings() if settings is None else settings
            static, offset, table = state["static"], state["static_offset"], self.switches.table_spec()
        return self.frame.splats(self.deformation, canonical, static, offset, time, settings, table, params)

    def render_settings(self) -> FrameSettings:
        """The render switches outside training: the config's, those left to None decided by
        garo_ns.render.switches (from the losses recorded at the end of training)."""
        return self.switches.settings(self.config, self.training_run, self.device)

    def render_switch_summary(self) -> Dict[str, Any]:
        """The switches in use and what each approximate one was measured to change (garo-eval's JSON)."""
        return self.switches.summary(self.config, self.training_run, self.device)

    # ------------------------------------------------------------------ static classification
    def static_fraction(self) -> Optional[float]:
        """Share of Gaussians currently classified static, or None before any classification."""
        return static_fraction(self.strategy_state.get("static"), self.num_points)

    def refresh_static(self, times: Optional[Tensor] = None) -> None:
        """Re-decide which Gaussians are static, at `times` (garo_ns.engine.callbacks.refresh_static)."""
        refresh_static(self, times)

    def contribution(self, cameras: Cameras) -> Tensor:
        """Summed blending weight of every Gaussian over `cameras`, each at its own time [N]."""
        views = (self.camera_view(cameras[i : i + 1].to(self.device)) for i in range(cameras.shape[0]))
        return summed_contribution(
            views, lambda t: self.gaussians_at(t, exact=True), self.num_points, self.device, self.config.rasterizer
        )

    # ------------------------------------------------------------------ rendering
    def camera_view(self, camera: Cameras, c2w: Optional[Tensor] = None) -> RenderView:
        """`camera` (one) as the rasterizer takes it, at this step's resolution and the camera's time
        (`default_time`, warned once, when it has none); `c2w` replaces its pose (the camera
        optimizer's correction during training)."""
        idx = (camera.metadata or {}).get("cam_idx") if self.training and self.step_cameras is not None else None
        numbers = self.step_cameras.numbers(int(idx), self._get_downscale_factor()) if idx is not None else None
        numbers = numbers or camera_numbers(camera, self._get_downscale_factor())
        time = numbers[3]
        if time is None:
            if not self._warned_no_time:
                CONSOLE.print(
                    f"[yellow]Camera carries no time; rendering at default_time={self.config.default_time}[/yellow]"
                )
                self._warned_no_time = True
            time = float(self.config.default_time)
        c2w = camera.camera_to_worlds if c2w is None else c2w
        return camera_view(camera, c2w, self._get_downscale_factor(), self.device, time, numbers)

    def render(
        self,
        view: RenderView,
        render_mode: str = "RGB",
        backgrounds: Optional[Tensor] = None,
        splats: Optional[Splats] = None,
    ) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
        """Rasterize `splats` (default: the Gaussians at `view.time`): render [1, H, W, C], alpha
        [1, H, W, 1] and the rasterizer's info. Outside training through the frame path."""
        splats = self.gaussians_at(view.time) if splats is None else splats
        degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        backend: Backend = self.config.rasterizer
        if self.training:
            return render_splats(splats, view, degree, backgrounds, render_mode, backend, self.config.train_lean_raster)
        lean = bool(self.render_settings().lean_raster)
        return self.frame.rasterize(
            splats, view, degree, backgrounds, render_mode, backend, lean, self.config.frame_graph
        )

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:
        if not isinstance(camera, Cameras):
            raise TypeError(f"get_outputs needs a Cameras object, got {type(camera).__name__}")
        if camera.shape[0] != 1:
            raise ValueError(f"renders one camera at a time, got {camera.shape[0]}")
        # cuBLAS reads this flag when each product runs, the backward's included: on from a training step's forward
        # until its update is done (after_iteration), off for every other render.
        torch.backends.cuda.matmul.allow_tf32 = self.training and self.config.deform_train_tf32
        c2w = self.camera_optimizer.apply_to_camera(camera) if self.training else camera.camera_to_worlds
        view = self.camera_view(camera, c2w)
        splats = self.gaussians_at(view.time)
        if self.crop_box is not None and not self.training:
            keep = self.crop_box.within(splats.means).squeeze()
            if keep.sum() == 0:
                return self.get_empty_outputs(view.width, view.height, self.background_color)
            splats = splats.select(keep)
        self.last_size = (view.height, view.width)
        render_mode = "RGB+ED" if (self.config.output_depth_during_training or not self.training) else "RGB"
        render, alpha, info = self.render(view, render_mode, splats=splats)
        # The geometry GARO measures, for the strategy (no copies: detached views).
        info.update(means3d=splats.means.detach(), quats3d=splats.quats.detach(), scales3d=splats.scales.detach())
        self.info = info
        if self.training:
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step, info)
        background = self.background_color.to(self.device)
        return camera_outputs(render, alpha, background, render_mode == "RGB+ED", self.training)

    # ------------------------------------------------------------------ losses and metrics (garo_ns.engine.scoring)
    def ground_truth(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Tensor:
        """The batch's image at the render's resolution, composited on the render's background [H, W, 3]."""
        return self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Any]:
        return scoring.metrics_dict(self, outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        return scoring.loss_dict(self, outputs, batch)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        return scoring.image_metrics_and_images(self, outputs, batch)

    # ------------------------------------------------------------------ checkpoints
    def update_to_step(self, step: int) -> None:
        self.step = step

    def load_state_dict(self, state_dict, strict: bool = True, **kwargs):  # type: ignore[override]
        """Resize the Gaussians in place to the checkpoint's count, then load.

        In place (same Parameter objects), so optimizers built before loading stay bound to the
        loaded Gaussians; the step is the checkpoint's, set through `update_to_step`.
        """
        checkpoints.fit_model_to(self, state_dict)  # older checkpoints' keys, its count, its field
        result = torch.nn.Module.load_state_dict(self, state_dict, strict=strict)
        # Decided only now: torch restores the extra state (the record) before the Gaussians and the field.
        self.switches.parameters_changed()
        if not self.training:  # loaded to render (ns-viewer, ns-render, garo-eval load in eval mode)
            self.build_time_table()
            line = self.switches.line(self.config, self.training_run, self.device)
            CONSOLE.print(f"[yellow]{line}[/yellow]" if self.switches.failed_table() else line, soft_wrap=True)
        return result

    @torch.no_grad()
    def build_time_table(self) -> None:
        """Build the time table now if this model renders with one: a loaded model builds it at load, not in its first
        frame, where the viewer interrupts a render whenever the camera or the time moves (a build cut short there
        starts over, and meanwhile no frame arrives)."""
        spec = self.switches.table_spec()
        if spec is not None and self.deformation_active() and self.render_settings().time_table:
            self.frame.time_table(self.deformation, self.canonical(), spec)  # a failure: switches.failed_table()

    def get_extra_state(self) -> Dict[str, Any]:
        """What travels with the checkpoint besides the parameters (garo_ns.state.checkpoints.extra_state)."""
        return checkpoints.extra_state(self)

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        checkpoints.restore_extra_state(self, state)
