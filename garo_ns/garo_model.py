"""Deformable Gaussian splatting model: splatfacto plus D-3DGS's deformation field (nerfstudio glue).

Canonical Gaussians live in `gauss_params` as in splatfacto; `gaussians_at` moves them to a time (the one way
to get the Gaussians at a time). Elsewhere: the starting Gaussians (`initialisation`), every change of their
count (`GaroStrategy`), rendering (`render`: a camera's view, the fast frame path outside training), the static
classification (`static`), the field with its time noise and health check (`deformation`), and the state of
checkpoints written by earlier versions (`checkpoints`).

Changes to splatfacto that a user may notice (each documented on its config field): D-3DGS's densification
defaults, scaled by the 3DGS camera extent from the dataparser; the background is the data's alpha colour;
LPIPS only when its weights are available offline; checkpoints keep the real step and the strategy's state,
and optimizers stay bound to the loaded Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils import writer
from nerfstudio.utils.colors import get_color
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.nn import Parameter

from garo_ns import checkpoints
from garo_ns.compaction.guard import TrainingViewGuard
from garo_ns.compaction.schedule import Compaction
from garo_ns.compaction.training import run_round
from garo_ns.deformation import DeformationField, collapse_warning, health_check, health_due, time_noise
from garo_ns.errors import GaroTrainingError
from garo_ns.garo_strategy import TRANSIENT_STATE, GaroStrategy
from garo_ns.initialisation import initial_gaussians
from garo_ns.metrics import make_lpips
from garo_ns.render.backend import Backend, resolve_backend
from garo_ns.render.contribution import summed_contribution
from garo_ns.render.frame import (
    Canonical,
    FramePath,
    FrameSettings,
    RenderPrecision,
    Splats,
    activate,
    compose,
    render_splats,
)
from garo_ns.render.switches import DEFAULT_BOUND_DB, measure_on_views, replay, resolve
from garo_ns.render.view import RenderView, camera_extent, camera_time, camera_view
from garo_ns.static import classification_due, classify, sample_times, static_fraction


@dataclass
class GaroModelConfig(SplatfactoModelConfig):
    """Deformable splatfacto with D-3DGS's training recipe and optional GARO pruning.

    Densification defaults follow D-3DGS (arguments/__init__.py of the official code), which in
    turn follows 3DGS: grow on the plain view-space gradient above 2e-4, clone below 1% of the
    scene extent and split above, cull opacity below 0.005 and world size above 10% of the extent,
    refine every 100 steps from 500 to 15k, reset opacity every 3000 steps.
    """

    _target: Type = field(default_factory=lambda: GaroModel)

    # --- D-3DGS / 3DGS schedule (splatfacto's own defaults differ) ---
    warmup_length: int = 500
    """Densification starts after this step (3DGS densify_from_iter)."""
    refine_every: int = 100
    """Densify and prune every this many steps (3DGS densification_interval)."""
    num_downscales: int = 0
    """Full resolution from the first step, as D-3DGS trains."""
    background_color: Literal["random", "black", "white"] = "black"
    """Render background; replaced by the dataset's alpha colour when the dataparser reports it."""
    cull_alpha_thresh: float = 0.005
    """Prune Gaussians with opacity below this (3DGS min_opacity)."""
    cull_scale_thresh: float = 0.1
    """Prune Gaussians larger than this fraction of the scene extent (3DGS big_points_ws)."""
    reset_alpha_every: int = 30
    """Reset opacities every this many refinements (30 x 100 = 3000 steps, 3DGS opacity_reset_interval)."""
    densify_grad_thresh: float = 0.0002
    """Grow Gaussians whose mean view-space gradient exceeds this (3DGS densify_grad_threshold)."""
    use_absgrad: bool = False
    """D-3DGS uses the plain gradient."""
    densify_size_thresh: float = 0.01
    """Clone below, split above this fraction of the scene extent (3DGS percent_dense)."""
    stop_screen_size_at: int = 0
    """Screen-size pruning off: in 3DGS it never triggers (max_radii2D is reset before use)."""
    stop_split_at: int = 15000
    """Densification ends here (3DGS densify_until_iter)."""
    random_init: bool = True
    """D-3DGS initialises synthetic scenes with random points."""
    num_random: int = 100_000
    """Number of random initial Gaussians (3DGS: 100k for synthetic scenes)."""
    random_scale: float = 2.6
    """Edge of the random-init cube: [-1.3, 1.3]^3 as in 3DGS's synthetic scenes."""
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    ssim_lambda: float = 0.2

    # --- deformation field (D-3DGS) ---
    deform_pos_freqs: int = 10
    """Positional-encoding frequencies of the canonical position."""
    deform_time_freqs: int = 6
    """Positional-encoding frequencies of time: 6 for synthetic scenes, 10 for real captures."""
    deform_depth: int = 8
    """Hidden layers of the deformation MLP."""
    deform_width: int = 256
    """Width of the deformation MLP."""
    deform_skip: int = 4
    """The input is concatenated again after this hidden layer."""
    deform_time_net: int = 30
    """D-3DGS's time network for synthetic scenes (`--is_blender`): the time encoding passes through
    a 256-unit hidden layer to this many features before the MLP. 0: the encoding goes in directly,
    as D-3DGS does for real captures (the `-real` presets)."""
    deform_warmup: int = 3000
    """Static warm-up: the deformation field is used from this step on (D-3DGS warm_up)."""
    deform_head_init: Literal["zero", "default"] = "default"
    """Initial output heads of the MLP: PyTorch's default (as D-3DGS) or zero (identity at the
    switch-on). Zero heads give every unit of the last hidden layer the same first updates; on lego
    their last layer died wholesale in 1 of 5 runs, the field then modelled no motion
    (benchmarks/results/deform_health_H200.json; 0 of 5 with the default)."""
    health_every: int = 500
    """Check every this many steps after the warm-up that the deformation field still models
    motion (garo_ns.deformation.field_health): logged, with a warning when it has collapsed. 0: off."""
    time_noise: float = 0.0
    """Training only: the MLP's time input gets Gaussian noise of this many frame intervals (one
    draw per step, shared by all Gaussians), decaying linearly to 0 at `time_noise_steps`. D-3DGS
    uses 0.1 on real captures (its `ast_noise`) to smooth motion between sparse frames; 0: off."""
    time_noise_steps: int = 20_000
    """Step at which the time-input noise reaches 0."""
    default_time: float = 0.0
    """Time used for cameras that carry none (e.g. some viewer and render paths); warned once."""
    scene_extent: Optional[float] = None
    """Scene extent for densification thresholds; None takes the dataparser's camera extent."""

    # --- rendering ---
    rasterizer: Backend = "auto"
    """'cuda' (gsplat kernels), 'reference' (pure torch), or 'auto': cuda when it can run."""

    # --- render-time speed: each a switch, each measured by the benchmark. None (the default) leaves a
    # switch to garo_ns.render.switches: off in a training run (and for a viewer attached to it); for a
    # finished model, the exact ones (cuda_graph, lean_raster) on where CUDA runs, static_skip and a lower
    # render_precision on when their PSNR loss on training views, measured at the end of training, is
    # within switch_bound_db. A value set here is used as set. ---
    static_skip: Optional[bool] = None
    """When not training, Gaussians classified static skip the MLP; their offsets are frozen at
    their time average (the classification itself always runs during training; it is cheap)."""
    static_threshold: float = 2.5e-4
    """Static: freezing its offsets at their time average moves no part of the Gaussian by more than
    this fraction of the scene extent at any sampled training time (position deviation plus size
    times rotation and scale deviations; on D-NeRF at 800 px, 2.5e-4 is about a third of a pixel)."""
    static_every: int = 1000
    """Re-decide which Gaussians are static every this many steps once the deformation is on, and at
    the last step; a Gaussian that starts moving becomes dynamic again."""
    static_times: int = 32
    """Training times sampled for the static classification (evenly spread over the dataset's times)."""
    render_precision: Optional[RenderPrecision] = None
    """Precision of the deformation MLP when not training: fp32, tf32 (CUDA tensor cores), bf16, or fp16
    (CUDA: half weights with fp32 accumulation, each Gaussian's position part of the first and skip
    layers cached; garo_ns.render.half_field), or fp16-fused (the same arithmetic as one Triton kernel that
    keeps the activations on chip; garo_ns.render.fused_field; CUDA with Triton, elsewhere as fp16; never
    chosen when left to None). Offsets differ from fp32 by at most about 2e-4 of the scene extent (tf32
    alike, bf16 1.5e-3; benchmarks/deform_mlp.py); the bound checked on real scenes is a rendered PSNR
    within 0.02 dB of fp32 on every view (the benchmark's `+half` and `+fused` rows)."""
    cache_deformation: bool = True
    """When not training, reuse the deformed Gaussians if the same time is rendered again and no
    parameter changed (the viewer re-renders one time for every camera move). Exact."""
    cuda_graph: Optional[bool] = None
    """When not training on CUDA, run everything between the time and the rasterizer (MLP,
    composition, activations) as one captured CUDA graph instead of dozens of kernel launches;
    captured again when the Gaussians or the render switches change. Same arithmetic as without.
    With `lean_raster` too, the camera's share (projection, view directions, visibility) is a
    second graph, fed the camera's matrices."""
    lean_raster: Optional[bool] = None
    """When not training on CUDA, call gsplat's kernels directly instead of its general Python
    wrapper (garo_ns.render.backend.rasterize_lean): same kernels and pixels, less Python per frame."""
    switch_bound_db: float = DEFAULT_BOUND_DB
    """Largest PSNR loss, on any training view measured at the end of training, with which an
    approximate switch left to None is turned on for a finished model."""
    prune_contribution_ratio: float = 0.0
    """Expert knob: at each of `prune_contribution_steps`, prune this fixed fraction of the Gaussians
    with the smallest summed blending weight over the training views (0: off). The same share for
    every scene; `compact` chooses each scene's share from its training views instead."""
    prune_contribution_steps: Tuple[int, ...] = (20000, 30000)
    """Steps of the contribution pruning (after densification has ended, so the rest can adapt)."""

    # --- compaction after densification (garo-compact; garo_ns.compaction) ---
    compact: bool = False
    """After densification, remove the least important Gaussians in rounds, with fine-tuning in between,
    until a round costs more training-view PSNR than `compact_tolerance_db`: each scene gets the budget
    its training views need. Each round is logged; the summary goes into checkpoints and garo-eval."""
    compact_tolerance_db: float = Compaction.tolerance_db
    """Training-view PSNR a removal may cost, in dB; a larger value gives a smaller, faster model."""
    compact_start: Optional[int] = None
    """Step of the first round; None: `stop_split_at`, where densification ends."""
    compact_every: int = Compaction.every
    """Steps of fine-tuning between rounds."""
    compact_fraction: float = Compaction.fraction
    """Share of the Gaussians a round removes (by blending weight over the training views x volume^beta)."""
    compact_max_rounds: int = Compaction.max_rounds
    """Most rounds of removal."""
    compact_min_gaussians: int = Compaction.min_gaussians
    """Compaction never leaves fewer Gaussians than this."""
    compact_guard_views: int = Compaction.guard_views
    """Training views the guard measures PSNR on (evenly spread over time; the eval split is never read)."""
    compact_volume_beta: float = Compaction.volume_beta
    """Exponent of the volume in the importance (LightGaussian's global significance; 0: weight alone)."""

    # --- GARO (geometry-aware redundancy optimisation) ---
    garo_mode: Literal["off", "oaa", "gca", "full"] = "full"
    """off: plain densification (the D-3DGS baseline); oaa: activity only (the paper's "w/o GCA");
    gca: curvature only, every visible Gaussian a candidate (the paper's "w/o OAA"); full: activity
    candidates filtered by curvature (the paper's method)."""
    tau_activity: float = GaroStrategy.tau_activity
    """Candidates are Gaussians whose mean view-space gradient norm is below this (the paper's)."""
    n_max: int = GaroStrategy.n_max
    """At most this many candidates (the least active) per GARO step (the paper's)."""
    tau_curvature: float = GaroStrategy.tau_curvature
    """Candidates whose curvature is below this are redundant (the paper's)."""
    rho_max: float = GaroStrategy.rho_max
    """At most floor(rho_max * N) Gaussians are pruned per GARO step (the paper's default)."""
    k_neighbors: int = GaroStrategy.k_neighbors
    """Neighbours for the curvature estimate (the paper's K)."""
    garo_start: Optional[int] = None
    """First step at which GARO may prune; None: the first refinement step (after `warmup_length`)."""
    garo_stop: Optional[int] = None
    """GARO prunes up to (not including) this step; None: `stop_split_at`, where densification ends."""
    garo_every: Optional[int] = None
    """GARO prunes every this many steps; None: `refine_every` (every densification step, as the paper)."""
    garo_activity_window: Literal["training", "garo_step"] = GaroStrategy.activity_window
    """training: g_i is the mean over every iteration of training in which Gaussian i was visible
    (the paper's equation); garo_step: the mean since the previous GARO step only."""

    def __post_init__(self) -> None:
        self.compaction()  # a compaction setting out of range fails here, before any training

    def compaction(self) -> Compaction:
        """The compaction settings of this config; raises GaroConfigError for one out of range."""
        fields = Compaction.__dataclass_fields__
        return Compaction(**{k: getattr(self, f"compact_{k}") for k in fields})  # type: ignore[arg-type]

    def make_deformation(self) -> DeformationField:
        """The deformation field these settings describe (untrained)."""
        return DeformationField(
            self.deform_pos_freqs,
            self.deform_time_freqs,
            self.deform_depth,
            self.deform_width,
            self.deform_skip,
            head_init=self.deform_head_init,
            time_net=self.deform_time_net,
        )

    def make_strategy(self) -> GaroStrategy:
        """The densification and GARO strategy these settings describe."""
        return GaroStrategy(
            prune_opa=self.cull_alpha_thresh,
            grow_grad2d=self.densify_grad_thresh,
            grow_scale3d=self.densify_size_thresh,
            grow_scale2d=self.split_screen_size,
            prune_scale3d=self.cull_scale_thresh,
            prune_scale2d=self.cull_screen_size,
            refine_scale2d_stop_iter=self.stop_screen_size_at,
            refine_start_iter=self.warmup_length,
            refine_stop_iter=self.stop_split_at,
            reset_every=self.reset_alpha_every * self.refine_every,
            refine_every=self.refine_every,
            pause_refine_after_reset=0,
            absgrad=self.use_absgrad,
            revised_opacity=False,
            verbose=False,
            mode=self.garo_mode,
            tau_activity=self.tau_activity,
            n_max=self.n_max,
            tau_curvature=self.tau_curvature,
            rho_max=self.rho_max,
            k_neighbors=self.k_neighbors,
            garo_start_iter=self.garo_start,
            garo_stop_iter=self.garo_stop,
            garo_every=self.garo_every,
            activity_window=self.garo_activity_window,
            compaction=self.compaction() if self.compact else None,
        )


