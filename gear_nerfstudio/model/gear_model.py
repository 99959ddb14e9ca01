"""Gear-NeRF model for nerfstudio (Liu et al., CVPR 2024).

Per batch of rays: base sampler (uniform, n = 64 in the paper, or a proposal network) -> gear level p of
each base sample -> split sampler (Sec 4.4) -> GearField (Eq 3-7) -> renderers for colour (Eq 1),
depth, accumulation, SAM features (Eq 8), gear level and samples per ray. Losses: Eq 2, Eq 9 and the
K-Planes regularisers. The gear function g is a separate parameter group ("gear_field") that the
radiance optimiser never sees; it is trained by the gear-update step (Sec 4.3, Eq 10-11).
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Set, Tuple, Type

import matplotlib
import numpy as np
import torch
import tyro
from jaxtyping import Bool, Float, Int
from torch import Tensor
from torch.nn import Parameter

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.losses import MSELoss, distortion_loss, interlevel_loss
from nerfstudio.model_components.ray_samplers import (
    ProposalNetworkSampler,
    UniformLinDispPiecewiseSampler,
    UniformSampler,
)
from nerfstudio.model_components.renderers import AccumulationRenderer, DepthRenderer, RGBRenderer
from nerfstudio.model_components.scene_colliders import AABBBoxCollider, NearFarCollider
from nerfstudio.models.base_model import Model, ModelConfig
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE

from gear_nerfstudio import distributed
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.fields.gear_field import GearField, GearFieldHeadNames, sample_points
from gear_nerfstudio.fields.proposal_field import ProposalDensityField
from gear_nerfstudio.fields.seen_space import SeenSpace
from gear_nerfstudio.model.image_render import render_image
from gear_nerfstudio.model.moving_region import EvalViews, region_sums
from gear_nerfstudio.model.renderers import GearLevelRenderer, SamRenderer
from gear_nerfstudio.model.split_sampler import SplitSampler


@dataclass
class GearNeRFModelConfig(ModelConfig):
    """Gear-NeRF model config. Defaults are the paper's settings (Sec 5.1) where it states them."""

    _target: Type = field(default_factory=lambda: GearNeRFModel)
    enable_collider: tyro.conf.Suppress[bool] = False
    """Not used: the model clips rays to near/far (or the scene box) itself."""
    collider_params: tyro.conf.Suppress[Optional[Dict[str, float]]] = None
    """Not used: near_plane / far_plane below."""
    loss_coefficients: tyro.conf.Suppress[Dict[str, float]] = field(default_factory=dict)
    """Not used: each loss has its own multiplier below."""
    prompt: tyro.conf.Suppress[Optional[str]] = None
    """Not used (a text prompt for language-field methods)."""

    near_plane: Optional[float] = None
    """Near plane in scene units; None takes ``metadata["near"]`` from the dataparser."""
    far_plane: Optional[float] = None
    """Far plane in scene units; None takes ``metadata["far"]``. Without either: clip rays to the scene box."""
    unbounded: Optional[bool] = None
    """Contract unbounded space (SceneContraction, order=inf); None takes ``metadata["unbounded"]``."""
    num_frames: Optional[int] = None
    """Frames T of the window; None takes ``metadata["num_frames"]`` (1, a static scene, when absent)."""
    num_gears: int = 4
    """N_gear."""
    feature_dim: int = 32
    """M, the dimension of the feature f (Eq 3)."""
    resolutions: Tuple[int, ...] = (64, 128, 256, 512)
    """Spatial resolutions of the planes (features concatenated across resolutions before B_j)."""
    gear_feature_dim: int = 32
    """M', channels of the gear function's planes h', k' (Eq 4; the paper does not state it). The radiance field
    starts the same whatever M'."""
    gear_resolution: int = 64
    """Spatial resolution of h', k'."""
    gear_time_resolution: Optional[int] = None
    """Temporal resolution of k'; None uses num_frames."""
    time_resolutions: Optional[Tuple[int, ...]] = None
    """Rows of each gear's space-time planes k^G, one value per gear; None: linear from gear 1's rows
    (``gear1_row_fraction``) to num_frames at the top gear (Sec 4.4)."""
    gear1_row_fraction: float = 0.0
    """Rows of gear 1's space-time planes as a fraction of num_frames, growing linearly to num_frames at the top
    gear; 0: the paper's single row (Sec 4.4), a static gear 1. Ignored when ``time_resolutions`` is set."""
    geo_feat_dim: int = 15
    """Features from the density MLP to the colour MLP."""
    hidden_dim: int = 64
    """Width of the density and SAM MLPs."""
    hidden_dim_color: int = 64
    """Width of the colour MLP."""
    sam_dim: int = 256
    """Dimension of the SAM encoder features."""
    appearance_dim: int = 16
    """Channels of the per-camera appearance code in the colour MLP (exposure, white balance); 0: off. Other
    cameras (held-out, viewer) take the training cameras' mean code."""
    min_views: int = 0
    """Evaluation renders (viewer, ns-render, ns-eval) keep the density only where at least this many training
    cameras (all of a smaller rig's) see a point; 0: all space, as training."""
    initial_density: Optional[float] = None
    """Density per scene unit the radiance field starts from (the density MLP's output bias); None: PyTorch's
    initialisation, about exp(-1) = 0.37 (K-Planes)."""
    plane_kernel: Literal["torch", "warp"] = "torch"
    """Plane lookups of the radiance field and the proposal networks: "torch" (grid_sample per plane) or "warp" (one
    fused Warp kernel, same values; needs the ``kernel`` extra). See benchmarks/results/plane_kernel.md."""
    sam_head_dim: Optional[int] = 32
    """SAM embedding dimension per sample before the learned lift to sam_dim; None predicts sam_dim."""
    num_samples: int = 64
    """n, base samples per ray (Sec 4.4)."""
    split_base: int = 2
    """A base sample at gear p is split into split_base^(p-1) samples (Sec 4.4)."""
    base_sampler: Literal["uniform", "proposal"] = "uniform"
    """Base samples: stratified uniform between near and far (paper) or a proposal network (K-Planes)."""
    num_proposal_samples: Tuple[int, ...] = (256, 128)
    """Samples per ray of each proposal iteration."""
    proposal_resolutions: Tuple[int, ...] = (128, 256)
    """Spatial resolution of each proposal network's planes."""
    proposal_feature_dim: int = 8
    """Plane channels of the proposal networks."""
    proposal_time_resolution: Optional[int] = None
    """Temporal resolution of the proposal networks; None uses half the frames (K-Planes)."""
    proposal_warmup: int = 5000
    """Scales the proposal update interval from 1 to proposal_update_every over this many steps."""
    proposal_update_every: int = 5
    """Update the proposal networks every this many steps after the warmup."""
    use_proposal_weight_anneal: bool = True
    """Anneal the proposal weights before PDF sampling (Mip-NeRF 360, Eq 18)."""
    proposal_weights_anneal_slope: float = 10.0
    """Slope of the annealing function."""
    proposal_weights_anneal_max_num_iters: int = 1000
    """Iterations over which the annealing reaches 1."""
    background_color: Literal["random", "last_sample", "black", "white"] = "last_sample"
    """Background colour; 'last_sample': each ray's last sample's colour (as nerfacto, for captures without
    alpha)."""
    sam_loss_mult: float = 1.0
    """Weight of L_SAM (Eq 9), applied when the batch has "sam_features"."""
    plane_tv_mult: float = 2e-4
    """Total variation of the radiance planes (K-Planes DyNeRF)."""
    l1_time_planes_mult: float = 1e-4
    """L1 deviation of the space-time planes from 1 (K-Planes DyNeRF)."""
    time_smoothness_mult: float = 1e-3
    """Second difference along t of the space-time planes (K-Planes DyNeRF)."""
    plane_tv_proposal_mult: float = 2e-4
    """Plane TV of the proposal networks (K-Planes DyNeRF)."""
    l1_time_planes_proposal_mult: float = 1e-4
    """L1 time planes of the proposal networks (K-Planes DyNeRF)."""
    time_smoothness_proposal_mult: float = 1e-5
    """Time smoothness of the proposal networks (K-Planes DyNeRF)."""
    interlevel_loss_mult: float = 1.0
    """Proposal (interlevel) loss, proposal base sampler only."""
    distortion_loss_mult: float = 0.0
    """Weight of the distortion loss (Mip-NeRF 360) on the base samples, proposal base sampler only; 0: off."""
    render_outputs: Tuple[str, ...] = ("rgb", "depth", "accumulation", "gear")
    """Outputs of full-image renders (viewer, ns-render, ns-eval); add "sam", "gear_level" or "num_samples" to
    compute those as well (the SAM feature map costs an MLP per sample and 256 channels per pixel)."""
    render_num_samples: Optional[int] = None
    """n at full-image renders (viewer, ns-render, ns-eval, the gear updates' views, tracking); None: num_samples.
    Fewer is faster at a small change of the image (`benchmarks/results/render_speed.md`)."""
    render_num_proposal_samples: Optional[Tuple[int, ...]] = None
    """Samples of each proposal iteration at full-image renders (proposal base sampler); None:
    num_proposal_samples."""
    render_chunk_samples: Optional[int] = None
    """Field samples evaluated at once in full-image renders (the memory bound; a chunk takes as many rays as fit);
    None: 2^15 on the CPU, 2^21 on a GPU."""


