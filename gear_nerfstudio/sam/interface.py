"""The SAM interface every backend implements, and the embedding geometry they share.

SAM resizes an image so that its longest side is 1024 px, pads it to 1024 x 1024 at the bottom/right
and encodes it to a 256 x 64 x 64 embedding: cell (i, j) covers image pixels whose coordinates,
scaled by `grid_size / max(H, W)`, fall in [j, j+1) x [i, i+1). Every backend uses this geometry
(with its own grid size), so supervision (Eq 9), loss maps (Sec 4.3) and tracking (Sec 4.5) can move
between pixels and embedding cells without knowing the backend.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor


@dataclass
class Embedding:
    """An image embedding: features (C, G, G) over the padded square of an image of image_size (H, W).

    ``depth`` (G, G), optional: the radiance field's rendered depth at the centres of the cells that cover the
    image (see `valid_grid`; the rest is ignored). It is a cue that a decoder may use (the built-in stand-in
    does) or ignore (SAM does): embeddings rendered from the field carry it, encoded images do not.
    """

    features: np.ndarray
    image_size: Tuple[int, int]
    depth: Optional[np.ndarray] = None

    @property
    def grid_size(self) -> int:
        return int(self.features.shape[-1])


CUE_FEATURE_NORM = 0.75
"""Median norm that cell features are scaled to before the log depth goes beside them (`with_depth_cue`)."""

EMPTY_CELL_NORM = 1e-3
"""A cell whose feature norm is below this share of the largest carries no features (`median_norm`)."""


def median_norm(features: np.ndarray) -> float:
    """Median feature norm of the cells (rows, cols, C) that carry features; 0 when none does.

    Cells that carry none are left out: rays of a render that meet nothing (space that too few training cameras
    see, `GearNeRFModelConfig.render.min_views`) and black pixels of an image. A view that reaches past what the cameras
    saw, such as the viewer's wide one, can have more of them than not, and their zero median would scale
    everything else up a millionfold (the segmentation then split a clicked object into single cells).
    """
    norms = np.linalg.norm(features, axis=-1)
    carrying = norms[norms > EMPTY_CELL_NORM * norms.max()] if norms.size else norms
    return float(np.median(carrying)) if carrying.size else 0.0


def valid_depth(embedding: Embedding) -> Optional[np.ndarray]:
    """An embedding's depth cue on its valid cells (rows, cols); rays that meet nothing (an infinite or undefined
    depth) count as at the furthest depth of the map. None without a depth."""
    if embedding.depth is None:
        return None
    rows, cols = valid_grid(embedding.image_size, embedding.grid_size)
    depth = np.asarray(embedding.depth[:rows, :cols], dtype=np.float64)
    finite = np.isfinite(depth)
    return np.where(finite, depth, depth[finite].max() if finite.any() else 1.0)


def log_depth(depth: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """Log of a `valid_depth` map after a 3 x 3 median that removes the isolated stray depths of rays that slip
    through a surface and keeps depth edges in place. None without a depth."""
    if depth is None:
        return None
    return np.log(np.maximum(ndimage.median_filter(depth, size=3, mode="nearest"), 1e-6))


def with_depth_cue(features: np.ndarray, logs: Optional[np.ndarray]) -> np.ndarray:
    """Features (rows, cols, C) of an embedding's valid cells with its depth cue beside them: scaled to a
    `median_norm` of CUE_FEATURE_NORM, with the log depth (`log_depth`) as one more channel, so that a depth ratio
    of e (a person two units in front of a wall five units away is a ratio of 2.5) weighs as much as a typical
    feature. Unchanged without a depth."""
    if logs is None:
        return features
    scale = CUE_FEATURE_NORM / max(median_norm(features), 1e-12)
    return np.concatenate([features * scale, logs[..., None]], axis=-1)


def cells_per_pixel(image_size: Tuple[int, int], grid_size: int) -> float:
    """Scale from image pixel coordinates to embedding cell coordinates."""
    return grid_size / max(image_size)


def valid_grid(image_size: Tuple[int, int], grid_size: int) -> Tuple[int, int]:
    """Rows and columns of the grid that cover the image (the rest covers SAM's padding)."""
    scale = cells_per_pixel(image_size, grid_size)
    return min(grid_size, int(np.ceil(image_size[0] * scale))), min(grid_size, int(np.ceil(image_size[1] * scale)))


def pixel_cells(
    x: np.ndarray, y: np.ndarray, image_size: Tuple[int, int], grid_size: int
) -> Tuple[np.ndarray, np.ndarray]:
    """Row and column of the valid cell under each image point (x, y) in pixel coordinates, clipped to the valid
    grid."""
    rows, cols = valid_grid(image_size, grid_size)
    scale = cells_per_pixel(image_size, grid_size)
    return np.clip((y * scale).astype(np.int64), 0, rows - 1), np.clip((x * scale).astype(np.int64), 0, cols - 1)


def cell_centres(image_size: Tuple[int, int], grid_size: int) -> Tensor:
    """Image pixel coordinates (x, y) of the centres of the valid cells, shape (rows, cols, 2)."""
    rows, cols = valid_grid(image_size, grid_size)
    scale = cells_per_pixel(image_size, grid_size)
    ys, xs = torch.meshgrid(torch.arange(rows) + 0.5, torch.arange(cols) + 0.5, indexing="ij")
    return torch.stack([xs, ys], dim=-1) / scale


def sample_features(features: Tensor, pixels: Tensor, image_size: Tuple[int, int]) -> Tensor:
    """Bilinear features (N, C) at image pixel coordinates (N, 2) = (x, y) from a (C, G, G) grid."""
    grid_size = features.shape[-1]
    cells = pixels * cells_per_pixel(image_size, grid_size)
    normalised = cells / grid_size * 2.0 - 1.0  # align_corners=False: cell centres at (k + 0.5)
    sampled = torch.nn.functional.grid_sample(
        features[None].float(), normalised[None, None], mode="bilinear", padding_mode="border", align_corners=False
    )
    return sampled[0, :, 0].T


class SamBackend(ABC):
    """Encoder and prompt decoder of SAM or a stand-in.

    Attributes:
        name: backend name, written into the feature cache header.
        settings: everything that changes the encoder output (model files, sizes); a change
            invalidates cached features.
        embedding_dim: C of the embeddings.
        grid_size: G of the embeddings.
        parallel_encodes: how many images `SamFeatureCache.precompute` encodes at once: 1 (the default) for an
            encoder that already uses every core, more for one that runs on one core.
    """

    name: str
    embedding_dim: int
    grid_size: int
    parallel_encodes: int = 1

    @property
    @abstractmethod
    def settings(self) -> Dict[str, Any]:
        """Settings that determine the encoder's output."""

    @abstractmethod
    def encode(self, image: np.ndarray) -> Embedding:
        """Embed an RGB uint8 image (H, W, 3)."""

    @abstractmethod
    def decode(
        self,
        embedding: Embedding,
        points: Optional[np.ndarray] = None,
        labels: Optional[np.ndarray] = None,
        box: Optional[np.ndarray] = None,
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Masks for prompts on an embedding.

        Args:
            embedding: from `encode`, or rendered features arranged on the same grid.
            points: (N, 2) pixel coordinates (x, y) in the embedded image.
            labels: (N,) 1 for positive, 0 for negative points.
            box: (4,) x0, y0, x1, y1 in pixels.

        Returns:
            masks (K, H, W) bool at the embedded image's size, scores (K,), best first.
        """
