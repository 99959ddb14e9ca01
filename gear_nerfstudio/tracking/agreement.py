"""Multi-view agreement at the clicked time (issue 26; after SA3D's cross-view check): the object's mask in a target
view, lifted with the rendered depth to 3D points, is compared with the object's masks in the training views at the
same time. Where most of the views that see a point put it inside the object, the point belongs to the object, so
its cell joins the target view's mask before the mask propagates (Sec 4.5).

Only cells are added: the decoder on one view often leaves out a part of an object that differs in colour and lies
near the depth of what is behind it (a person's dark trousers two cells wide above the floor), which the other
views show; a view's own mask of the object is more often right about what it took in. And only cells that join
the mask are added (`agreed_mask`). Tracking a person into a held-out camera (3 seeds, both people;
benchmarks/results/tracking_real.md), mIoU / t-mIoU without / with the agreement: `panoptic` 70.3 / 62.7 -> 74.4 /
62.4 (`ns-gear-track`'s default `--min-views` 2; over all space 61.8 / 56.4 -> 66.3 / 59.1), the 31 cameras 75.1 /
65.0 -> 77.6 / 66.6. In scratch runs, letting the views also remove cells gave 63.9 at the clicked time on
`panoptic` (all space) where adding only gave 66.7.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, Iterable, List

import numpy as np
import torch
from scipy import ndimage
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.projection import project
from gear_nerfstudio.sam.interface import Embedding, SamBackend, cell_centres, pixel_cells
from gear_nerfstudio.tracking.click import TrackingError, project_prompt, single_camera
from gear_nerfstudio.tracking.propagation import mask_cells, render_embedding, segment

if TYPE_CHECKING:
    from nerfstudio.models.base_model import Model

AGREEING_SHARE = 0.5
"""Share of the views that see a point and must put it inside the object for its cell to join the mask."""
MIN_VIEWS = 4
"""Views that must see a point before the agreement decides about it."""
OCCLUSION_MARGIN = 0.1
"""A point is seen by a view when it is no further from the view than the view's rendered depth there, plus this
share of it."""


@dataclass
class ObjectView:
    """The object in one training view at the clicked time: the view, the depth rendered at its SAM grid's cells
    (`Embedding.depth`) and the decoder's mask of the object there (the features are not kept)."""

    camera: Cameras
    depth: np.ndarray
    mask: np.ndarray


def object_views(
    model: "Model",
    backend: SamBackend,
    views: Dict[str, Cameras],
    points: Iterable[Tensor],
    labels: np.ndarray,
    time: float,
) -> Dict[str, ObjectView]:
    """The object in each of the named `views` at `time`: the clicks' 3D `points` with their `labels` prompt the
    decoder on the view's rendered SAM features. A view into which a click does not project is left out. Made once
    for all the target views of a click."""
    points = [torch.as_tensor(point, dtype=torch.float32) for point in points]
    found = {}
    for name, camera in views.items():
        camera = single_camera(camera)
        try:
            pixels = np.array([project_prompt(camera, point) for point in points])
        except (TrackingError, DatasetError):
            continue
        embedding = render_embedding(model, camera, time, backend)
        found[name] = ObjectView(camera, embedding.depth, segment(backend, embedding, pixels, labels))
    return found


def cell_points(camera: Cameras, embedding: Embedding) -> Tensor:
    """World points (rows, cols, 3) where the rays through the centres of an embedding's valid cells end at its
    rendered depth (nerfstudio's depth: the distance along the ray)."""
    centres = cell_centres(embedding.image_size, embedding.grid_size)
    rows, cols = centres.shape[:2]
    rays = single_camera(camera).generate_rays(camera_indices=0, coords=centres[..., [1, 0]].reshape(-1, 2))
    depth = torch.from_numpy(np.asarray(embedding.depth[:rows, :cols], dtype=np.float32)).reshape(-1, 1)
    return (rays.origins.cpu() + rays.directions.cpu() * depth).reshape(rows, cols, 3)


def agreed_mask(camera: Cameras, embedding: Embedding, mask: np.ndarray, views: List[ObjectView]) -> np.ndarray:
    """The mask (H, W) of the object in `camera`, from its rendered `embedding` (with depth), with the cells added
    whose 3D points lie inside the object's mask in at least AGREEING_SHARE of the `views` that see them (at least
    MIN_VIEWS) and that join the mask (8-connected, through such cells). An agreed cell apart from the mask (one
    cell at the image's edge, where the depth lifts it wrongly) would only widen the mask's box, which prompts the
    next frame: in `panoptic`'s held-out camera one such cell took the next frame's mask into the floor."""
    world = cell_points(camera, embedding)
    rows, cols = world.shape[:2]
    points = world.reshape(-1, 3)
    positions = points.numpy()
    votes, inside = np.zeros(rows * cols), np.zeros(rows * cols)
    for view in views:
        uv, in_front = project(view.camera, points)
        x, y = uv[0, :, 0].numpy(), uv[0, :, 1].numpy()
        height, width = view.mask.shape
        seen = in_front[0].numpy() & (x >= 0) & (x < width) & (y >= 0) & (y < height)
        cell_row, cell_col = pixel_cells(x, y, view.mask.shape, view.depth.shape[-1])
        distance = np.linalg.norm(positions - view.camera.camera_to_worlds[0, :, 3].cpu().numpy(), axis=1)
        seen &= distance <= view.depth[cell_row, cell_col] * (1.0 + OCCLUSION_MARGIN)
        pixel_row, pixel_col = np.clip(y.astype(np.int64), 0, height - 1), np.clip(x.astype(np.int64), 0, width - 1)
        votes += seen
        inside += seen & view.mask[pixel_row, pixel_col]
    agreed = ((votes >= MIN_VIEWS) & (inside >= AGREEING_SHARE * votes)).reshape(rows, cols)
    cells = mask_cells(mask, embedding.grid_size)
    pieces, _ = ndimage.label(agreed | cells, structure=np.ones((3, 3)))
    added = agreed & ~cells & np.isin(pieces, pieces[cells])
    height, width = embedding.image_size
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    return mask | added[pixel_cells(xs, ys, embedding.image_size, embedding.grid_size)]
