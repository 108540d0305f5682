"""Method specifications registered with nerfstudio: `garo-deform`, `deform-splatfacto` and `garo-compact`
(each with a `-real` twin for real captures: NeRF-DS / HyperNeRF, or your own video after `ns-process-data video`).

Both train the same deformable model with D-3DGS's recipe (40k steps, learning rates of the
official code, densification from 500 to 15k); `deform-splatfacto` turns GARO pruning off and is
the D-3DGS baseline. Learning rates, as the official D-3DGS code (branch `paper`) sets them: it
scales the position and scale rates by a fixed spatial factor of 5 for every scene (3DGS used
the camera extent; the densification thresholds still use the extent, which the model gets from
the dataparser):
  positions 1.6e-4 x 5 -> 1.6e-6 x 5 over 30k steps, deformation 1.6e-4 x 5 -> 1.6e-6 over 40k
  steps, colour 2.5e-3 (rest 1/20 of it), opacity 0.05, scale 1e-3 x 5, rotation 1e-3.
`garo-compact` is `garo-deform` followed by compaction after densification (garo_ns.compaction):
rounds of removing the least important Gaussians, with fine-tuning in between, each measured on training
views before it removes, within `--pipeline.model.compact-round-bound-db` per round and
`--pipeline.model.compact-budget-db` in all. Its deformation MLP trains in fp32. Each method turns on what its own
40k A/B on jumpingjacks, mutant and standup measured: `garo-deform` bf16 products and the fused layers
(`with_fast_field`), then the official code's scale composition with the offsets' last product in fp32
(`with_official_composition_fp32_heads`); `deform-splatfacto` that composition in fp32 (`with_official_composition`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import torch
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification
from torch.nn import Parameter

from garo_ns import compat
from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
from garo_ns.data.nerfds import NerfDSDataParserConfig
from garo_ns.engine.adam import LeanAdam
from garo_ns.garo_model import GaroModelConfig

compat.install()

ITERATIONS = 40_000
REAL_ITERATIONS = 20_000
# The -real recipes' Gaussian budget (`max_gaussians`). Without one, on a phone video (pillow) the model never fit
# its training views (16 to 17 dB), so some 30k Gaussians kept a high gradient at every refinement and the count grew
# by about a quarter each time: 889k at step 7.6k, 39 ms a step, 12.5 GB and rising (the 80 GB OOM near 8k). Within
# 200k it fit the same views better (19.0 dB at 7.6k) at 12 ms a step (benchmarks/results/real_growth_H200.json).
# In COLMAP's units (nerfds-data's camera_distance 0, the official code's) the cap moved to 700k: with both, held-out
# frames gained 0.97 dB on cat-pikachu-7 (which stopped growing at 271k, as the official code did) and 0.67 dB on
# pillow (698k, 10.9 GB allocated at peak: a 24 GB GPU holds it), against 200k in the old units
# (benchmarks/results/ab_real_cat_H200.md, ab_real_pillow_{lr,all}_H200.json).
REAL_MAX_GAUSSIANS = 700_000
SPATIAL_LR_SCALE = 5.0  # D-3DGS's fixed `spatial_lr_scale` (gaussian_model.py, deform_model.py)


@dataclass
class AdamConfig(AdamOptimizerConfig):
    """nerfstudio's Adam, fused (one kernel per parameter group) where its parameters are on CUDA: the same update
    as the multi-tensor path that nerfstudio uses, with far less host time in each step's eight updates, and that
    fused step without torch's per-call bookkeeping (`garo_ns.engine.adam.LeanAdam`)."""

    def setup(self, params: Iterable[Parameter]) -> torch.optim.Optimizer:
        params = list(params)
        if params and all(p.is_cuda for p in params):
            return LeanAdam(params, lr=self.lr, eps=self.eps, weight_decay=self.weight_decay)
        return torch.optim.Adam(params, lr=self.lr, eps=self.eps, weight_decay=self.weight_decay)


