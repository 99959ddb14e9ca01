"""Propagation of free-viewpoint tracking (Gear-NeRF Sec 4.5): masks in a target view at the clicked time and,
frame by frame, at other times.

The target view's SAM feature map is rendered from the 4D embedding (Eq 8) and decoded with the projected click
(`click.project_prompt`) as the prompt. Masks for novel time steps: the bounding box of the mask at time t
prompts the decoder on the rendered features at the neighbouring frame t + 1 (or t - 1), frame by frame.

Propagation "embedding" (ours, the default) checks each box result with the 4D embedding. The object's
appearance is the set of rendered SAM features of the cells under the clicked-time mask, with the rendered
depth beside them (the depth cue, `interface.with_depth_cue`), against those of the rest of the view
(`ObjectAppearance`); at t + 1 the cells nearer to an object feature than to any
background feature form regions, and the region that overlaps the box's mask (else the best-matching one)
is the object (`object_region`). When the box's mask and that region disagree (IoU of their cells below
AGREEMENT), the decoder is prompted again with points spread over the region and the region's own box
(`region_prompt`). A box alone loses an object that moves further than its own size between frames, and
a box taken from a mask that covered only part of the object (one stripe of a striped ball) shrinks the
next mask to that part, frame after frame; the region's points and box re-prompt the whole object. The
paper's box-only propagation remains as "box".
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
from gear_nerfstudio.sam.interface import (
    Embedding,
    SamBackend,
    cell_centres,
    log_depth,
    valid_depth,
    valid_grid,
    with_depth_cue,
)
from gear_nerfstudio.tracking.metrics import iou
from gear_nerfstudio.tracking.click import TrackingError, check_time, image_size, single_camera

if TYPE_CHECKING:
    from nerfstudio.models.base_model import Model

Propagation = Literal["embedding", "box"]
"""How a mask at t prompts t +- 1: its box, checked and re-prompted by the object's embedding (ours), or its box."""
AGREEMENT = 0.5
"""IoU of cells between the box's mask and the object's region below which the region re-prompts."""
APPEARANCE_SAMPLES = 512
"""Cells of the object, and of the background, kept as `ObjectAppearance` (evenly spaced)."""
REGION_POINTS = 3
"""Positive points spread over the object's region when it re-prompts."""


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
    with evaluating(model), model.rendering("sam", "depth"):
        return model.get_outputs_for_camera_ray_bundle(rays)


def render_embedding(model: "Model", camera: Cameras, time: float, backend: SamBackend) -> Embedding:
    """SAM features rendered by the model (Eq 8) at the centres of the backend's grid cells that cover
    the image, zero on the padding cells: an Embedding that the backend's decoder accepts, with the depth
    rendered at the same cells (`Embedding.depth`, the decoder's depth cue)."""
    time = check_time(time)
    sam_dim = getattr(getattr(model, "config", None), "sam_dim", backend.embedding_dim)
    if sam_dim != backend.embedding_dim:
        raise TrackingError(
            f"the model renders {sam_dim}-dimensional SAM features but the {backend.name!r} SAM backend "
            f"decodes {backend.embedding_dim}-dimensional ones"
        )
    size = image_size(camera)
    centres = cell_centres(size, backend.grid_size)  # (rows, cols, 2)
    outputs = _render(model, camera, time, centres)
    rows, cols = centres.shape[:2]
    features = np.zeros((backend.embedding_dim, backend.grid_size, backend.grid_size), dtype=np.float32)
    features[:, :rows, :cols] = outputs["sam"].detach().cpu().float().permute(2, 0, 1).numpy()
    depth = np.zeros((backend.grid_size, backend.grid_size), dtype=np.float32)
    depth[:rows, :cols] = outputs["depth"][..., 0].detach().cpu().float().numpy()
    return Embedding(features=features, image_size=size, depth=depth)


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
    """Features (rows * cols, C) of the cells that cover the image, row-major (as `cell_centres`), with the
    embedding's depth cue beside them when it has one (`with_depth_cue`)."""
    rows, cols = valid_grid(embedding.image_size, embedding.grid_size)
    features = embedding.features[:, :rows, :cols].transpose(1, 2, 0).astype(np.float64)
    return with_depth_cue(features, log_depth(valid_depth(embedding))).reshape(rows * cols, -1)


def _sample(features: np.ndarray, count: int) -> np.ndarray:
    """At most `count` rows of `features`, evenly spaced (deterministic)."""
    if len(features) <= count:
        return features
    return features[np.linspace(0, len(features) - 1, count).astype(np.int64)]


@dataclass
class ObjectAppearance:
    """The object's rendered SAM features at the clicked time and those of the rest of the view (each at
    most APPEARANCE_SAMPLES cells): a cell at another time belongs to the object when its nearest object
    feature is nearer than its nearest background feature. Every part of an object (each stripe of a
    ball, a person's shirt and trousers) keeps its own features, which a mean would blur together."""

    object: np.ndarray  # (N, C)
    background: np.ndarray  # (M, C)

    @staticmethod
    def of(embedding: Embedding, mask: np.ndarray) -> Optional["ObjectAppearance"]:
        """From the clicked-time embedding and mask; None when the mask holds no cell or every cell."""
        features = valid_cell_features(embedding)
        inside = mask_cells(mask, embedding.grid_size).reshape(-1)
        if inside.all() or not inside.any():
            return None
        return ObjectAppearance(
            _sample(features[inside], APPEARANCE_SAMPLES), _sample(features[~inside], APPEARANCE_SAMPLES)
        )

    def cells(self, embedding: Embedding) -> Tuple[np.ndarray, np.ndarray]:
        """Object cells (rows, cols) bool of another embedding, and every cell's squared distance to its
        nearest object feature."""
        features = valid_cell_features(embedding)

        def nearest(reference: np.ndarray) -> np.ndarray:
            squared = (features**2).sum(1)[:, None] + (reference**2).sum(1)[None] - 2.0 * features @ reference.T
            return squared.min(axis=1)

        to_object = nearest(self.object)
        shape = valid_grid(embedding.image_size, embedding.grid_size)
        return (to_object < nearest(self.background)).reshape(shape), to_object.reshape(shape)


