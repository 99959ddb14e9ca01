"""Loss maps of training views and what the updates read off them (Sec 4.3): patch prompts, and the motion
gate (ground-truth change over time) with the pixels it marks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datasets.base_dataset import InputDataset
from torch import Tensor

from gear_nerfstudio.spread import evenly_spread


def patch_size_for(shape: Tuple[int, int], patch_size: int) -> int:
    """Patch side used on a loss map of this (h, w): at most the map's shorter side."""
    return max(1, min(patch_size, *shape))


def patch_means(values: Tensor, size: int) -> Tensor:
    """Average of a (h, w) map over size x size patches (the last row / column may be partial)."""
    return F.avg_pool2d(values[None, None], size, stride=size, ceil_mode=True)[0, 0]


def patch_prompts(
    loss_map: Tensor, patch_size: int, top_k: int, moving: Optional[Tensor] = None
) -> Tuple[Tensor, Tensor]:
    """Centres (x, y) of the top-k highest (label 1) and lowest (label 0) average-loss patches.

    moving: (rows, cols) bool per patch; only moving patches can give positive prompts (fewer than k
    positives, or none, when fewer patches move).
    """
    height, width = loss_map.shape
    size = patch_size_for((height, width), patch_size)
    pooled = patch_means(loss_map, size)
    k = min(top_k, pooled.numel() // 2)
    flat = pooled.flatten()
    candidates = flat if moving is None else torch.where(moving.flatten(), flat, -torch.inf)
    num_high = min(k, int(torch.isfinite(candidates).sum()))
    high = torch.topk(candidates, num_high).indices
    low = torch.topk(-flat, k).indices
    index = torch.cat([high, low])
    rows, cols = index // pooled.shape[1], index % pooled.shape[1]
    centres_x = torch.clamp((cols.float() + 0.5) * size, max=width - 0.5)
    centres_y = torch.clamp((rows.float() + 0.5) * size, max=height - 0.5)
    labels = torch.cat([torch.ones(num_high), torch.zeros(k)])
    return torch.stack([centres_x, centres_y], dim=-1), labels


def moving_patches(change: Tensor, patch_size: int, threshold: float) -> Tensor:
    """Patches (rows, cols) whose mean over-time change of the ground truth reaches the threshold."""
    return patch_means(change, patch_size_for(tuple(change.shape), patch_size)) >= threshold


def patches_to_pixels(patches: Tensor, shape: Tuple[int, int], patch_size: int) -> Tensor:
    """Per-patch booleans (rows, cols) spread to the pixels (h, w) of the map they were pooled from."""
    size = patch_size_for(shape, patch_size)
    pixels = patches.repeat_interleave(size, dim=0).repeat_interleave(size, dim=1)
    return pixels[: shape[0], : shape[1]]


def moving_pixels(change: Tensor, patch_size: int, threshold: float) -> Tensor:
    """Pixels (h, w) of the patches that ``moving_patches`` marks on a change map."""
    return patches_to_pixels(moving_patches(change, patch_size, threshold), tuple(change.shape), patch_size)


def stay_focus(mask: Tensor, in_motion: Tensor, patch_size: int) -> Tensor:
    """Pixels of S_stay at risk of moving up with the upshift mask (h, w): outside it, but within one patch of it,
    or in a moving patch (where the object is at other times). The gear function is smooth in space and time,
    so these are where an upshift spills over."""
    near = F.max_pool2d(mask[None, None].float(), 2 * patch_size + 1, stride=1, padding=patch_size)[0, 0] > 0
    return (near | in_motion) & ~mask


def resized_image(dataset: InputDataset, image_index: int, size: Tuple[int, int]) -> Tensor:
    """Image ``image_index`` of a dataset as RGB (h, w, 3), area-resampled to size (h, w)."""
    image = dataset.get_image_float32(image_index)[..., :3].permute(2, 0, 1)[None]
    return F.interpolate(image, size=size, mode="area")[0].permute(1, 2, 0)


def frame_change(
    dataset: InputDataset, image_index: int, rgb: Tensor, num_frames: int, window: Optional[int] = None
) -> Tensor:
    """Motion gate: per pixel of ``rgb`` (image ``image_index`` already resized to (h, w, 3) by ``resized_image``),
    the largest mean absolute RGB difference to up to ``num_frames`` other frames of the same camera, spread over
    the video or, with ``window``, over the frames at most ``window`` frames away (0 with none). Uses the
    dataparser's ``camera_ids`` and ``frame_ids`` metadata."""
    cameras, frames = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
    near = torch.ones_like(frames, dtype=torch.bool) if window is None else (frames - frames[image_index]).abs() <= window
    others = torch.nonzero((cameras == cameras[image_index]) & (frames != frames[image_index]) & near)[:, 0]
    size = tuple(rgb.shape[:2])
    change = torch.zeros(size)
    if len(others) == 0:
        return change
    for index in others[evenly_spread(len(others), num_frames)].tolist():
        change = torch.maximum(change, (rgb - resized_image(dataset, int(index), size)).abs().mean(-1))
    return change


@dataclass
class LossMap:
    """One rendered training view at loss-map resolution."""

    image_index: int
    camera: Cameras
    rgb: Tensor  # (h, w, 3) ground truth
    loss: Tensor  # (h, w) L(r)
    rgb_loss: Tensor  # (h, w) L_pho(r)
    surface: Tensor  # (h, w, 3) the surface point each pixel sees (rendered median depth)
    change: Tensor  # (h, w) ground-truth change over the video (motion gate)
    local_change: Tensor  # (h, w) ground-truth change to the previous and next frames