def optimizers(max_steps: int = ITERATIONS, spatial: float = SPATIAL_LR_SCALE) -> dict:
    """D-3DGS's optimizers and schedules, as nerfstudio optimizer configs."""
    return {
        "means": {
            "optimizer": AdamConfig(lr=1.6e-4 * spatial, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6 * spatial, max_steps=30_000),
        },
        "deformation": {
            "optimizer": AdamConfig(lr=1.6e-4 * spatial, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps),
        },
        "features_dc": {"optimizer": AdamConfig(lr=0.0025, eps=1e-15), "scheduler": None},
        "features_rest": {"optimizer": AdamConfig(lr=0.0025 / 20, eps=1e-15), "scheduler": None},
        "opacities": {"optimizer": AdamConfig(lr=0.05, eps=1e-15), "scheduler": None},
        "scales": {"optimizer": AdamConfig(lr=0.001 * spatial, eps=1e-15), "scheduler": None},
        "quats": {"optimizer": AdamConfig(lr=0.001, eps=1e-15), "scheduler": None},
        "camera_opt": {
            "optimizer": AdamConfig(lr=1e-4, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=max_steps),
        },
    }


def default_device() -> str:
    """The device a run trains on unless `--machine.device-type` says otherwise: the GPU where CUDA works, else the
    CPU (the reference rasterizer), so that the README's commands run as printed on a machine without a GPU."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def trainer_config(method_name: str, garo_mode: str) -> TrainerConfig:
    """A full training config of the deformable model with GARO in `garo_mode`. The viewer listens on this machine
    alone (127.0.0.1; `--viewer.websocket-host 0.0.0.0` to serve others), where nerfstudio listens on every address."""
    config = TrainerConfig(
        method_name=method_name,
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=100_000,
        max_num_iterations=ITERATIONS,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(
                dataparser=GaroDNeRFDataParserConfig(),
                cache_images="gpu",  # "gpu" means the model's device; "cpu" pins memory, which needs CUDA
                cache_images_type="uint8",
            ),
            model=GaroModelConfig(garo_mode=garo_mode),  # type: ignore[arg-type]
        ),
        optimizers=optimizers(),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15, websocket_host="127.0.0.1"),
        vis="viewer",
    )
    config.machine.device_type = default_device()  # type: ignore[assignment]
    return config


def with_fast_field(config: TrainerConfig) -> TrainerConfig:
    """`config` with the deformation MLP's training products in bf16 (`deform_train_bf16`) and its layers fused
    (`deform_fused_layers`, garo_ns.ops.dense): each measured at 40k on jumpingjacks, mutant and standup against the
    recipe without it (docs/benchmarks.md: "bf16 training", "The field's layers fused")."""
    config.pipeline.model.deform_train_bf16 = True
    config.pipeline.model.deform_fused_layers = True
    return config


def with_official_composition(config: TrainerConfig) -> TrainerConfig:
    """`config` with the official D-3DGS code's scale composition (`deform_scale_offset="linear"`) and the field's
    products in fp32 (TF32), as that code trains. In fp32 it gained on all three shared scenes at 40k, two rounds
    (+0.08, +0.23, +0.09 dB: benchmarks/results/ab_scale_term_fp32_H200.json), where in bf16 it lost 0.25 dB on
    jumpingjacks (ab_scale_term_H200.json; the likely cause: bf16 keeps 8 bits of an offset that nearly cancels a
    small scale). It scores the official code's PSNR on mutant and standup (baseline_vs_official_recipe_H200.json;
    jumpingjacks awaits an official run on the same GPU model). Mutant's 40k took 468 s alone on an H200 (436 s in
    bf16 with `log`, at an earlier commit): fp32 costs time, and `linear` keeps 10% fewer Gaussians there."""
    config.pipeline.model.deform_scale_offset = "linear"
    config.pipeline.model.deform_train_bf16 = False
    return config


def with_official_composition_fp32_heads(config: TrainerConfig) -> TrainerConfig:
    """`config` with the official scale composition (`linear`) and, where the field's products are bf16, its three
    heads in fp32 (`deform_fp32_heads`): the offsets keep fp32's precision at about 0.5% of the field's products, so
    bf16 training keeps its speed. Against the bf16 recipe with `log` at 40k (3, 3 and 2 runs per side): +0.17 dB on
    average (-0.05, +0.32, +0.23 on jumpingjacks, mutant, standup; LPIPS +0.0013, +0.0002, +0.0001, the direction
    `linear` took in fp32 too), benchmarks/results/ab_fp32_heads_H200.json. It also gives `garo-deform` the
    baseline's composition, so that GARO against `deform-splatfacto` measures GARO, not the scale term."""
    config.pipeline.model.deform_scale_offset = "linear"
    config.pipeline.model.deform_fp32_heads = True
    return config


garo_deform = MethodSpecification(
    config=with_official_composition_fp32_heads(with_fast_field(trainer_config("garo-deform", "full"))),
    description="Deformable 3D Gaussians (D-3DGS) with GARO redundancy pruning.",
)

