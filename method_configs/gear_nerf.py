"""Gear-NeRF method presets for ``ns-train``.

* ``gear-nerf``: the paper's settings (M = 32, N_gear = 4, n = 64, Adam with lr 0.02).
* ``gear-nerf-small``: CPU preset (small planes, n = 24 base samples from small proposal networks, 1024 rays per
  batch, 3,750 iterations: about the CPU time that 5,000 iterations of 24 uniform samples took; 1,546 s of CPU time
  single-threaded on 30 frames of 30 cameras at 304x168 on a 2-core machine, ``real_capture_causes.md``).
* ``gear-nerf-baseline``: N_gear = 1, i.e. plain K-Planes, sized and sampled as the small preset.

Every preset takes its base samples from proposal networks (K-Planes), has a per-camera appearance code, renders
evaluation views from the near plane (``GearNeRFModelConfig``) and draws a quarter of each batch's rays through
points triangulated from the training views, with their depth (``data.sparse_points``). On the real captures the
proposal sampler beat 24 uniform samples at about equal time and grew none of the layers that uniform samples left
in front of the held-out camera (``benchmarks/results/real_capture_causes.md``). Long videos never load all frames: the
datamanager keeps 40 training images in memory at a time, replaced every 100 iterations.
"""

from __future__ import annotations

from typing import List

from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from gear_nerfstudio.data.datamanager import GearDataManagerConfig
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
from gear_nerfstudio.model.sampling import ProposalConfig
from gear_nerfstudio.pipeline import GearPipelineConfig
from gear_nerfstudio.schedulers import FloatCosineDecaySchedulerConfig
from gear_nerfstudio.trainer_config import GearTrainerConfig

LEARNING_RATE = 0.02
"""Initial learning rate for all parameters (Sec 5.1)."""
EPOCHS_PER_RUN = 20
"""The paper's code trains 20 epochs of a fixed number of iterations; every preset takes the same proportion of
its own default iterations as its epoch for L and L' (Sec 4.3)."""
GEAR1_ROW_FRACTION = 0.25
"""Gear 1's space-time planes keep a quarter of the frames as rows (the paper: 1 row), so that what stays in gear 1
and moves renders blurred, not as a blend of poses (docs/decisions.md)."""

SPARSE_DEPTH_SHARE = 0.25
"""A quarter of each batch's rays go through triangulated points, with the sparse depth loss (docs/decisions.md)."""


