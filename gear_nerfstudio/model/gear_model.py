"""Gear-NeRF model for nerfstudio (Liu et al., CVPR 2024).

Per batch of rays, one forward pass: base samples (uniform, n = 64 in the paper, or a proposal network), the gear
level p of each and the split sampler (Sec 4.4; ``sampling.GearSampler``) -> GearField (Eq 3-7) and renderers for
colour (Eq 1), depth, accumulation, SAM features (Eq 8), gear level and samples per ray (``rendering.GearRenderer``).
Full-image renders are sparse forward passes in chunks (``image_render``). Losses: Eq 2, Eq 9 and the K-Planes
regularisers (``losses.GearLosses``); image metrics in ``metrics``. The gear function g is a separate parameter group
("gear_field") that the radiance optimiser never sees; it is trained by the gear-update step (Sec 4.3, Eq 10-11).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Set, Tuple, Type

import torch
import tyro
from jaxtyping import Float, Int
from torch import Tensor
from torch.nn import Parameter

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.ray_samplers import UniformSampler
from nerfstudio.model_components.scene_colliders import AABBBoxCollider, NearFarCollider
from nerfstudio.models.base_model import Model, ModelConfig
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE

from gear_nerfstudio import distributed
from gear_nerfstudio.fields.gear_field import GearField
from gear_nerfstudio.fields.proposal_field import ProposalDensityField
from gear_nerfstudio.fields.seen_space import SeenSpace
from gear_nerfstudio.model.image_render import render_image
from gear_nerfstudio.model.losses import GearLosses, LossWeights
from gear_nerfstudio.model.metrics import ImageMetrics, near_layer, psnr
from gear_nerfstudio.model.moving_region import EvalViews, region_sums
from gear_nerfstudio.model.rendering import FullImageRenders, GearRenderer, RenderRequest
from gear_nerfstudio.model.sampling import GearSampler, ProposalConfig, SampleCounts


@dataclass
class GearNeRFModelConfig(ModelConfig):
    """Gear-NeRF model config. Defaults are the paper's settings (Sec 5.1) where it states them."""

    _target: Type = field(default_factory=lambda: GearNeRFModel)
    enable_collider: tyro.conf.Suppress[bool] = False
    """Not used: the model clips rays to near/far (or the scene box) itself."""
    collider_params: tyro.conf.Suppress[Optional[Dict[str, float]]] = None
    """Not used: near_plane / far_plane below."""
    loss_coefficients: tyro.conf.Suppress[Dict[str, float]] = field(default_factory=dict)
    """Not used: each loss has its own multiplier (losses)."""
    prompt: tyro.conf.Suppress[Optional[str]] = None
    """Not used (a text prompt for language-field methods)."""
    eval_num_rays_per_chunk: tyro.conf.Suppress[int] = 4096
    """Not used: full-image renders are chunked by samples (render.chunk_samples)."""

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
    """Rows of each gear's space-time planes k^G; None: from gear1_row_fraction (Sec 4.4)."""
    gear1_row_fraction: float = 0.0
    """Gear 1's space-time rows as a fraction of num_frames, linear to num_frames at the top gear; 0: one row, the
    paper's static gear 1 (Sec 4.4)."""
    geo_feat_dim: int = 15
    """Features from the density MLP to the colour MLP."""
    hidden_dim: int = 64
    """Width of the density and SAM MLPs."""
    hidden_dim_color: int = 64
    """Width of the colour MLP."""
    sam_dim: int = 256
    """Dimension of the SAM encoder features."""
    appearance_dim: int = 16
    """Channels of the per-camera appearance code (exposure, white balance); 0: off. New cameras take the mean."""
    initial_density: Optional[float] = None
    """Density per scene unit the field starts from (the density MLP's bias); None: PyTorch's, about 0.37."""
    plane_kernel: Literal["torch", "warp"] = "torch"
    """Plane lookups: "torch" (grid_sample) or "warp" (one fused kernel, same values; the ``kernel`` extra)."""
    sam_head_dim: Optional[int] = 32
    """SAM embedding dimension per sample before the learned lift to sam_dim; None predicts sam_dim."""
    num_samples: int = 64
    """n, base samples per ray (Sec 4.4)."""
    split_base: int = 2
    """A base sample at gear p is split into split_base^(p-1) samples (Sec 4.4)."""
    base_sampler: Literal["uniform", "proposal"] = "uniform"
    """Base samples: stratified uniform between near and far (paper) or a proposal network (K-Planes)."""
    proposal: ProposalConfig = field(default_factory=ProposalConfig)
    """The proposal networks (base_sampler "proposal")."""
    background_color: Literal["random", "last_sample", "black", "white"] = "last_sample"
    """Background colour; 'last_sample': each ray's last sample's colour (as nerfacto, for captures without
    alpha)."""
    losses: LossWeights = field(default_factory=LossWeights)
    """The multiplier of each loss."""
    render: FullImageRenders = field(default_factory=FullImageRenders)
    """Full-image renders (viewer, ns-render, ns-eval, the gear updates' views, tracking)."""

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """Loads a run's config.yml, also one written before the groups above, whose options were flat
        (``FLAT_OPTIONS``); options the file lacks take their defaults."""
        defaults = vars(type(self)())
        for group, options in FLAT_OPTIONS.items():
            if group not in state:
                flat = {new: state.pop(old) for old, new in options.items() if old in state}
                state[group] = type(defaults[group])(**flat)
        self.__dict__.update({**defaults, **state})


