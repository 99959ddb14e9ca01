"""Rendering of split samples (Sec 4.4) through the gear field: colour (Eq 1), depth, accumulation, the SAM feature
map (Eq 8), the gear level and the samples of each ray."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, FrozenSet, Optional, Tuple

import matplotlib
import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.model_components.renderers import AccumulationRenderer, DepthRenderer, RGBRenderer

from gear_nerfstudio.fields.gear_field import GearField, sample_points
from gear_nerfstudio.fields.gear_function import gear_level
from gear_nerfstudio.fields.planes import broadcast_times, normalize_positions
from gear_nerfstudio.model.renderers import GearLevelRenderer, SamRenderer
from gear_nerfstudio.model.sampling import GearSamples
from gear_nerfstudio.model.split_sampler import SplitRaySamples

OUTPUTS = frozenset({"rgb", "depth", "accumulation", "sam", "gear_level", "gear", "num_samples"})
"""Every output of a render."""
VISIBLE_WEIGHT = 1e-5
"""Smallest weight w_i of a sample whose colour and SAM embedding a sparse render computes."""


@dataclass
class FullImageRenders:
    """Settings of full-image renders (viewer, ns-render, ns-eval, the gear updates' views, tracking)."""

    outputs: Tuple[str, ...] = ("rgb", "depth", "accumulation", "gear")
    """Outputs computed; add "sam", "gear_level" or "num_samples" (the SAM map costs an MLP per sample)."""
    num_samples: Optional[int] = None
    """n, base samples per ray; None: the model's num_samples. Fewer is faster, at a small change of the image."""
    num_proposal_samples: Optional[Tuple[int, ...]] = None
    """Samples of each proposal iteration; None: the proposal networks' num_samples."""
    chunk_samples: Optional[int] = None
    """Field samples evaluated at once (the memory bound); None: 2^15 on the CPU, 2^21 on a GPU."""
    min_views: int = 0
    """Keep the density only where at least this many training cameras (all of a smaller rig's) see a point; 0:
    all space, as training. Evaluation renders only."""


@dataclass(frozen=True)
class RenderRequest:
    """What a render computes: the outputs ``names``, and whether it is sparse (full-image renders): colour and SAM
    embedding only for samples whose weight w_i (Eq 1) reaches ``VISIBLE_WEIGHT`` and each ray's last sample (what
    lies behind an opaque surface costs its density only), the gear level p of a sample that was not split taken
    from its base sample instead of Eq 5 again."""

    names: FrozenSet[str] = field(default=OUTPUTS)
    sparse: bool = False


class GearRenderer(nn.Module):
    """The outputs of a batch of rays from their split samples and the field.

    Args:
        background_color: colour behind the scene (nerfstudio's RGBRenderer).
        num_gears: N_gear, the range of the "gear" image's colour map.
    """

    def __init__(self, background_color: str, num_gears: int) -> None:
        super().__init__()
        self.num_gears = num_gears
        self.rgb = RGBRenderer(background_color=background_color)
        self.accumulation = AccumulationRenderer()
        self.depth = DepthRenderer(method="median")
        self.sam = SamRenderer()
        self.gear_level = GearLevelRenderer()
        # the "gear" image's turbo colour map (as nerfstudio's apply_colormap, whose range asserts and per-call
        # table upload each cost a host sync every training step)
        self.register_buffer("gear_colors", torch.tensor(matplotlib.colormaps["turbo"].colors), persistent=False)

    def forward(
        self, field: GearField, rays: RayBundle, samples: GearSamples, request: RenderRequest
    ) -> Tuple[Dict[str, Tensor], Float[Tensor, "rays max_samples 1"]]:
        """The outputs of ``rays`` (Eq 1, Eq 8): rgb, depth, accumulation and those of ``request.names`` among sam,
        gear_level, gear and num_samples; and the weights w_i of the split samples."""
        split, names = samples.split, request.names
        ray_samples = split.ray_samples
        positions = split.pack(ray_samples.frustums.get_positions())
        x, inside = normalize_positions(positions, field.aabb, field.spatial_distortion)
        times = None if ray_samples.times is None else split.pack(ray_samples.times)
        t = broadcast_times(times, positions.shape[:-1], positions)
        levels = None
        if request.sparse:
            # a sample at gear 1 was not split (split_base^0 = 1): it is its base sample and keeps its level p (Eq 5)
            levels = split.pack(samples.levels.gather(1, split.parent)[..., None])[:, 0]
            split_up = levels > 1
            levels[split_up] = gear_level(field.gear_function(x[split_up], t[split_up]), field.num_gears)
        density, embedding = field.normalised_density(x, t, inside, levels)
        geometry, features, levels = field.split_embedding(embedding)
        # A sparse render needs the weights to choose its samples. Otherwise they come after the per-sample heads, as
        # the field's outputs came before them: backward sums gradients in the order of the forward pass, so training
        # stays the same to the last bit.
        weights = self.weights(split, density) if request.sparse else None
        index = None if weights is None else self.visible(split, weights)
        rays_of = split.ray_index if index is None else split.ray_index[index]
        codes = None if field.appearance is None else field.appearance(rays.metadata, len(rays))[rays_of]
        directions = split.pack(ray_samples.frustums.directions)
        points = sample_points(picked(positions, index), None, picked(directions, index), codes)
        colours = field.colour(points, picked(geometry, index))
        embeddings = field.sam_net(picked(features, index)) if "sam" in names else None
        if weights is None:
            weights = self.weights(split, density)

        outputs = {"rgb": self.rgb(rgb=split.unpack(scattered(colours, index, len(positions))), weights=weights)}
        outputs["accumulation"] = self.accumulation(weights=weights)
        outputs["depth"] = self.depth(weights=weights, ray_samples=ray_samples)
        if embeddings is not None:
            rendered = self.sam(split, weights, scattered(embeddings, index, len(positions)))
            outputs["sam"] = field.lift_sam(rendered, outputs["accumulation"])
        if "gear_level" in names or "gear" in names:
            outputs["gear_level"] = self.gear_level(split, weights, levels)
            outputs["gear"] = self.gear_image(outputs["gear_level"])
        if "num_samples" in names:
            outputs["num_samples"] = split.num_samples_per_ray[:, None].to(weights.dtype)
        return outputs, weights

    @staticmethod
    def weights(split: SplitRaySamples, density: Float[Tensor, "packed 1"]) -> Float[Tensor, "rays max_samples 1"]:
        """Eq 1's weights w_i of the split samples from their density (0 for the padding)."""
        return split.ray_samples.get_weights(torch.where(split.valid[..., None], split.unpack(density), 0.0))

    @staticmethod
    def visible(split: SplitRaySamples, weights: Float[Tensor, "rays max_samples 1"]) -> Int[Tensor, "visible"]:
        """Packed indices of the samples whose weight reaches ``VISIBLE_WEIGHT``, and of each ray's last sample."""
        visible = split.pack(weights)[:, 0] >= VISIBLE_WEIGHT
        visible[split.num_samples_per_ray.cumsum(0) - 1] = True
        return visible.nonzero()[:, 0]

    def gear_image(self, gear_level: Float[Tensor, "*bs 1"]) -> Float[Tensor, "*bs 3"]:
        """The "gear" output: the rendered gear level on the turbo colour map, gear 1 to N_gear."""
        fraction = ((gear_level.detach() - 1.0) / max(self.num_gears - 1, 1)).clamp(0.0, 1.0)
        return self.gear_colors[(fraction.nan_to_num(0.0) * 255).long()[..., 0]]


def picked(values: Tensor, index: Optional[Tensor]) -> Tensor:
    """The rows ``index`` of ``values``; all of them when ``index`` is None."""
    return values if index is None else values[index]


def scattered(values: Tensor, index: Optional[Tensor], count: int) -> Tensor:
    """``count`` rows holding ``values`` at the rows ``index`` and zeros elsewhere; ``values`` when index is None."""
    if index is None:
        return values
    return values.new_zeros((count, values.shape[-1])).index_copy(0, index, values)
