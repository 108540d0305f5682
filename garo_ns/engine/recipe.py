"""D-3DGS's training recipe in splatfacto's terms: the settings whose D-3DGS values differ from
splatfacto's defaults, and the densification they give.

Densification follows D-3DGS (arguments/__init__.py of the official code), which in turn follows
3DGS: grow on the plain view-space gradient above 2e-4, clone below 1% of the scene extent and split
above, cull opacity below 0.005 and world size above 10% of the extent, refine every 100 steps from
500 to 15k, reset opacity every 3000 steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, Literal, Mapping, Optional

import torch
from nerfstudio.models.splatfacto import SplatfactoModelConfig
from nerfstudio.utils.colors import get_color
from torch import Tensor

from garo_ns.errors import GaroConfigError


@dataclass
class D3dgsRecipe(SplatfactoModelConfig):
    """Splatfacto's settings with D-3DGS's schedule and thresholds as defaults."""

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
    """D-3DGS uses the plain gradient; the renderer computes no other, so True is refused."""
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
    loss_cuda_graph: bool = True
    """Training on CUDA: the image loss (L1 and SSIM, forward and backward: some sixty small kernels whose launches
    cost the host more than the GPU their work) replays a CUDA graph captured once per image size
    (garo_ns.engine.losses.ImageLoss). With `deform_cuda_graph`, a 40k jumpingjacks run took 362 s instead of 556 s
    (benchmarks/results/train_profile_graphs_*); the same kernels, so the same numbers
    (tests/test_training_graphs.py)."""
    fused_ssim: bool = True
    """Training on CUDA: the loss's SSIM, forward and backward, in four Triton kernels (garo_ns.engine.fused_ssim)
    instead of grouped convolutions and some forty elementwise kernels that each read and write whole image maps: 0.33
    ms instead of 1.22 for an 800x800 loss on an H100, both graphed (benchmarks/results/loss_speed_H100.json). The same
    values to fp32 rounding (tests/test_fused_ssim.py); the scores' SSIM stays the convolutions'."""
    adam_cuda_graph: bool = False
    """Training on CUDA: once the parameters and optimizer states have stayed where they are for longer than
    densification's interval (after densification; again after each compaction round), every group's Adam update
    and the gradients' zeroing replay one CUDA graph (garo_ns.engine.adam.AdamGraph) instead of about 1 ms of host time
    a step in launches. The same updates, but for each learning rate rounded to fp32 on the device (tests/test_adam.py).
    Off: 40k runs alone on an H100 took 324 / 317 / 336 s with it against 327 / 325 / 321 without (mutant, standup,
    jumpingjacks; benchmarks/results/train_profile_adamgraph_*), no gain beyond two runs' spread; with the step graph's
    own gradients (ab110af) mutant's step at 16.5k took 6.32 ms with it, 6.21 without (train_profile_adam17k*)."""
    gc_threshold: int = 20_000
    """While training, Python's garbage collector scans its youngest generation every this many net allocations
    of containers instead of every 700 (garo_ns.ops.collector): a step allocates thousands, so at 700 it runs two or
    three times a step. 600 CPU steps spent 0.53 to 0.58 s in collections at 700, 0.03 s at 20,000
    (benchmarks/results/collector_cpu.json); no gain beyond the spread on an H100. 0: Python's own."""
    train_lean_raster: bool = True
    """Training on CUDA: rasterize through gsplat's kernels behind two autograd nodes (garo_ns.render.train_raster)
    instead of gsplat's `rasterization` wrapper: the same kernels, values and gradients (tests/test_train_raster.py,
    on an H100 too). At step 2000 of a jumpingjacks run on an H100 the rasterization forward took 0.54 ms of host
    time instead of 0.84 (benchmarks/results/train_profile_short_*_H100.json); the backward was unchanged."""
    scene_extent: Optional[float] = None
    """Scene extent for densification thresholds; None takes the dataparser's camera extent."""
    expandable_segments: bool = False
    """Training on CUDA: the caching allocator grows its memory segments in place (PyTorch's
    `expandable_segments`; garo_ns.engine.allocator) unless PYTORCH_CUDA_ALLOC_CONF is set. Densification's growing
    tensors otherwise leave blocks that no longer fit: a phone video's baseline held 29.9 GB for 6.6 GB of tensors
    and stopped at step 5.1k under a 24 GB cap, where with it the run passed step 10.6k using 8.6 GB
    (benchmarks/results/real_memory_teddy_H200.json). On in the `-real` recipes; not measured on D-NeRF's."""
    max_gaussians: Optional[int] = None
    """The most Gaussians densification may grow to (None: no limit): where a refinement would pass it, only the
    candidates of the highest view-space gradients grow. It bounds training memory; GARO and the other pruning still
    remove below it."""

    def validate_recipe(self) -> None:
        """Raise GaroConfigError for a recipe setting the renderer cannot honour: `use_absgrad` (the
        rasterizer's absolute gradients are never computed, so densification would find none)."""
        if self.use_absgrad:
            raise GaroConfigError(
                "--pipeline.model.use-absgrad True is not supported: the renderer computes the plain view-space "
                "gradient only (D-3DGS's densification signal)"
            )
        if isinstance(self.num_random, bool) or not isinstance(self.num_random, int) or self.num_random < 4:
            raise GaroConfigError(
                f"--pipeline.model.num-random must be an int >= 4 (each Gaussian takes its size from 3 neighbours), "
                f"got {self.num_random!r}"
            )
        if self.max_gaussians is not None and (
            isinstance(self.max_gaussians, bool) or not isinstance(self.max_gaussians, int) or self.max_gaussians < 1
        ):
            raise GaroConfigError(
                f"--pipeline.model.max-gaussians must be None or an int >= 1, got {self.max_gaussians!r}"
            )

    def densification_arguments(self) -> Dict[str, Any]:
        """gsplat DefaultStrategy's arguments for this recipe (its names for splatfacto's settings)."""
        return dict(
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
            max_gaussians=self.max_gaussians,
        )

    def extent_for(self, metadata: Mapping[str, Any]) -> float:
        """The scene extent the densification thresholds scale with: `scene_extent`, else the
        dataparser's camera extent (in `metadata`), else 1."""
        extent = self.scene_extent or metadata.get("camera_extent") or 1.0
        if not (isinstance(extent, (int, float)) and math.isfinite(extent) and extent > 0):
            raise ValueError(f"scene extent must be a positive number, got {extent!r}")
        return float(extent)

    def background_for(self, metadata: Mapping[str, Any]) -> Tensor:
        """The render background [3]: the data's alpha colour (in `metadata`), else `background_color`."""
        alpha = metadata.get("alpha_color")
        if alpha is None and self.background_color == "random":
            raise ValueError(
                "background_color 'random' is not supported: set it to the dataset's alpha colour (black or white)"
            )
        return (get_color(self.background_color) if alpha is None else torch.as_tensor(alpha).reshape(3)).float()
