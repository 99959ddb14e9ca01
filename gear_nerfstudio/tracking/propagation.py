"""Propagation of free-viewpoint tracking (Gear-NeRF Sec 4.5): masks in a target view at the clicked time and,
frame by frame, at other times.

The target view's SAM feature map is rendered from the 4D embedding (Eq 8) and decoded with the projected click
(`click.project_prompt`) as the prompt. Masks for novel time steps: the bounding box of the mask at time t
prompts the decoder on the rendered features at the neighbouring frame t + 1 (or t - 1), frame by frame.

Propagation "embedding" (ours, the default) checks each box result with the 4D embedding: the object's
feature is the mean rendered SAM feature under the clicked-time mask. When the mask that the box gives at
t + 1 has a mean feature closer to the background's than to the object's, the object has left the box;
it is then looked up in the rendered features at t + 1 (`locate_object`: a point inside the cells closer
to the object's feature than to the rest of the image), and that point prompts as a positive point with
the box moved onto it. A box alone loses an object that moves further than its own size between frames;
the paper's box-only propagation remains as "box".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import torch
from scipy import ndimage
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from gear_nerfstudio.model.gear_model import evaluating
from gear_nerfstudio.sam.interface import Embedding, SamBackend, cell_centres, valid_grid
from gear_nerfstudio.tracking.click import TrackingError, check_time, image_size, single_camera

if TYPE_CHECKING:
    from nerfstudio.models.base_model import Model

Propagation = Literal["embedding", "box"]
"""How a mask at t prompts t +- 1: its box, re-found by the object's embedding when lost (ours), or its box."""


@dataclass
class TrackedMask:
    """The mask of one target view at one time, with the prompt that produced it (Sec 4.5)."""

    time: float
    mask: np.ndarray  # (H, W) bool
    prompt: Dict = field(default_factory=dict)  # {"points", "labels"} (click), {"box", "from_time"} (+ points, labels)


def _render(model: "Model", camera: Cameras, time: float, pixels: Tensor) -> Dict[str, Tensor]:
    """Model outputs for rays through pixel coordinates (..., 2) = (x, y) of a camera at a time."""
    camera = single_camera(camera, time).to(model.device)
    rays = camera.generate_rays(camera_indices=0, coords=pixels[..., [1, 0]].to(model.device))
    with evaluating(model):
        return model.get_outputs_for_camera_ray_bundle(rays)


def render_embedding(model: "Model", camera: Cameras, time: float, backend: SamBackend) -> Embedding:
    """SAM features rendered by the model (Eq 8) at the centres of the backend's grid cells that cover
    the image, zero on the padding cells: an Embedding that the backend's decoder accepts."""
    time = check_time(time)
    sam_dim = getattr(getattr(model, "config", None), "sam_dim", backend.embedding_dim)
    if sam_dim != backend.embedding_dim:
        raise TrackingError(
            f"the model renders {sam_dim}-dimensional SAM features but the {backend.name!r} SAM backend "
            f"decodes {backend.embedding_dim}-dimensional ones"
        )
    size = image_size(camera)
    centres = cell_centres(size, backend.grid_size)  # (rows, cols, 2)
    rendered = _render(model, camera, time, centres)["sam"]  # (rows, cols, C)
    rows, cols = centres.shape[:2]
    features = np.zeros((backend.embedding_dim, backend.grid_size, backend.grid_size), dtype=np.float32)
    features[:, :rows, :cols] = rendered.detach().cpu().float().permute(2, 0, 1).numpy()
    return Embedding(features=features, image_size=size)


