"""Full-image renders (viewer, ns-render, ns-eval, gear updates, tracking) chunk by chunk: rays go in chunks of as
many rays as a bound on field samples allows, judged by the samples per ray of the previous chunk; results are
written into the image as they come."""

from __future__ import annotations

from typing import Callable, Collection, Dict

import torch
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle


@torch.no_grad()
def render_image(
    render_rays: Callable[[RayBundle], Dict[str, Tensor]],
    bundle: RayBundle,
    names: Collection[str],
    chunk_samples: int,
    num_samples: int,
) -> Dict[str, Tensor]:
    """The outputs ``names`` of ``render_rays`` (a forward pass of a flat bundle that includes "num_samples", the
    samples of each ray) over a bundle of any shape, in chunks of at most about ``chunk_samples`` field samples
    (``num_samples``: base samples per ray); outputs of shape (*bundle, C) on the bundle's device."""
    rays = bundle.flatten()
    images: Dict[str, Tensor] = {}
    start = 0
    per_ray = float(num_samples)
    while start < len(rays):
        count = max(1, int(chunk_samples / max(per_ray, num_samples / 4)))
        chunk = rays[start : start + count]
        outputs = render_rays(chunk)
        per_ray = float(outputs["num_samples"].sum()) / len(chunk)
        for name, value in outputs.items():
            if name not in names:
                continue
            if name not in images:
                images[name] = value.new_empty((len(rays), value.shape[-1]), device=bundle.origins.device)
            images[name][start : start + len(chunk)] = value
        start += len(chunk)
    return {name: image.view(*bundle.shape, -1) for name, image in images.items()}