class GaroModel(SplatfactoModel):
    """Splatfacto with a D-3DGS deformation field and a GARO-capable densification strategy."""

    config: GaroModelConfig

    # ------------------------------------------------------------------ set-up
    def populate_modules(self) -> None:
        cfg = self.config
        metadata: Dict[str, Any] = dict(self.kwargs.get("metadata") or {})
        extent = cfg.scene_extent or metadata.get("camera_extent") or 1.0
        if not (isinstance(extent, (int, float)) and math.isfinite(extent) and extent > 0):
            raise ValueError(f"scene extent must be a positive number, got {extent!r}")
        self.scene_extent = float(extent)
        start = initial_gaussians(self.seed_points, cfg.random_init, cfg.num_random, cfg.random_scale, cfg.sh_degree)
        self.gauss_params = torch.nn.ParameterDict({k: Parameter(v) for k, v in start.items()})
        self.deformation = cfg.make_deformation()
        self.camera_optimizer = cfg.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")

        from nerfstudio.models.splatfacto import SSIM
        from torchmetrics.image import PeakSignalNoiseRatio

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self._lpips = [make_lpips()]  # out of the module tree: LPIPS may be absent, checkpoints must not need it
        self.step = 0
        self.crop_box = None
        self._warned_no_time = False
        alpha = metadata.get("alpha_color")
        if alpha is None and cfg.background_color == "random":
            raise ValueError(
                "background_color 'random' is not supported: set it to the dataset's alpha colour (black or white)"
            )
        background = get_color(cfg.background_color) if alpha is None else torch.as_tensor(alpha).reshape(3)
        # A buffer, so the background the model was trained on travels with its checkpoints.
        self.register_buffer("background_rgb", background.clone().float())
        self._extent_from_data = cfg.scene_extent is None and "camera_extent" in metadata
        self.strategy = cfg.make_strategy()
        self.compaction_guard: Optional[TrainingViewGuard] = None  # training views (compaction, switches)
        self.training_run = False  # set when the model gets training callbacks
        self.switch_record: Optional[Dict[str, Any]] = None  # what each approximate switch cost
        self._switch_cache: Optional[Tuple[Any, Any, FrameSettings]] = None
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.scene_extent)
        self.train_times: Optional[Tensor] = None
        self.train_cameras: Optional[Cameras] = None
        self._last_step: Optional[int] = None
        self.frame = FramePath()
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
        """Make the model agree with its training data whatever the dataparser: render on the
        data's alpha colour, and (unless set) scale densification by the 3DGS camera extent."""
        outputs = getattr(getattr(pipeline, "datamanager", None), "train_dataparser_outputs", None)
        if outputs is None:
            return
        self.train_cameras = outputs.cameras
        if outputs.cameras.times is not None:
            self.train_times = torch.unique(outputs.cameras.times.detach().reshape(-1).float().cpu())
        alpha = outputs.alpha_color
        if alpha is not None and not torch.allclose(alpha.float().cpu(), self.background_rgb.cpu()):
            CONSOLE.print(f"[yellow]Background set to the data's alpha colour {alpha.tolist()}[/yellow]")
            self.background_color = alpha
        if self.config.scene_extent is None and not self._extent_from_data:
            self.scene_extent = camera_extent(outputs.cameras.camera_to_worlds.detach().cpu().numpy())
            self.strategy_state["scene_scale"] = self.scene_extent
        # Training views (the training split only) for compaction's guard and the render switches' measurement.
        self.compaction_guard = TrainingViewGuard.from_datamanager(
            pipeline.datamanager, self.config.compact_guard_views
        )

    # ------------------------------------------------------------------ training callbacks
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        attributes = training_callback_attributes
        self.training_run = True
        self.adopt_training_data(attributes.pipeline)
        if attributes.trainer is not None:
            self._last_step = int(attributes.trainer.config.max_num_iterations) - 1
        before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return [
            TrainingCallback([before], self.step_cb, args=[attributes.optimizers]),
            TrainingCallback([after], self.after_iteration),
        ]

    def step_cb(self, optimizers: Optimizers, step: int) -> None:
        self.step = step
        self.optimizers = optimizers.optimizers

    def after_iteration(self, step: int) -> None:
        """The strategy (densification, GARO, contribution pruning, compaction), then the static
        classification, then the deformation field's health check."""
        cfg = self.config
        self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step, self.info)
        last = self.strategy_state.get("garo_last") or {}
        if last.get("step") == step:
            for key in ("candidates", "redundant", "pruned", "seconds", "num_gaussians"):
                writer.put_scalar(name=f"garo/{key}", scalar=float(last[key]), step=step)
        ratio = cfg.prune_contribution_ratio
        if ratio > 0 and step in cfg.prune_contribution_steps and self.train_cameras is not None:
            contribution = self.contribution(self.train_cameras)
            n = self.strategy.prune_by_contribution(
                self.gauss_params, self.optimizers, self.strategy_state, contribution, ratio
            )
            CONSOLE.print(f"step {step}: pruned {n} least contributing Gaussians, {self.num_points} left")
        run_round(self, step, self._last_step)  # compaction (garo_ns.compaction), when configured
        if self.deformation_active() and classification_due(step, cfg.deform_warmup, cfg.static_every, self._last_step):
            self.refresh_static()
            fraction = self.static_fraction()
            if fraction is not None:
                writer.put_scalar("garo/static_fraction", fraction, step)
        self.check_health(step)
        if step == self._last_step and self.compaction_guard is not None and self.deformation_active():
            try:
                self.record_switches(step)
            except Exception as err:  # a measurement must never cost the run its final checkpoint
                CONSOLE.print(f"[yellow]Render switches not measured ({err}); they stay off unless set[/yellow]")

    def check_health(self, step: int) -> None:
        """Every `health_every` steps after the warm-up, measure whether the deformation field
        still models motion; warn once when it has collapsed (no later step can undo it)."""
        cfg = self.config
        if self.num_points == 0 or not health_due(step, cfg.deform_warmup, cfg.health_every):
            return
        health = health_check(self.deformation, self.means, sample_times(self.train_times, 8), self.scene_extent, step)
        self.health_log.append(health)
        writer.put_scalar("garo/deform_time_sensitivity", health["time_sensitivity"], step)
        writer.put_scalar("garo/deform_dead_fraction_max", max(health["dead_fraction"]), step)
        if health["collapsed"] and not any(h["collapsed"] for h in self.health_log[:-1]):
            CONSOLE.print(collapse_warning(health, cfg.deform_head_init))

    # ------------------------------------------------------------------ the Gaussians at a time
    def deformation_active(self) -> bool:
        """Whether the deformation field is applied at the current step (after the static warm-up)."""
        return self.step >= self.config.deform_warmup

    def canonical(self) -> Canonical:
        """The parameters as stored (canonical geometry, log-scales, opacity logits, SH)."""
        return Canonical(self.means, self.quats, self.scales, self.opacities, self.features_dc, self.features_rest)

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
            return activate(canonical, compose(self.deformation, canonical, time))
        state = self.strategy_state
        settings = self.render_settings() if settings is None else settings
        return self.frame.splats(self.deformation, canonical, state["static"], state["static_offset"], time, settings)

    def render_settings(self) -> FrameSettings:
        """The render switches outside training: the config's, those left to None decided by
        garo_ns.render.switches (from the losses recorded at the end of training)."""
        requested = {k: getattr(self.config, k) for k in FrameSettings.__dataclass_fields__}
        record, bound = self.switch_record, self.config.switch_bound_db
        key = (tuple(requested.values()), self.training_run, bound, self.device.type)
        cached = self._switch_cache
        if cached is not None and cached[0] == key and cached[1] is record:  # twice a frame: decide once
            return cached[2]
        cuda = self.switch_inputs()[1]
        measure = replay(record["tried"]) if record else None
        settings = resolve(requested, self.training_run, cuda, measure, bound_db=bound)[0]
        self._switch_cache = (key, record, settings)
        return settings

    def switch_inputs(self) -> Tuple[Dict[str, Any], bool]:
        """The config's render switches (None: left to the plugin) and whether rendering runs on CUDA."""
        requested = {k: getattr(self.config, k) for k in FrameSettings.__dataclass_fields__}
        return requested, resolve_backend(self.config.rasterizer, self.device) == "cuda"

    @torch.no_grad()
    def record_switches(self, step: int) -> None:
        """Measure on the training views what each approximate render switch costs against the plain
        render (exact switches off: they change no pixel), and keep it for the finished model."""
        guard = self.compaction_guard
        assert guard is not None
        was_training = self.training
        self.eval()  # no time noise
        try:

            def render(i: int, trial: Optional[FrameSettings]) -> Tensor:
                switches = None if trial is None else replace(trial, cuda_graph=False, lean_raster=False)
                return guard.render(self, i, switches)

            targets = guard.targets(self)
            requested, cuda = self.switch_inputs()
            measure = measure_on_views(render, targets)
            tried = resolve(requested, False, cuda, measure, bound_db=self.config.switch_bound_db)[1]
        finally:
            self.train(was_training)
        self.switch_record = {"step": step, "views": len(targets), "tried": tried}
        losses = ", ".join(f"{k} {v:.4f} dB" for k, v in tried.items()) or "none left to the plugin"
        CONSOLE.print(f"Render switches on {len(targets)} training views (PSNR loss against plain): {losses}")

    # ------------------------------------------------------------------ static classification
    def static_fraction(self) -> Optional[float]:
        """Share of Gaussians currently classified static, or None before any classification."""
        return static_fraction(self.strategy_state.get("static"), self.num_points)

    @torch.no_grad()
    def refresh_static(self, times: Optional[Tensor] = None) -> None:
        """Re-decide which Gaussians are static from the current deformation field, at `times`
        (default: up to `static_times` of the training times, evenly spread)."""
        times = sample_times(self.train_times, self.config.static_times) if times is None else times
        threshold = self.config.static_threshold * self.scene_extent
        static, offset = classify(self.deformation, self.means, self.scales, times, threshold)
        self.strategy_state.update({"static": static, "static_offset": offset, "static_step": int(self.step)})

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
        time = camera_time(camera)
        if time is None:
            if not self._warned_no_time:
                CONSOLE.print(
                    f"[yellow]Camera carries no time; rendering at default_time={self.config.default_time}[/yellow]"
                )
                self._warned_no_time = True
            time = float(self.config.default_time)
        c2w = camera.camera_to_worlds if c2w is None else c2w
        return camera_view(camera, c2w, self._get_downscale_factor(), self.device, time)

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
            return render_splats(splats, view, degree, backgrounds, render_mode, backend)
        lean = bool(self.render_settings().lean_raster)
        return self.frame.rasterize(splats, view, degree, backgrounds, render_mode, backend, lean)

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:
        if not isinstance(camera, Cameras):
            raise TypeError(f"get_outputs needs a Cameras object, got {type(camera).__name__}")
        if camera.shape[0] != 1:
            raise ValueError(f"renders one camera at a time, got {camera.shape[0]}")
        c2w = self.camera_optimizer.apply_to_camera(camera) if self.training else camera.camera_to_worlds
        view = self.camera_view(camera, c2w)
        splats = self.gaussians_at(view.time)
        if self.crop_box is not None and not self.training:
            keep = self.crop_box.within(splats.means).squeeze()
            if keep.sum() == 0:
                return self.get_empty_outputs(view.width, view.height, self.background_color)
            splats = splats.select(keep)
        W, H = view.width, view.height
        self.last_size = (H, W)
        render_mode = "RGB+ED" if (self.config.output_depth_during_training or not self.training) else "RGB"
        render, alpha, info = self.render(view, render_mode, splats=splats)
        # The geometry GARO measures, for the strategy (no copies: detached views).
        info.update(means3d=splats.means.detach(), quats3d=splats.quats.detach(), scales3d=splats.scales.detach())
        self.info = info
        if self.training:
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step, info)
        background = self.background_color.to(self.device)
        rgb = render[..., :3] + (1 - alpha) * background
        # The loss sees the render unclamped, as D-3DGS's does: a clamp would stop the gradient of
        # every over-bright pixel (and with it part of the densification signal).
        rgb = rgb if self.training else torch.clamp(rgb, 0.0, 1.0)
        depth = None
        if render_mode == "RGB+ED":
            depth = render[..., 3:4]
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if not self.training:
            background = background.expand(H, W, 3)
        return {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}

    # ------------------------------------------------------------------ losses and metrics
    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training and not bool(torch.isfinite(losses["main_loss"])):
            raise GaroTrainingError(
                f"non-finite loss at step {self.step}; training stopped, earlier checkpoints are kept"
            )
        return losses

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        pred = outputs["rgb"]
        gt_b = torch.moveaxis(gt, -1, 0)[None]
        pred_b = torch.moveaxis(pred, -1, 0)[None]
        metrics = {"psnr": float(self.psnr(gt_b, pred_b).item()), "ssim": float(self.ssim(gt_b, pred_b))}
        lpips = self._lpips[0]
        if lpips is not None:
            metrics["lpips"] = float(lpips.to(pred.device)(gt_b.clamp(0, 1), pred_b.clamp(0, 1)))
        metrics["num_gaussians"] = float(self.num_points)
        return metrics, {"img": torch.cat([gt, pred], dim=1)}

    # ------------------------------------------------------------------ checkpoints
    def update_to_step(self, step: int) -> None:
        self.step = step

    def load_state_dict(self, state_dict, strict: bool = True, **kwargs):  # type: ignore[override]
        """Resize the Gaussians in place to the checkpoint's count, then load.

        In place (same Parameter objects), so optimizers built before loading stay bound to the
        loaded Gaussians; the step is the checkpoint's, set through `update_to_step`.
        """
        checkpoints.upgrade_gaussian_keys(state_dict)
        checkpoints.resize_gaussians(self.gauss_params, state_dict["gauss_params.means"].shape[0])
        if self.deformation.time_net is not None and not checkpoints.has_time_net(state_dict):
            # Written before the time network was part of the recipe: rebuild the field without it
            # so the run renders as it was trained (an optimizer built earlier is not bound to it).
            CONSOLE.print("[yellow]Checkpoint has no deformation time network: loading the field without it[/yellow]")
            self.config.deform_time_net = 0
            self.deformation = self.config.make_deformation().to(self.background_rgb.device)
        return torch.nn.Module.load_state_dict(self, state_dict, strict=strict)

    def get_extra_state(self) -> Dict[str, Any]:
        """The densification strategy's running state (the compaction's summary too, not its undo copy)
        travels with the checkpoint."""
        state = {k: v for k, v in self.strategy_state.items() if k not in TRANSIENT_STATE}
        return {"strategy_state": state, "render_switches": self.switch_record}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        checkpoints.restore_strategy_state(self.strategy_state, (state or {}).get("strategy_state") or {}, self.device)
        self.switch_record = (state or {}).get("render_switches")