FLAT_OPTIONS: Dict[str, Dict[str, str]] = {
    "proposal": {
        "num_proposal_samples": "num_samples", "proposal_resolutions": "resolutions",
        "proposal_feature_dim": "feature_dim", "proposal_time_resolution": "time_resolution",
        "proposal_warmup": "warmup", "proposal_update_every": "update_every",
        "use_proposal_weight_anneal": "weight_anneal", "proposal_weights_anneal_slope": "anneal_slope",
        "proposal_weights_anneal_max_num_iters": "anneal_iterations",
    },
    "losses": {
        "sam_loss_mult": "sam", "plane_tv_mult": "plane_tv", "l1_time_planes_mult": "l1_time_planes",
        "time_smoothness_mult": "time_smoothness", "plane_tv_proposal_mult": "plane_tv_proposal",
        "l1_time_planes_proposal_mult": "l1_time_planes_proposal",
        "time_smoothness_proposal_mult": "time_smoothness_proposal", "interlevel_loss_mult": "interlevel",
        "distortion_loss_mult": "distortion",
    },
    "render": {
        "render_outputs": "outputs", "render_num_samples": "num_samples",
        "render_num_proposal_samples": "num_proposal_samples", "render_chunk_samples": "chunk_samples",
        "min_views": "min_views",
    },
}  # fmt: skip
"""Each group's options in config files written before the groups (2026-12-07): flat name -> name in the group."""


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
        proposal = config.proposal
        if config.base_sampler == "proposal":
            time_resolution = proposal.time_resolution or max(1, self.num_frames // 2)
            for i in range(len(proposal.num_samples)):
                self.proposal_networks.append(
                    ProposalDensityField(
                        self.scene_box.aabb,
                        resolution=proposal.resolutions[min(i, len(proposal.resolutions) - 1)],
                        time_resolution=time_resolution,
                        feature_dim=proposal.feature_dim,
                        spatial_distortion=contraction,
                        plane_kernel=config.plane_kernel,
                    )
                )
        render = config.render
        self.sampler = GearSampler(
            SampleCounts(config.num_samples, proposal.num_samples),
            SampleCounts(
                render.num_samples or config.num_samples, render.num_proposal_samples or proposal.num_samples
            ),
            config.split_base,
            self.proposal_networks,
            proposal,
            unbounded,
        )

        near = metadata.get("near") if config.near_plane is None else config.near_plane
        far = metadata.get("far") if config.far_plane is None else config.far_plane
        if near is None or far is None:
            CONSOLE.log("[yellow]Gear-NeRF: no near/far in config or metadata; rays are clipped to the scene box.")
            self.collider = AABBBoxCollider(self.scene_box)
        else:
            self.collider = NearFarCollider(near_plane=float(near), far_plane=float(far), reset_near_plane=False)

        self.renderer = GearRenderer(config.background_color, config.num_gears)
        self.losses = GearLosses(
            config.losses,
            self.renderer.rgb,
            self.proposal_networks,
        )
        self.metrics = ImageMetrics(self.renderer.rgb)
        self.render_hooks: List[Callable[[Cameras, Dict[str, Tensor]], Dict[str, Tensor]]] = []
        """Extra outputs of full-image renders (``get_outputs_for_camera``), such as the viewer's tracked mask."""
        self.warned_no_time = False
        self.extra_outputs: Set[str] = set()
        """Outputs that full-image renders compute beside ``render.outputs`` (``rendering``)."""
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
        return self.sampler.training_callbacks()

    def get_outputs(self, ray_bundle: RayBundle, request: RenderRequest = RenderRequest()) -> Dict[str, Any]:
        """The one forward pass: base samples -> gear levels -> split samples (Sec 4.4) -> field (Eq 3-7) -> rgb,
        depth, accumulation and those of sam (Eq 8), gear_level, gear and num_samples that ``request`` names (all by
        default); in training also the K-Planes regularisers and the proposal sampler's weights and samples."""
        samples = self.sampler(ray_bundle, self.field.gear_levels)
        outputs, weights = self.renderer(self.field, ray_bundle, samples, request)
        if self.training and not request.sparse:
            # The K-Planes regularisers are computed here, in the forward pass, not in get_loss_dict: under DDP
            # (several GPUs) a plane that only the loss would use (a gear in use but absent from this process's
            # batch) is not reached from the forward's outputs, so DDP marks it unused, and the backward pass then
            # fails when its gradient arrives.
            outputs.update({f"regulariser_{name}": value for name, value in self.field.regularisers().items()})
        if samples.proposal_samples and not request.sparse:
            weights_list = [*samples.proposal_weights, samples.split.to_base(weights)]
            ray_samples_list = [*samples.proposal_samples, samples.base]
            if self.training:
                outputs["weights_list"] = weights_list
                outputs["ray_samples_list"] = ray_samples_list
            for i in range(len(ray_samples_list) - 1):
                outputs[f"prop_depth_{i}"] = self.renderer.depth(
                    weights=weights_list[i], ray_samples=ray_samples_list[i]
                )
        return outputs

    @contextlib.contextmanager
    def rendering(self, *names: str) -> Iterator[None]:
        """Full-image renders inside also compute the outputs ``names`` (beside the config's ``render.outputs``)."""
        before = self.extra_outputs
        self.extra_outputs = before | set(names)
        try:
            yield
        finally:
            self.extra_outputs = before

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """Full-image renders: sparse forward passes (``RenderRequest``) of the outputs asked for (the config's
        ``render.outputs`` and those of ``rendering``), chunk by chunk (``image_render.render_image``), with the
        render sample counts."""
        names = frozenset(self.config.render.outputs) | self.extra_outputs
        request = RenderRequest(names | {"num_samples"}, sparse=True)
        chunk_samples = self.config.render.chunk_samples or (1 << 15 if self.device.type == "cpu" else 1 << 21)
        with self.sampler.rendering() as num_samples:
            return render_image(
                lambda rays: self.get_outputs(self.collider(rays.to(self.device)), request),
                camera_ray_bundle,
                names,
                chunk_samples,
                num_samples,
            )

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
        SAM feature map (Eq 8) beside the config's ``render.outputs`` (the gear updates' loss maps use it)."""
        rays = camera.to(self.device).generate_rays(camera_indices=0, keep_shape=True)
        with evaluating(self), self.rendering("sam"):
            return self.get_outputs_for_camera_ray_bundle(rays)

    def see_from(self, cameras: Cameras, min_views: Optional[int] = None) -> None:
        """Renders in evaluation mode keep the density where at least ``min_views`` (default: the config's) of these
        training cameras see a point (`fields.seen_space.SeenSpace`); nothing changes when it is 0."""
        min_views = self.config.render.min_views if min_views is None else min_views
        seen = None
        if min_views > 0:
            seen = SeenSpace(cameras, min_views, self.field.aabb, self.field.spatial_distortion)
        for field in [self.field, *self.proposal_networks]:  # they share one seen_space
            field.seen_space = seen

    @contextlib.contextmanager
    def all_space(self) -> Iterator[None]:
        """Inside, renders take the density everywhere (``see_from`` is set aside), as training does: the gear
        updates render training views so."""
        fields, seen = [self.field, *self.proposal_networks], self.field.seen_space
        for field in fields:
            field.seen_space = None
        try:
            yield
        finally:
            for field in fields:
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
        image = self.renderer.rgb.blend_background(batch["image"].to(self.device))
        if self.training:
            self.training_depth.copy_(distributed.average(outputs["depth"].detach().median()))
        return {
            "psnr": psnr(outputs["rgb"].detach(), image),
            "samples_per_ray": outputs["num_samples"].mean(),
        }

    def get_loss_dict(
        self, outputs: Dict[str, Any], batch: Dict[str, Tensor], metrics_dict: Optional[Dict[str, Tensor]] = None
    ) -> Dict[str, Tensor]:
        """Eq 2 (rgb), Eq 9 (sam, when the batch has "sam_features") and the K-Planes regularisers
        (``losses.GearLosses``)."""
        return self.losses(outputs, batch, self.training)

    def image_metrics(self, rgb: Float[Tensor, "H W 3"], image: Float[Tensor, "H W C"]) -> Dict[str, float]:
        """PSNR, SSIM (and LPIPS when its weights are local) of a render against its image (``ImageMetrics``)."""
        return self.metrics(rgb, image, self.device)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """PSNR, SSIM (and LPIPS when its weights are local), accumulation and near layer on a full image; with
        ``eval_views``, the sums of ``moving_region.region_sums`` for that view; rgb, depth, gear images."""
        image = self.renderer.rgb.blend_background(batch["image"].to(self.device))
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