def object_region(cells: np.ndarray, distance: np.ndarray, near: np.ndarray) -> Optional[np.ndarray]:
    """The 8-connected region of object cells (rows, cols) that overlaps the cells `near` most (the box
    prompt's mask); when none does, the region holding the best-matching cell. None without object cells."""
    regions, count = ndimage.label(cells, structure=np.ones((3, 3)))
    if count == 0:
        return None
    overlap = np.bincount(regions[near], minlength=count + 1)
    overlap[0] = 0
    if overlap.max() > 0:
        return regions == int(np.argmax(overlap))
    return regions == regions.reshape(-1)[int(np.argmin(np.where(cells, distance, np.inf)))]


def region_points(region: np.ndarray, count: int = REGION_POINTS) -> np.ndarray:
    """Up to `count` cells (K, 2) = (row, col) spread over a region's inner part (cells at least half as
    deep inside as its deepest): the deepest cell first, then each cell furthest from those chosen."""
    depth = ndimage.distance_transform_edt(np.pad(region, 1))[1:-1, 1:-1]
    inner = np.argwhere(depth >= 0.5 * depth.max())
    chosen = [np.argwhere(depth == depth.max())[0]]
    while len(chosen) < min(count, len(inner)):
        spread = np.min([np.square(inner - cell).sum(axis=1) for cell in chosen], axis=0)
        if spread.max() == 0:
            break
        chosen.append(inner[int(np.argmax(spread))])
    return np.array(chosen)


def region_prompt(region: np.ndarray, embedding: Embedding) -> Tuple[np.ndarray, np.ndarray]:
    """Positive points (K, 2) = (x, y) at `region_points` and the box (x0, y0, x1, y1) of the region's cells
    in pixels."""
    centres = cell_centres(embedding.image_size, embedding.grid_size).numpy()
    cells = region_points(region)
    rows, cols = np.nonzero(region)
    size = max(embedding.image_size) / embedding.grid_size  # pixels per cell
    box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=np.float64) * size
    box = np.minimum(box, [embedding.image_size[1], embedding.image_size[0]] * 2)
    return centres[cells[:, 0], cells[:, 1]], box


def track(
    backend: SamBackend,
    embedding_at: Callable[[float], Embedding],
    pixels: np.ndarray,
    labels: np.ndarray,
    click_time: float,
    times: Sequence[float],
    num_frames: int,
    propagation: Propagation = "embedding",
    refine: Optional[Callable[[Embedding, np.ndarray], np.ndarray]] = None,
) -> List[TrackedMask]:
    """Sec 4.5 on any source of embeddings: masks at the clicked time and at `times`, sorted by time.

    `pixels` (N, 2) with `labels` prompt the decoder on ``embedding_at(click_time)``, and `refine` (the clicked
    time's embedding, the mask) -> mask, when given, refines that mask (`agreement.agreed_mask`); then each mask
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
    if refine is not None:
        refined = refine(clicked, first)
        prompt["refined_pixels"] = int(np.count_nonzero(refined != first))  # tracking.json says what it changed
        first = refined
    visited = {click_time: TrackedMask(click_time, first, prompt)}
    appearance = ObjectAppearance.of(clicked, first) if propagation == "embedding" else None
    for chain in propagation_chains(click_time, times, num_frames):
        box, box_time = mask_box(first), click_time
        for time in chain:
            prompt = {"box": None if box is None else box.tolist(), "from_time": box_time}
            mask = np.zeros_like(first)
            if box is not None:
                embedding = embedding_at(time)
                mask = segment(backend, embedding, np.zeros((0, 2)), [], box)
                if appearance is not None:
                    cells, distance = appearance.cells(embedding)
                    near = mask_cells(mask, embedding.grid_size)
                    region = object_region(cells, distance, near)
                    if region is not None and iou(near, region) < AGREEMENT:
                        points, region_box = region_prompt(region, embedding)
                        prompt.update(box=region_box.tolist(), points=points.tolist(), labels=[1] * len(points))
                        mask = segment(backend, embedding, points, np.ones(len(points)), region_box)
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
    refine: Optional[Callable[[Embedding, np.ndarray], np.ndarray]] = None,
) -> List[TrackedMask]:
    """`track` on the SAM features the model renders for one target view (each time rendered once)."""
    rendered: Dict[float, Embedding] = {}

    def embedding_at(time: float) -> Embedding:
        if time not in rendered:
            rendered[time] = render_embedding(model, camera, time, backend)
        return rendered[time]

    return track(backend, embedding_at, pixels, labels, click_time, times, num_frames, propagation, refine)
