"""Which training cameras see a held-out view's near layer, and where they put their surface along it.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/near_layer_sightlines.py <run>/config.yml

The layer's points are the held-out camera's pixels at its first frame in a near layer (``near_layer_pixels``: depth
below a quarter of the training rays' median depth), lifted to 3D (up to ``POINTS``). Each is projected into every
training camera at the same time, and that camera's rendered depth at the projection is compared with its distance
to the point (scene units):

- "sees it": the training camera's surface lies within ``SURFACE`` of the point (the layer is a surface that camera
  sees: to it, the layer costs nothing);
- "stops before": its surface lies nearer (the point is hidden from it);
- "looks through": its surface lies beyond (its rays cross the point without stopping there);
- "outside": the point is outside its image or behind it.

A diagnosis of a trained run, not a fix; it does not change the model.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.model.gear_model import near_layer_pixels
from gear_nerfstudio.model.image_render import render_image
from gear_nerfstudio.tracking.projection import project

POINTS = 400
"""Layer points sampled (fixed seed)."""
SURFACE = 0.05
"""Scene units within which a training camera's rendered depth counts as the point's own surface."""


@torch.no_grad()
def main(config: Path) -> None:
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model = pipeline.model
    train, held = pipeline.datamanager.train_dataset.cameras, pipeline.datamanager.eval_dataset.cameras
    rays = held[0:1].generate_rays(camera_indices=0)
    depth = render_image(model, rays, set())["depth"]
    layer, depth = near_layer_pixels(depth, model.training_depth)[..., 0], depth[..., 0]
    if not layer.any():
        print("the held-out view's first frame has no near layer")
        return
    print(
        f"held-out view, first frame: near layer {float(layer.float().mean()):.3f} of the view at median depth "
        f"{float(depth[layer].median()):.3f}; training rays' median depth {float(model.training_depth):.3f}"
    )
    rows, cols = layer.nonzero(as_tuple=True)
    pick = torch.randperm(len(rows), generator=torch.Generator().manual_seed(0))[:POINTS]
    rows, cols = rows[pick], cols[pick]
    points = rays.origins[rows, cols] + rays.directions[rows, cols] * depth[rows, cols, None]

    counts = {"sees it": 0, "stops before": 0, "looks through": 0, "outside": 0}
    times = train.times[:, 0] if train.times is not None else torch.zeros(len(train))
    first = held.times[0, 0] if held.times is not None else times.min()
    same_time = ((times - first).abs() < 1e-6).nonzero()[:, 0]
    pixels, in_front = project(train[same_time], points)  # (C, N, 2) = (x, y)
    for i, uv, front in zip(same_time.tolist(), pixels, in_front):
        x, y = uv[:, 0], uv[:, 1]
        inside = front & (x >= 0) & (x < int(train.width[i])) & (y >= 0) & (y < int(train.height[i]))
        counts["outside"] += int((~inside).sum())
        if not inside.any():
            continue
        coords = torch.stack([y[inside], x[inside]], -1)[:, None, :]
        seen = render_image(model, train[i : i + 1].generate_rays(camera_indices=0, coords=coords), set())["depth"]
        distance = torch.linalg.norm(points[inside] - train.camera_to_worlds[i, :3, 3], dim=-1)
        beyond = seen.reshape(-1) - distance
        counts["sees it"] += int((beyond.abs() <= SURFACE).sum())
        counts["stops before"] += int((beyond < -SURFACE).sum())
        counts["looks through"] += int((beyond > SURFACE).sum())
        print(
            f"training image {i:4d}: {int(inside.sum()):3d} layer points in view, median distance "
            f"{float(distance.median()):.3f}; its surface lies {float(beyond.median()):+.3f} beyond them (median)"
        )
    print(f"layer points x training cameras at that time: {counts}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