deform_splatfacto = MethodSpecification(
    config=with_official_composition(trainer_config("deform-splatfacto", "off")),
    description="Deformable 3D Gaussians (D-3DGS recipe) without GARO: the baseline.",
)


def real_trainer_config(method_name: str, garo_mode: str) -> TrainerConfig:
    """The real-capture recipe (a NeRF-DS / HyperNeRF capture or an ns-process-data folder): D-3DGS's settings
    for real scenes and GARO's 20k-step NeRF-DS schedule, its learning rates decaying as over D-3DGS's 40k. Time is
    encoded with 10 frequencies, the MLP's time input is perturbed early in training (D-3DGS's annealed time noise),
    and the Gaussians start from the capture's points.npy (random in the unit cube when it has none). Densification
    grows to at most `REAL_MAX_GAUSSIANS`."""
    config = trainer_config(method_name, garo_mode)
    config.max_num_iterations = REAL_ITERATIONS
    # The official code's schedule lengths (positions over 30k steps, the field over 40k) whatever the run's length:
    # annealed within the 20k run instead, pillow's held-out frames lost 2.6 dB (16.46 against 19.10 dB,
    # benchmarks/results/ab_real_pillow_{base,lr}_H200.json).
    config.optimizers = optimizers()
    config.pipeline.datamanager.dataparser = NerfDSDataParserConfig()
    model = config.pipeline.model
    model.deform_time_freqs = 10
    model.deform_time_net = 0  # D-3DGS feeds real captures' time encoding to the MLP directly
    model.time_noise = 0.1
    model.time_noise_steps = REAL_ITERATIONS
    model.random_init = False  # points.npy when present; random otherwise
    model.random_scale = 2.0
    model.max_gaussians = REAL_MAX_GAUSSIANS
    model.expandable_segments = True  # within a 24 GB GPU at that budget (garo_ns.engine.allocator)
    return config


garo_deform_real = MethodSpecification(
    config=real_trainer_config("garo-deform-real", "full"),
    description="GARO on real captures (your own video after ns-process-data, or NeRF-DS / HyperNeRF; nerfds-data).",
)

deform_splatfacto_real = MethodSpecification(
    config=real_trainer_config("deform-splatfacto-real", "off"),
    description="D-3DGS baseline on real captures (ns-process-data video, NeRF-DS / HyperNeRF; nerfds-data).",
)


# GARO's cap per step under compaction: half the paper's 0.02, chosen on jumpingjacks, mutant and standup
# (docs/compaction.md, "How the defaults were chosen"). At 0.02 GARO alone cost mutant and standup 0.41 to
# 0.66 dB at 40k, more than compaction may lose in all; at 0.01 it cost jumpingjacks nothing measurable, and
# the rounds, which measure each removal before making it, do the rest of the removing.
COMPACT_RHO_MAX = 0.01


def with_compaction(config: TrainerConfig, every: int, max_rounds: int) -> TrainerConfig:
    """`config` with compaction after densification: a round every `every` steps from the end of
    densification (15k), at most `max_rounds`, so the last ends with time left to fine-tune; GARO prunes
    at `COMPACT_RHO_MAX` before it."""
    model = config.pipeline.model
    model.rho_max = COMPACT_RHO_MAX
    model.compact = True
    model.compact_every = every
    model.compact_max_rounds = max_rounds
    return config


# 40k steps: rounds at 15k, 16k, ..., 29k at the latest, then 11k steps of training on what is left.
garo_compact = MethodSpecification(
    config=with_compaction(trainer_config("garo-compact", "full"), every=1000, max_rounds=15),
    description="GARO, then compaction that finds each scene's budget under a training-view PSNR guard.",
)

# 20k steps: rounds at 15k, 15.4k, ..., 18.6k at the latest, then 1.4k steps of training on what is left.
garo_compact_real = MethodSpecification(
    config=with_compaction(real_trainer_config("garo-compact-real", "full"), every=400, max_rounds=10),
    description="garo-compact on real captures (ns-process-data video, NeRF-DS / HyperNeRF; nerfds-data).",
)

METHODS = {
    "garo-deform": garo_deform,
    "deform-splatfacto": deform_splatfacto,
    "garo-compact": garo_compact,
    "garo-deform-real": garo_deform_real,
    "deform-splatfacto-real": deform_splatfacto_real,
    "garo-compact-real": garo_compact_real,
}
"""Every method of the plugin by name, as pyproject.toml registers them."""