def schedule_options(iterations: int) -> List[str]:
    """``ns-train`` options that scale the gear-update schedule to a run of this many iterations, as the presets
    do (an epoch is 1/20 of the run): for commands that train a preset for fewer iterations than its default."""
    return ["--pipeline.gear-updates.iterations-per-epoch", str(max(1, iterations // EPOCHS_PER_RUN))]


def trainer_config(
    method_name: str, model: GearNeRFModelConfig, num_rays_per_batch: int, max_num_iterations: int, warmup: int
) -> GearTrainerConfig:
    """A trainer with Adam (cosine decay after a warmup, as K-Planes) for every parameter group, and gear
    updates with epochs of 1/20 of ``max_num_iterations``.

    The gear function ("gear_field") gets Adam at the same rate without a schedule; the radiance loss
    never reaches it, so only the gear-update step (Sec 4.3) moves it.
    """

    def radiance_optimizer() -> dict:
        return {
            "optimizer": AdamOptimizerConfig(lr=LEARNING_RATE, eps=1e-12),
            "scheduler": FloatCosineDecaySchedulerConfig(warm_up_end=warmup, max_steps=max_num_iterations),
        }

    return GearTrainerConfig(
        method_name=method_name,
        steps_per_eval_batch=500,
        steps_per_eval_image=500,
        steps_per_save=2000,
        steps_per_eval_all_images=max_num_iterations,
        max_num_iterations=max_num_iterations,
        mixed_precision=False,
        pipeline=GearPipelineConfig(
            datamanager=GearDataManagerConfig(
                dataparser=TechnicolorDataParserConfig(),
                train_num_rays_per_batch=num_rays_per_batch,
                eval_num_rays_per_batch=num_rays_per_batch,
                sparse_depth_share=SPARSE_DEPTH_SHARE,
                train_num_images_to_sample_from=40,
                train_num_times_to_repeat_images=100,
                eval_num_images_to_sample_from=8,
                eval_num_times_to_repeat_images=100,
            ),
            model=model,
            gear_updates=GearUpdateConfig(iterations_per_epoch=max_num_iterations // EPOCHS_PER_RUN),
        ),
        optimizers={
            "fields": radiance_optimizer(),
            "proposal_networks": radiance_optimizer(),
            "gear_field": {"optimizer": AdamOptimizerConfig(lr=LEARNING_RATE, eps=1e-12), "scheduler": None},
        },
        vis="viewer",
    )


SMALL_ITERATIONS = 3750
"""Default iterations of the CPU presets: about the CPU time of 5,000 iterations with 24 uniform samples (the proposal
networks' 96 density samples per ray make an iteration 1.4x longer; 3,750 of them took 1.03-1.07x the time). On the
real capture (panoptic_basketball_video, 30 frames at 304x168) held-out PSNR still rose by about 0.5 dB from 2,000 to
6,000 iterations of the uniform sampler (benchmarks/results/real_capture_causes.md)."""


PAPER_ITERATIONS = 30000
"""Default iterations of ``gear-nerf``: 30,000 of 4,096 rays (123 M rays). The paper's code trains N3D 20 epochs of
4,000 iterations of 16,384 rays (1.3 G rays) and Immersive 20 x 4,000 of 5,000 rays (400 M): ``gear-nerf`` keeps the
paper's L = 3, L' = 10 in proportion (epochs of 1,500 iterations: updates at 4,500, 9,000 and 13,500, as the
paper's at 12,000, 24,000 and 36,000 of 80,000) on a 3x (Immersive) to 11x (N3D) smaller ray budget."""


def small_model(num_gears: int) -> GearNeRFModelConfig:
    """Planes, MLPs and proposal networks sized for a CPU (64 and 32 proposal samples on planes of 64 and 128, then
    24 base samples); the paper's L = 3, L' = 10 with epochs of 187 iterations (1/20 of the preset's 3,750), i.e.
    updates at steps 561, 1,122 and 1,683 at any scene size."""
    return GearNeRFModelConfig(
        num_gears=num_gears,
        feature_dim=16,
        resolutions=(32, 64),
        gear_resolution=32,
        hidden_dim=32,
        hidden_dim_color=32,
        sam_head_dim=16,
        num_samples=24,
        base_sampler="proposal",
        proposal=ProposalConfig(num_samples=(64, 32), resolutions=(64, 128)),
        gear1_row_fraction=GEAR1_ROW_FRACTION,
    )


gear_nerf = MethodSpecification(
    config=trainer_config(
        "gear-nerf",
        GearNeRFModelConfig(
            num_gears=4,
            feature_dim=32,
            num_samples=64,
            base_sampler="proposal",
            gear1_row_fraction=GEAR1_ROW_FRACTION,
        ),
        num_rays_per_batch=4096,
        max_num_iterations=PAPER_ITERATIONS,
        warmup=512,
    ),
    description="Gear-NeRF (CVPR 2024): gears, motion-aware spatio-temporal sampling, 4D SAM embedding.",
)

gear_nerf_small = MethodSpecification(
    config=trainer_config(
        "gear-nerf-small", small_model(num_gears=4), 1024, max_num_iterations=SMALL_ITERATIONS, warmup=100
    ),
    description="Gear-NeRF CPU preview preset: small planes, 24 base samples per ray from proposal networks, 1024 rays "
    "per batch.",
)

gear_nerf_baseline = MethodSpecification(
    config=trainer_config(
        "gear-nerf-baseline", small_model(num_gears=1), 1024, max_num_iterations=SMALL_ITERATIONS, warmup=100
    ),
    description="Baseline for the benchmark: one gear (plain K-Planes), small preset sizes and sampling.",
)