MIN_MSE = 1e-10
"""Floor of the mean squared error in PSNR: a perfect prediction reports 100 dB instead of inf."""


def psnr(prediction: Tensor, target: Tensor) -> Tensor:
    """PSNR in dB for colours in [0, 1], -10 log10(MSE), with the MSE clamped at ``MIN_MSE``.

    Without the floor an exact match (all-black or all-white frames, background pixels) gives log10(0),
    i.e. inf, which poisons every mean over images that ns-eval and the logs take.
    """
    return -10.0 * torch.log10(torch.mean((prediction - target) ** 2).clamp(min=MIN_MSE))


NEAR_LAYER_DEPTH = 0.25
"""A pixel of an evaluation view is in a near layer when its depth is below this share of the training rays'
median depth."""
NEAR_LAYER_WARNING = 0.2
"""Share of an opaque evaluation view (accumulation above 0.9) in a near layer that training reports."""


def near_layer_pixels(depth: Float[Tensor, "*bs 1"], training_depth: Tensor) -> Bool[Tensor, "*bs 1"]:
    """Pixels of a render whose depth is below ``NEAR_LAYER_DEPTH`` x the training rays' median depth: on a rig whose
    cameras see the scene from similar distances, a held-out view that ends that close sees a layer in front of
    itself (none before any training batch has set the reference)."""
    return depth < NEAR_LAYER_DEPTH * training_depth


