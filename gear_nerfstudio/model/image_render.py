"""Full-image renders of a Gear-NeRF model (viewer, ns-render, ns-eval, gear updates, tracking): the image of
``GearNeRFModel.get_outputs`` (Eq 1, 8 over the split samples of Sec 4.4) with less work per pixel.

- Colour and SAM embedding are computed only for samples whose weight w_i (Eq 1) reaches ``VISIBLE_WEIGHT``, and
  for each ray's last sample: what lies behind an opaque surface costs its density only.
- Only the outputs asked for are computed (``render_outputs`` of the model's config, plus ``extra``).
- The base sampler draws the model's render sample counts (``render_num_samples``, ``render_num_proposal_samples``)
  where they are set.
- Rays go in chunks of as many rays as ``render_chunk_samples`` field samples allow, judged by the samples per ray
  of the previous chunk; results are written into the image as they come. A chunk reads two counts on the host: the
  split sampler's and the number of visible samples.
"""

from __future__ import annotations

from typing import Collection, Dict, Tuple

import torch
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle

from gear_nerfstudio.fields.gear_field import sample_points
from gear_nerfstudio.fields.gear_function import gear_level
from gear_nerfstudio.fields.planes import broadcast_times, normalize_positions
from gear_nerfstudio.model.split_sampler import split_ray_samples

VISIBLE_WEIGHT = 1e-5
"""Smallest weight w_i of a sample whose colour and SAM embedding a render computes."""


def render_rays(model: torch.nn.Module, rays: RayBundle, names: Collection[str]) -> Tuple[Dict[str, Tensor], int]:
    """The outputs ``names`` of a flat bundle of rays of `model` (a ``GearNeRFModel``), and the number of field
    samples evaluated."""
    field = model.field
    rays = model.collider(rays)
    base, _, _ = model.sample_base(rays)
    levels = field.gear_levels(base.frustums.get_positions(), base.times)
    split = split_ray_samples(base, levels, model.config.split_base)
    samples = split.ray_samples

    positions = split.pack(samples.frustums.get_positions())
    x, inside = normalize_positions(positions, field.aabb, field.spatial_distortion)
    t = broadcast_times(None if samples.times is None else split.pack(samples.times), positions.shape[:-1], positions)
    # a sample at gear 1 was not split (split_base^0 = 1): it is its base sample and keeps its level p (Eq 5)
    sample_levels = split.pack(levels.gather(1, split.parent)[..., None])[:, 0]
    split_up = sample_levels > 1
    sample_levels[split_up] = gear_level(field.gear_function(x[split_up], t[split_up]), field.num_gears)
    density, embedding = field.normalised_density(x, t, inside, sample_levels)
    weights = samples.get_weights(torch.where(split.valid[..., None], split.unpack(density), 0.0))
    geometry, features, sample_levels = field.split_embedding(embedding)

    visible = split.pack(weights)[:, 0] >= VISIBLE_WEIGHT
    visible[split.num_samples_per_ray.cumsum(0) - 1] = True
    index = visible.nonzero()[:, 0]
    codes = None if field.appearance is None else field.appearance(rays.metadata, len(rays))[split.ray_index[index]]
    directions = split.pack(samples.frustums.directions)[index]
    colours = field.colour(sample_points(positions[index], None, directions, codes), geometry[index])
    rgb = colours.new_zeros((len(positions), 3)).index_copy(0, index, colours)

    accumulation = model.renderer_accumulation(weights=weights)
    outputs = {
        "rgb": model.renderer_rgb(rgb=split.unpack(rgb), weights=weights),
        "accumulation": accumulation,
        "depth": model.renderer_depth(weights=weights, ray_samples=samples),
    }
    if "sam" in names:
        embeddings = field.sam_net(features[index])
        embeddings = embeddings.new_zeros((len(positions), embeddings.shape[-1])).index_copy(0, index, embeddings)
        outputs["sam"] = field.lift_sam(model.renderer_sam(split, weights, embeddings), accumulation)
    if "gear_level" in names or "gear" in names:
        outputs["gear_level"] = model.renderer_gear_level(split, weights, sample_levels)
        outputs["gear"] = model.gear_image(outputs["gear_level"])
    if "num_samples" in names:
        outputs["num_samples"] = split.num_samples_per_ray[:, None].to(weights.dtype)
    return {name: value for name, value in outputs.items() if name in names}, len(positions)


@torch.no_grad()
def render_image(model: torch.nn.Module, bundle: RayBundle, extra: Collection[str] = ()) -> Dict[str, Tensor]:
    """``render_rays`` over a bundle of any shape, chunk by chunk; outputs of shape (*bundle, C) on the
    bundle's device."""
    names = set(model.config.render_outputs) | set(extra)
    rays = bundle.flatten()
    chunk_samples = model.config.render_chunk_samples or (1 << 15 if model.device.type == "cpu" else 1 << 21)
    images: Dict[str, Tensor] = {}
    start = 0
    with model.render_sampling() as num_samples:
        per_ray = float(num_samples)
        while start < len(rays):
            count = max(1, int(chunk_samples / max(per_ray, num_samples / 4)))
            chunk = rays[start : start + count].to(model.device)
            outputs, evaluated = render_rays(model, chunk, names)
            per_ray = evaluated / len(chunk)
            for name, value in outputs.items():
                if name not in images:
                    images[name] = value.new_empty((len(rays), value.shape[-1]), device=bundle.origins.device)
                images[name][start : start + len(chunk)] = value
            start += len(chunk)
    return {name: image.view(*bundle.shape, -1) for name, image in images.items()}