def render_rgb(model: "Model", camera: Cameras, time: float) -> np.ndarray:
    """The model's colour image (H, W, 3) uint8 of a camera at a time (for overlays)."""
    height, width = image_size(camera)
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    rgb = _render(model, camera, check_time(time), torch.stack([xs, ys], dim=-1))["rgb"]
    return (rgb.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def segment(
    backend: SamBackend,
    embedding: Embedding,
    points: np.ndarray,
    labels: np.ndarray,
    box: Optional[np.ndarray] = None,
) -> np.ndarray:
    """The decoder's best mask (H, W) bool for point prompts (x, y) with labels (1 positive, 0
    negative) and/or a box (x0, y0, x1, y1); points may be empty when a box is given."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    if len(points) == 0:
        points, labels = None, None
    masks, _ = backend.decode(embedding, points=points, labels=labels, box=box)
    return np.asarray(masks[0], dtype=bool)


def mask_box(mask: np.ndarray) -> Optional[np.ndarray]:
    """Bounding box (x0, y0, x1, y1) in pixel coordinates of a mask's pixels (edges, so x1 = last
    column + 1); None for an empty mask."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=np.float64)


def frame_times(num_frames: int) -> List[float]:
    """Times of the frames of the model's window: index / (T - 1), 0 for T = 1."""
    return [index / max(num_frames - 1, 1) for index in range(max(num_frames, 1))]


def propagation_chains(click_time: float, times: Sequence[float], num_frames: int) -> Tuple[List[float], List[float]]:
    """Times visited after and before the clicked time, nearest first: every frame between the click
    and the furthest requested time, plus the requested times themselves (Sec 4.5 steps one frame
    at a time)."""
    later = [t for t in times if t > click_time]
    earlier = [t for t in times if t < click_time]
    frames = frame_times(num_frames)
    forward = sorted({*later, *(f for f in frames if later and click_time < f < max(later))})
    backward = sorted({*earlier, *(f for f in frames if earlier and min(earlier) < f < click_time)}, reverse=True)
    return forward, backward


def mask_cells(mask: np.ndarray, grid_size: int) -> np.ndarray:
    """Valid embedding cells (rows, cols) whose centre pixel lies inside a mask (H, W)."""
    centres = cell_centres(mask.shape, grid_size).numpy()
    rows = np.clip(centres[..., 1].astype(int), 0, mask.shape[0] - 1)
    cols = np.clip(centres[..., 0].astype(int), 0, mask.shape[1] - 1)
    return mask[rows, cols]


def valid_cell_features(embedding: Embedding) -> np.ndarray:
    """Features (rows * cols, C) of the cells that cover the image, row-major (as `cell_centres`)."""
    rows, cols = valid_grid(embedding.image_size, embedding.grid_size)
    return embedding.features[:, :rows, :cols].reshape(embedding.features.shape[0], -1).T