def near_layer(depth: Float[Tensor, "*bs 1"], training_depth: Tensor) -> float:
    """Share of a render's pixels in a near layer (``near_layer_pixels``)."""
    return float(near_layer_pixels(depth, training_depth).float().mean())


def near_layer_warning(views: List[Tuple[str, Dict[str, float]]], training_depth: float) -> Optional[str]:
    """One line naming the views (label, image metrics) that are opaque (accumulation above 0.9) and have more than
    ``NEAR_LAYER_WARNING`` of their pixels in a near layer; None when there are none."""
    layered = [
        f"{label} ({100 * metrics['near_layer']:.0f} %)"
        for label, metrics in views
        if metrics["near_layer"] > NEAR_LAYER_WARNING and metrics["accumulation"] > 0.9
    ]
    if not layered:
        return None
    return (
        f"Gear-NeRF: an opaque layer sits in front of the camera, closer than {NEAR_LAYER_DEPTH:g} x the training rays' "
        f"median depth ({training_depth:.3g}), in {len(layered)} of {len(views)} evaluation views: {', '.join(layered)}"
    )


def lpips_weights_path() -> Path:
    """Where torchvision keeps the AlexNet weights that torchmetrics' LPIPS needs."""
    from torchvision.models import AlexNet_Weights

    return Path(torch.hub.get_dir()) / "checkpoints" / Path(AlexNet_Weights.DEFAULT.url).name


@contextlib.contextmanager
def evaluating(model: Model) -> Iterator[None]:
    """Render in evaluation mode (no sample jitter), restoring the model's mode afterwards."""
    was_training = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was_training)


