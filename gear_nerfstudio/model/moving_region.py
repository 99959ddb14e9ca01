"""What moves in an evaluation view, and the scores inside and outside it.

The held-out camera's moving region at each frame comes from masks of what moves where the dataset has them
(``<moving_masks>/<camera name>/<frame number:05d>.png``, non-zero = moving), else from the ground truth itself: the
pixels whose colour differs from the window's per-pixel median (``CHANGE_THRESHOLD``). Per view, ``region_sums``
adds up squared errors and gear levels (Eq 5) inside and outside the region; ``region_scores`` turns the sums,
averaged over views, into PSNR over the moving pixels and the rest, and the gear shares.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from PIL import Image
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datasets.base_dataset import InputDataset

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.spread import evenly_spread

CHANGE_THRESHOLD = 0.04
"""A pixel moves when the largest channel difference from the window's median, averaged over its 3 x 3
neighbourhood, exceeds this (colours in [0, 1]); measured against the person masks of the real capture
(docs/decisions.md)."""
DILATION = 2
"""Pixels added around the moving region (masks and change alike), as the benchmarks' person masks."""
MEDIAN_FRAMES = 31
"""Frames, evenly spread over the window, whose per-pixel median is the background of the change region."""
SUMS = ("moving_error", "moving_pixels", "moving_gear_2_pixels", "static_error", "static_pixels", "static_gear_1_pixels")
"""Per-view sums (``region_sums``), averaged over views before ``region_scores``."""


def mask_path(folder: Path, camera: str, number: int) -> Path:
    """Where a capture keeps a camera's mask of what moves at one frame: ``<folder>/<camera>/<number:05d>.png``."""
    return folder / camera / f"{number:05d}.png"


def _dilate(mask: Bool[Tensor, "H W"], radius: int) -> Bool[Tensor, "H W"]:
    return F.max_pool2d(mask[None, None].float(), 2 * radius + 1, stride=1, padding=radius)[0, 0] > 0


def _erode(mask: Bool[Tensor, "H W"], radius: int) -> Bool[Tensor, "H W"]:
    return ~_dilate(~mask, radius)


def changed_pixels(image: Float[Tensor, "H W 3"], background: Float[Tensor, "H W 3"]) -> Bool[Tensor, "H W"]:
    """Pixels whose colour differs from the background (``CHANGE_THRESHOLD``), opened by one pixel so that isolated
    noise drops out, then dilated by ``DILATION``."""
    difference = (image - background).abs().amax(dim=-1)
    smooth = F.avg_pool2d(difference[None, None], 3, stride=1, padding=1, count_include_pad=False)[0, 0]
    changed = smooth > CHANGE_THRESHOLD
    return _dilate(_erode(changed, 1), 1 + DILATION)  # opened, then dilated: square windows add up


class EvalViews:
    """The evaluation dataset's views (the held-out camera at each frame of the window): their cameras, names and
    moving regions."""

    def __init__(self, dataset: InputDataset, moving_masks: Optional[Path] = None) -> None:
        self.dataset = dataset
        self.moving_masks = moving_masks
        self._background: Optional[Tensor] = None
        metadata = dataset.metadata
        self.names = [str(metadata["camera_names"][int(c)]) for c in metadata["camera_ids"]]
        self.frame_numbers = [int(metadata["frame_numbers"][int(f)]) for f in metadata["frame_ids"]]

    def __len__(self) -> int:
        return len(self.dataset)

    def camera(self, index: int) -> Cameras:
        return self.dataset.cameras[index : index + 1]

    def label(self, index: int) -> str:
        """The view's camera name and frame number, as the dataset names them."""
        return f"{self.names[index]} frame {self.frame_numbers[index]}"

    def background(self) -> Float[Tensor, "H W 3"]:
        """Per-pixel median of up to ``MEDIAN_FRAMES`` views spread over the window."""
        if self._background is None:
            picks = evenly_spread(len(self.dataset), MEDIAN_FRAMES)
            stack = np.stack([self.dataset.get_numpy_image(i)[..., :3] for i in picks])
            self._background = torch.from_numpy(np.median(stack, axis=0).astype(np.float32) / 255.0)
        return self._background

    def moving(self, index: int, image: Float[Tensor, "H W 3"]) -> Optional[Bool[Tensor, "H W"]]:
        """The moving region of view ``index`` (its ground-truth ``image``); None for a window of one frame without
        masks, where nothing can be seen to move."""
        height, width = image.shape[:2]
        if self.moving_masks is not None:
            path = mask_path(self.moving_masks, self.names[index], self.frame_numbers[index])
            try:
                mask = Image.open(path).convert("L").resize((width, height), Image.Resampling.NEAREST)
            except OSError as err:
                raise DatasetError(f"{path}: not a readable mask image ({err})") from err
            region = torch.from_numpy(np.array(mask) > 0)
            return _dilate(region, DILATION).to(image.device)
        if len(self.dataset) < 2:
            return None
        return changed_pixels(image[..., :3], self.background().to(image.device))


def region_sums(
    rgb: Float[Tensor, "H W 3"],
    image: Float[Tensor, "H W 3"],
    moving: Optional[Bool[Tensor, "H W"]],
    levels: Int[Tensor, "H W"],
) -> Dict[str, float]:
    """Squared error (mean over channels) and pixel counts inside and outside the moving region, with the moving
    pixels at gear >= 2 and the others at gear 1 (``levels``: Eq 5 at each pixel's surface)."""
    if moving is None:
        moving = torch.zeros(levels.shape, dtype=torch.bool, device=levels.device)
    error = ((rgb - image) ** 2).mean(dim=-1)
    moving = moving.to(error.device)
    levels = levels.to(error.device)
    return {
        "moving_error": float(error[moving].sum()),
        "moving_pixels": float(moving.sum()),
        "moving_gear_2_pixels": float((levels[moving] >= 2).sum()),
        "static_error": float(error[~moving].sum()),
        "static_pixels": float((~moving).sum()),
        "static_gear_1_pixels": float((levels[~moving] == 1).sum()),
    }


def region_scores(sums: Dict[str, float], min_mse: float) -> Dict[str, float]:
    """From ``region_sums`` (of one view, or averaged over views): ``psnr_moving`` and ``psnr_static`` over the pixels
    of each region (MSE clamped at ``min_mse``), ``moving_at_gear_2`` and ``static_at_gear_1`` as shares. A region
    without pixels has no scores (missing, not zero)."""
    scores = {}
    for region, share, gear_pixels in (
        ("moving", "moving_at_gear_2", "moving_gear_2_pixels"), ("static", "static_at_gear_1", "static_gear_1_pixels")
    ):
        pixels = sums[f"{region}_pixels"]
        if pixels > 0:
            scores[f"psnr_{region}"] = -10.0 * math.log10(max(sums[f"{region}_error"] / pixels, min_mse))
            scores[share] = sums[gear_pixels] / pixels
    return scores