def object_features(embedding: Embedding, mask: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Mean feature (C,) of the cells under a mask and of the other valid cells; None when either is empty."""
    features = valid_cell_features(embedding)
    inside = mask_cells(mask, embedding.grid_size).reshape(-1)
    if inside.all() or not inside.any():
        return None
    return features[inside].mean(axis=0), features[~inside].mean(axis=0)


def holds_object(embedding: Embedding, mask: np.ndarray, features: Tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether a mask's mean feature is closer to the object's feature than to the background's."""
    inside = object_features(embedding, mask)
    if inside is None:
        return False
    obj, background = features
    return float(np.square(inside[0] - obj).sum()) < float(np.square(inside[0] - background).sum())


def locate_object(embedding: Embedding, features: Tuple[np.ndarray, np.ndarray]) -> Optional[Tuple[float, float]]:
    """Pixel (x, y) inside the object at another time, from its feature: among the cells closer to the
    object's feature than to the background's, take the 8-connected region holding the closest cell and
    return its innermost cell's centre (furthest from the region's border). None when no cell is closer.
    """
    obj, background = features
    rows, cols = valid_grid(embedding.image_size, embedding.grid_size)
    cells = valid_cell_features(embedding)
    to_object = np.square(cells - obj).sum(axis=1)
    candidates = (to_object < np.square(cells - background).sum(axis=1)).reshape(rows, cols)
    if not candidates.any():
        return None
    closest = np.unravel_index(int(np.argmin(np.where(candidates.reshape(-1), to_object, np.inf))), (rows, cols))
    regions, _ = ndimage.label(candidates, structure=np.ones((3, 3)))
    region = regions == regions[closest]
    depth = ndimage.distance_transform_edt(np.pad(region, 1))[1:-1, 1:-1]
    innermost = int(np.argmax(depth))
    x, y = cell_centres(embedding.image_size, embedding.grid_size).reshape(-1, 2)[innermost].tolist()
    return x, y


def centred_box(box: np.ndarray, centre: Tuple[float, float], image_size: Tuple[int, int]) -> np.ndarray:
    """The box (x0, y0, x1, y1) if it holds `centre` = (x, y); else moved to be centred on it, then shifted
    back inside the image."""
    if box[0] <= centre[0] < box[2] and box[1] <= centre[1] < box[3]:
        return np.asarray(box, dtype=np.float64)
    width, height = box[2] - box[0], box[3] - box[1]
    x0 = float(np.clip(centre[0] - width / 2, 0.0, max(image_size[1] - width, 0.0)))
    y0 = float(np.clip(centre[1] - height / 2, 0.0, max(image_size[0] - height, 0.0)))
    return np.array([x0, y0, x0 + width, y0 + height], dtype=np.float64)


def track(
    backend: SamBackend,
    embedding_at: Callable[[float], Embedding],
    pixels: np.ndarray,
    labels: np.ndarray,
    click_time: float,
    times: Sequence[float],
    num_frames: int,
    propagation: Propagation = "embedding",
) -> List[TrackedMask]:
    """Sec 4.5 on any source of embeddings: masks at the clicked time and at `times`, sorted by time.

    `pixels` (N, 2) with `labels` prompt the decoder on ``embedding_at(click_time)``; then each mask
    prompts the next frame outwards (see the module docstring for the two propagations). A lost, empty
    mask hands on the last box.
    """
    if propagation not in ("embedding", "box"):
        raise TrackingError(f"unknown propagation {propagation!r}: choose 'embedding' or 'box'")
    click_time = check_time(click_time, "click time")
    times = [check_time(t) for t in times]
    clicked = embedding_at(click_time)
    first = segment(backend, clicked, pixels, labels)
    prompt = {"points": np.asarray(pixels).tolist(), "labels": np.asarray(labels).astype(int).tolist()}
    visited = {click_time: TrackedMask(click_time, first, prompt)}
    features = object_features(clicked, first) if propagation == "embedding" else None
    for chain in propagation_chains(click_time, times, num_frames):
        box, box_time = mask_box(first), click_time
        for time in chain:
            prompt = {"box": None if box is None else box.tolist(), "from_time": box_time}
            mask = np.zeros_like(first)
            if box is not None:
                embedding = embedding_at(time)
                mask = segment(backend, embedding, np.zeros((0, 2)), [], box)
                found = None
                if features is not None and not holds_object(embedding, mask, features):
                    found = locate_object(embedding, features)
                if found is not None:
                    prompt.update(box=centred_box(box, found, first.shape).tolist(), points=[list(found)], labels=[1])
                    mask = segment(backend, embedding, np.array([found]), [1], np.array(prompt["box"]))
            visited[time] = TrackedMask(time, mask, prompt)
            if mask.any():
                box, box_time = mask_box(mask), time
    wanted = {click_time, *times}
    return [visited[t] for t in sorted(visited) if t in wanted]


def track_view(
    model: "Model",
    backend: SamBackend,
    camera: Cameras,
    pixels: np.ndarray,
    labels: np.ndarray,
    click_time: float,
    times: Sequence[float],
    num_frames: int,
    propagation: Propagation = "embedding",
) -> List[TrackedMask]:
    """`track` on the SAM features the model renders for one target view (each time rendered once)."""
    rendered: Dict[float, Embedding] = {}

    def embedding_at(time: float) -> Embedding:
        if time not in rendered:
            rendered[time] = render_embedding(model, camera, time, backend)
        return rendered[time]

    return track(backend, embedding_at, pixels, labels, click_time, times, num_frames, propagation)