class GearNeRFModel(Model):
    """Gear-NeRF: serial 4D feature volumes, gears, motion-aware sampling and a 4D SAM embedding."""

    config: GearNeRFModelConfig

    def populate_modules(self) -> None:
        """Field, samplers, collider, renderers, losses and metrics."""
        config = self.config
        metadata: Dict[str, Any] = self.kwargs.get("metadata") or {}
        self.num_frames = int(config.num_frames or metadata.get("num_frames", 1))
        unbounded = bool(metadata.get("unbounded", False) if config.unbounded is None else config.unbounded)
        contraction = SceneContraction(order=float("inf")) if unbounded else None

        self.field = GearField(
            self.scene_box.aabb,
            num_frames=self.num_frames,
            num_gears=config.num_gears,
            feature_dim=config.feature_dim,
            resolutions=config.resolutions,
            gear_feature_dim=config.gear_feature_dim,
            gear_resolution=config.gear_resolution,
            gear_time_resolution=config.gear_time_resolution,
            time_resolutions=config.time_resolutions,
            gear1_row_fraction=config.gear1_row_fraction,
            geo_feat_dim=config.geo_feat_dim,
            hidden_dim=config.hidden_dim,
            hidden_dim_color=config.hidden_dim_color,
            sam_dim=config.sam_dim,
            sam_head_dim=config.sam_head_dim,
            spatial_distortion=contraction,
            appearance_dim=config.appearance_dim if metadata.get("camera_names") else 0,
            num_cameras=len(metadata.get("camera_names", ())),
            trained_cameras=sorted(set(torch.as_tensor(metadata.get("camera_ids", [])).tolist())),
            initial_density=config.initial_density,
            plane_kernel=config.plane_kernel,
        )

        self.proposal_networks = torch.nn.ModuleList()
        render_proposal = config.render_num_proposal_samples
        if render_proposal is not None and len(render_proposal) != len(config.num_proposal_samples):
            raise InputError(
                f"--pipeline.model.render-num-proposal-samples has {len(render_proposal)} values but the model has "
                f"{len(config.num_proposal_samples)} proposal iterations (--pipeline.model.num-proposal-samples)"
            )
        if config.base_sampler == "proposal":
            time_resolution = config.proposal_time_resolution or max(1, self.num_frames // 2)
            for i in range(len(config.num_proposal_samples)):
                self.proposal_networks.append(
                    ProposalDensityField(
                        self.scene_box.aabb,
                        resolution=config.proposal_resolutions[min(i, len(config.proposal_resolutions) - 1)],
                        time_resolution=time_resolution,
                        feature_dim=config.proposal_feature_dim,
                        spatial_distortion=contraction,
                        plane_kernel=config.plane_kernel,
                    )
                )

            def update_schedule(step: int) -> float:
                return np.clip(
                    np.interp(step, [0, config.proposal_warmup], [0, config.proposal_update_every]),
                    1,
                    config.proposal_update_every,
                )

            initial_sampler = UniformLinDispPiecewiseSampler() if unbounded else UniformSampler()
            self.base_sampler = ProposalNetworkSampler(
                num_proposal_samples_per_ray=config.num_proposal_samples,
                num_nerf_samples_per_ray=config.num_samples,
                num_proposal_network_iterations=len(config.num_proposal_samples),
                update_sched=update_schedule,
                initial_sampler=initial_sampler,
            )
        else:
            self.base_sampler = UniformSampler(num_samples=config.num_samples)
        self.split_sampler = SplitSampler(split_base=config.split_base)

        near = metadata.get("near") if config.near_plane is None else config.near_plane
        far = metadata.get("far") if config.far_plane is None else config.far_plane
        if near is None or far is None:
            CONSOLE.log("[yellow]Gear-NeRF: no near/far in config or metadata; rays are clipped to the scene box.")
            self.collider = AABBBoxCollider(self.scene_box)
        else:
            self.collider = NearFarCollider(near_plane=float(near), far_plane=float(far), reset_near_plane=False)

        self.renderer_rgb = RGBRenderer(background_color=config.background_color)
        self.renderer_accumulation = AccumulationRenderer()
        self.renderer_depth = DepthRenderer(method="median")
        self.renderer_sam = SamRenderer()
        self.renderer_gear_level = GearLevelRenderer()
        # the "gear" image's turbo colour map (as nerfstudio's apply_colormap, whose range asserts and per-call
        # table upload each cost a host sync every training step)
        self.register_buffer("gear_colors", torch.tensor(matplotlib.colormaps["turbo"].colors), persistent=False)
        self.rgb_loss = MSELoss()
        self._lpips: Dict[str, Any] = {}
        self.render_hooks: List[Callable[[Cameras, Dict[str, Tensor]], Dict[str, Tensor]]] = []
        """Extra outputs of full-image renders (``get_outputs_for_camera``), such as the viewer's tracked mask."""
        self.warned_no_time = False
        self.extra_outputs: Set[str] = set()
        """Outputs that full-image renders compute beside ``render_outputs`` (``rendering``)."""
        self.register_buffer("training_depth", torch.zeros(()))
        self.eval_views: Optional[EvalViews] = None
        """The evaluation views' cameras, names and moving regions (set by the pipeline): with them, image metrics
        include the sums of ``moving_region.region_sums``."""

    def gear_values(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*bs 1"]]
    ) -> Float[Tensor, "*bs"]:
        """Eq 4: differentiable gear value g(x, t) (world positions, times in [0, 1])."""
        return self.field.gear_values(positions, times)

    def gear_levels(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*bs 1"]]
    ) -> Int[Tensor, "*bs"]:
        """Eq 5: gear level p(x, t)."""
        return self.field.gear_levels(positions, times)

    def gear_assignment(self) -> Dict[str, Tensor]:
        """A copy of what a gear update changes (``GearField.gear_assignment``)."""
        return self.field.gear_assignment()

    def restore_gear_assignment(self, assignment: Dict[str, Tensor]) -> None:
        """Undo a gear update (``GearField.restore_gear_assignment``)."""
        self.field.restore_gear_assignment(assignment)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """Groups "fields" (planes h, k^G, B, F_theta), "gear_field" (h', k' only), "proposal_networks" if used."""
        groups = {
            "fields": self.field.radiance_parameters(),
            "gear_field": list(self.field.gear_function.parameters()),
        }
        if len(self.proposal_networks):
            groups["proposal_networks"] = list(self.proposal_networks.parameters())
        return groups

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        """Proposal weight annealing and update schedule, when the proposal sampler is used."""
        callbacks: List[TrainingCallback] = []
        if not isinstance(self.base_sampler, ProposalNetworkSampler) or not self.config.use_proposal_weight_anneal:
            return callbacks
        sampler = self.base_sampler
        max_iters = self.config.proposal_weights_anneal_max_num_iters
        slope = self.config.proposal_weights_anneal_slope

        def set_anneal(step: int) -> None:
            fraction = np.clip(step / max_iters, 0, 1)
            sampler.set_anneal((slope * fraction) / ((slope - 1) * fraction + 1))

        return callbacks + [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], set_anneal, update_every_num_iters=1),
            TrainingCallback(
                [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], sampler.step_cb, update_every_num_iters=1
            ),
        ]

    def sample_base(self, ray_bundle: RayBundle) -> Tuple[RaySamples, List[Tensor], List[RaySamples]]:
        """Base samples (n per ray) and, for the proposal sampler, its weights and samples per level."""
        if isinstance(self.base_sampler, ProposalNetworkSampler):
            density_fns = [functools.partial(net.density_fn, times=ray_bundle.times) for net in self.proposal_networks]
            return self.base_sampler(ray_bundle, density_fns=density_fns)
        return self.base_sampler(ray_bundle), [], []

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Any]:
        """Render rgb, depth, accumulation, sam (Eq 8), gear_level, gear and num_samples per ray."""
        base_samples, weights_list, ray_samples_list = self.sample_base(ray_bundle)
        split = self.split_sampler(base_samples, self.field.gear_levels)
        samples = split.ray_samples
        appearance = self.field.appearance
        packed = sample_points(
            split.pack(samples.frustums.get_positions()),
            None if samples.times is None else split.pack(samples.times),
            split.pack(samples.frustums.directions),
            None if appearance is None else appearance(ray_bundle.metadata, ray_bundle.origins.shape[0])[split.ray_index],
        )
        field_outputs = self.field(packed)
        density = torch.where(split.valid[..., None], split.unpack(field_outputs[FieldHeadNames.DENSITY]), 0.0)
        weights = samples.get_weights(density)

        rgb = self.renderer_rgb(rgb=split.unpack(field_outputs[FieldHeadNames.RGB]), weights=weights)
        accumulation = self.renderer_accumulation(weights=weights)
        sam = self.field.lift_sam(self.renderer_sam(split, weights, field_outputs[GearFieldHeadNames.SAM]), accumulation)
        gear_level = self.renderer_gear_level(split, weights, field_outputs[GearFieldHeadNames.GEAR_LEVEL])
        outputs: Dict[str, Any] = {
            "rgb": rgb,
            "depth": self.renderer_depth(weights=weights, ray_samples=samples),
            "accumulation": accumulation,
            "sam": sam,
            "gear_level": gear_level,
            "gear": self.gear_image(gear_level),
            "num_samples": split.num_samples_per_ray[:, None].to(weights.dtype),
        }
        if self.training:
            # The K-Planes regularisers are computed here, in the forward pass, not in get_loss_dict: under DDP
            # (several GPUs) a plane that only the loss would use (a gear in use but absent from this process's
            # batch) is not reached from the forward's outputs, so DDP marks it unused, and the backward pass then
            # fails when its gradient arrives.
            outputs.update({f"regulariser_{name}": value for name, value in self.field.regularisers().items()})
        if ray_samples_list:
            weights_list.append(split.to_base(weights))
            ray_samples_list.append(base_samples)
            if self.training:
                outputs["weights_list"] = weights_list
                outputs["ray_samples_list"] = ray_samples_list
            for i in range(len(ray_samples_list) - 1):
                outputs[f"prop_depth_{i}"] = self.renderer_depth(
                    weights=weights_list[i], ray_samples=ray_samples_list[i]
                )
        return outputs

    def gear_image(self, gear_level: Float[Tensor, "*bs 1"]) -> Float[Tensor, "*bs 3"]:
        """The "gear" output: the rendered gear level on the turbo colour map, gear 1 to N_gear."""
        fraction = ((gear_level.detach() - 1.0) / max(self.config.num_gears - 1, 1)).clamp(0.0, 1.0)
        return self.gear_colors[(fraction.nan_to_num(0.0) * 255).long()[..., 0]]

    @contextlib.contextmanager
    def rendering(self, *names: str) -> Iterator[None]:
        """Full-image renders inside also compute the outputs ``names`` (beside the config's ``render_outputs``)."""
        before = self.extra_outputs
        self.extra_outputs = before | set(names)
        try:
            yield
        finally:
            self.extra_outputs = before

    @contextlib.contextmanager
    def render_sampling(self) -> Iterator[int]:
        """Inside, the base sampler draws n = ``render_num_samples`` per ray (and ``render_num_proposal_samples``)
        where they are set; yields n."""
        sampler, config = self.base_sampler, self.config
        if isinstance(sampler, ProposalNetworkSampler):
            counts = {
                "num_nerf_samples_per_ray": config.render_num_samples,
                "num_proposal_samples_per_ray": config.render_num_proposal_samples,
            }
        else:
            counts = {"num_samples": config.render_num_samples}
        counts = {name: value for name, value in counts.items() if value is not None}
        before = {name: getattr(sampler, name) for name in counts}
        for name, value in counts.items():
            setattr(sampler, name, value)
        try:
            yield config.render_num_samples or config.num_samples
        finally:
            for name, value in before.items():
                setattr(sampler, name, value)

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """Full-image renders: ``image_render.render_image`` (only the outputs asked for, in large chunks)."""
        return render_image(self, camera_ray_bundle, self.extra_outputs)

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box: Optional[OrientedBox] = None) -> Dict[str, Tensor]:
        """The model's full-image render (``get_outputs_for_camera_ray_bundle``), plus the outputs of the
        ``render_hooks``. A camera without a time is rendered at time 0, with a warning (once) for a video:
        ``ns-render interpolate`` drops the times."""
        if camera.times is None and self.num_frames > 1 and not self.warned_no_time:
            CONSOLE.log(
                "[yellow]Gear-NeRF: a camera without a time is rendered at time 0 (ns-render interpolate drops the "
                "cameras' times); `ns-gear-path` writes camera paths with times for `ns-render camera-path`."
            )
            self.warned_no_time = True
        outputs = super().get_outputs_for_camera(camera, obb_box=obb_box)
        for hook in self.render_hooks:
            outputs.update(hook(camera, outputs))
        return outputs

    @property
    def num_gears(self) -> int:
        """N_gear."""
        return self.field.num_gears

    @torch.no_grad()
    def render_view(self, camera: Cameras) -> Dict[str, Tensor]:
        """A full render of one camera in evaluation mode (no sample jitter), restoring the mode afterwards, with the
        SAM feature map (Eq 8) beside the config's ``render_outputs`` (the gear updates' loss maps use it)."""
        rays = camera.to(self.device).generate_rays(camera_indices=0, keep_shape=True)
        with evaluating(self), self.rendering("sam"):
            return self.get_outputs_for_camera_ray_bundle(rays)

    def see_from(self, cameras: Cameras, min_views: Optional[int] = None) -> None:
        """Renders in evaluation mode keep the density where at least ``min_views`` (default: the config's) of these
        training cameras see a point (`fields.seen_space.SeenSpace`); nothing changes when it is 0."""
        min_views = self.config.min_views if min_views is None else min_views
        seen = None
        if min_views > 0:
            seen = SeenSpace(cameras, min_views, self.field.aabb, self.field.spatial_distortion)
        self._set_seen_space(seen)

    @contextlib.contextmanager
    def all_space(self) -> Iterator[None]:
        """Inside, renders take the density everywhere (``see_from`` is set aside), as training does: the gear
        updates render training views so."""
        seen = self.field.seen_space
        self._set_seen_space(None)
        try:
            yield
        finally:
            self._set_seen_space(seen)

    def _set_seen_space(self, seen: Optional[SeenSpace]) -> None:
        """The field and the proposal networks share one ``seen_space``."""
        for field in [self.field, *self.proposal_networks]:
            field.seen_space = seen

    @torch.no_grad()
    def visible_surface(self, camera: Cameras, outputs: Dict[str, Tensor]) -> Float[Tensor, "H W 3"]:
        """The world point each pixel of a one-camera render sees: its ray at the median depth."""
        rays = camera.to(self.device).generate_rays(camera_indices=0, keep_shape=True)
        return rays.origins + rays.directions * outputs["depth"]

    @torch.no_grad()
    def visible_gear_levels(self, camera: Cameras, outputs: Optional[Dict[str, Tensor]] = None) -> Int[Tensor, "H W"]:
        """Eq 5 at the surface each pixel of a one-camera render sees: the gear map.

        ``outputs``: that camera's render, made here when not given.
        """
        surface = self.visible_surface(camera, self.render_view(camera) if outputs is None else outputs)
        times = None if camera.times is None else camera.times.to(self.device).reshape(1, 1, 1)
        return self.field.gear_levels(surface, None if times is None else times.expand(*surface.shape[:-1], 1))

    @torch.no_grad()
    def sample_weights(
        self, camera: Cameras, pixels: Float[Tensor, "N 2"]
    ) -> Tuple[Float[Tensor, "M 3"], Float[Tensor, "M 1"], Float[Tensor, "M"]]:
        """Base samples (n per ray, stratified uniform) on the rays through pixels (row, col) of one camera:
        positions, times and volume-rendering weights (Eq 1)."""
        rays = camera.to(self.device).generate_rays(camera_indices=0, coords=pixels.to(self.device) + 0.5)
        samples = UniformSampler(num_samples=self.config.num_samples)(self.collider(rays))
        positions = samples.frustums.get_positions()
        density = self.field.density_fn(positions, samples.times)
        weights = samples.get_weights(density)[..., 0]
        return positions.reshape(-1, 3), samples.times.reshape(-1, 1), weights.reshape(-1)

    def get_metrics_dict(self, outputs: Dict[str, Any], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """PSNR of the batch and the mean number of samples per ray; a training batch also sets
        ``training_depth``, the median depth of its rays averaged over processes (the reference of ``near_layer``)."""
        image = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        if self.training:
            self.training_depth.copy_(distributed.average(outputs["depth"].detach().median()))
        return {
            "psnr": psnr(outputs["rgb"].detach(), image),
            "samples_per_ray": outputs["num_samples"].mean(),
        }

    def get_loss_dict(
        self, outputs: Dict[str, Any], batch: Dict[str, Tensor], metrics_dict: Optional[Dict[str, Tensor]] = None
    ) -> Dict[str, Tensor]:
        """Eq 2 (rgb), Eq 9 (sam, when the batch has "sam_features") and the K-Planes regularisers."""
        config = self.config
        pred_rgb, image = self.renderer_rgb.blend_background_for_loss_computation(
            pred_image=outputs["rgb"],
            pred_accumulation=outputs["accumulation"],
            gt_image=batch["image"].to(self.device),
        )
        loss_dict = {"rgb_loss": self.rgb_loss(image, pred_rgb)}
        if "sam_features" in batch:
            target = batch["sam_features"].to(self.device)
            loss_dict["sam_loss"] = config.sam_loss_mult * self.rgb_loss(target, outputs["sam"])
        if self.training:
            loss_dict["plane_tv"] = config.plane_tv_mult * outputs["regulariser_plane_tv"]
            loss_dict["l1_time_planes"] = config.l1_time_planes_mult * outputs["regulariser_l1_time_planes"]
            loss_dict["time_smoothness"] = config.time_smoothness_mult * outputs["regulariser_time_smoothness"]
            if "weights_list" in outputs:
                proposal = [net.regularisers() for net in self.proposal_networks]
                loss_dict["plane_tv_proposal"] = config.plane_tv_proposal_mult * sum(r["plane_tv"] for r in proposal)
                loss_dict["l1_time_planes_proposal"] = config.l1_time_planes_proposal_mult * sum(
                    r["l1_time_planes"] for r in proposal
                )
                loss_dict["time_smoothness_proposal"] = config.time_smoothness_proposal_mult * sum(
                    r["time_smoothness"] for r in proposal
                )
                loss_dict["interlevel_loss"] = config.interlevel_loss_mult * interlevel_loss(
                    outputs["weights_list"], outputs["ray_samples_list"]
                )
                if config.distortion_loss_mult > 0:
                    loss_dict["distortion_loss"] = config.distortion_loss_mult * distortion_loss(
                        outputs["weights_list"], outputs["ray_samples_list"]
                    )
        return loss_dict

    def lpips(self) -> Optional[torch.nn.Module]:
        """torchmetrics LPIPS if its AlexNet weights are already on disk (never downloads), else None."""
        if "metric" not in self._lpips:
            path = lpips_weights_path()
            if path.is_file():
                from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

                self._lpips["metric"] = LearnedPerceptualImagePatchSimilarity(normalize=True)
            else:
                CONSOLE.log(f"[yellow]LPIPS skipped: AlexNet weights not found at {path} (nothing is downloaded).")
                self._lpips["metric"] = None
        metric = self._lpips["metric"]
        return None if metric is None else metric.to(self.device)

    def image_metrics(self, rgb: Float[Tensor, "H W 3"], image: Float[Tensor, "H W C"]) -> Dict[str, float]:
        """PSNR, SSIM (and LPIPS when its weights are local) of a render against its image (RGBA images are
        blended with the background first)."""
        from torchmetrics.functional.image import structural_similarity_index_measure

        image = self.renderer_rgb.blend_background(image.to(self.device))
        rgb = rgb.to(self.device)
        image_nchw = torch.moveaxis(image, -1, 0)[None]
        rgb_nchw = torch.moveaxis(rgb, -1, 0)[None]
        metrics = {
            "psnr": float(psnr(rgb, image)),
            "ssim": float(structural_similarity_index_measure(rgb_nchw, image_nchw, data_range=1.0)),
        }
        lpips = self.lpips()
        if lpips is not None:
            metrics["lpips"] = float(lpips(rgb_nchw.clamp(0, 1), image_nchw.clamp(0, 1)))
        return metrics

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """PSNR, SSIM (and LPIPS when its weights are local), accumulation and near layer on a full image; with
        ``eval_views``, the sums of ``moving_region.region_sums`` for that view; rgb, depth, gear images."""
        image = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        rgb = outputs["rgb"]
        metrics_dict = self.image_metrics(rgb, image)
        metrics_dict["accumulation"] = float(outputs["accumulation"].mean())
        metrics_dict["near_layer"] = near_layer(outputs["depth"], self.training_depth)
        if self.eval_views is not None and "image_idx" in batch:
            index = int(batch["image_idx"])
            levels = self.visible_gear_levels(self.eval_views.camera(index), outputs)
            metrics_dict.update(region_sums(rgb, image, self.eval_views.moving(index, image), levels))
        images_dict = {
            "img": torch.cat([image, rgb], dim=1),
            "accumulation": colormaps.apply_colormap(outputs["accumulation"]),
            "depth": colormaps.apply_depth_colormap(outputs["depth"], accumulation=outputs["accumulation"]),
            "gear": outputs["gear"],
        }
        return metrics_dict, images_dict
