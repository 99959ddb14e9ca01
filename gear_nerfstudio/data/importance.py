"""Ray importance sampling by global median (ISG, Neural 3D Video [Li et al. 2022], Sec 3.3; K-Planes trains its
Neural 3D Video scenes with it).

A training pixel is drawn with probability proportional to its weight

    W(r) = max(alpha, 1/3 * sum over the colour channels of rho(C_t(r) - C_median(r))),   rho(x) = x^2 / (x^2 + gamma^2),

where C_median is the per-pixel median of its camera over the frames of the window and rho is the Geman-McClure
robust function. Pixels that differ from their camera's static background (the moving people of a capture) get
weights near 1; still pixels get weights near (noise / gamma)^2, but at least alpha, the floor of Neural 3D
Video's temporal-difference weights (IST), so that a noise-free still pixel is still drawn. Rays are otherwise
used as drawn (no reweighting of the loss), as in Neural 3D Video and K-Planes.

- `MedianImages`: the per-camera median image of a training dataset, from at most `max_frames` frames of each camera.
- `IsgDataset`: an InputDataset whose items carry their weight map (``sampling_weight``).
- `IsgPixelSampler`: nerfstudio's PixelSampler, drawing the pixels of a batch of images by their weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Type

import numpy as np
import torch
from jaxtyping import Float, Int, UInt8
from torch import Tensor

from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.pixel_samplers import PixelSampler, PixelSamplerConfig
from nerfstudio.utils.rich_utils import CONSOLE

SAMPLING_WEIGHT = "sampling_weight"
"""Key of an image's weight map (H, W, 1) in dataset items and image batches."""


def isg_weight(
    image: Float[Tensor, "H W 3"], median: Float[Tensor, "H W 3"], gamma: float, floor: float
) -> Float[Tensor, "H W 1"]:
    """W(r) above: the mean over channels of the Geman-McClure function of the difference to the median image,
    at least ``floor`` (alpha)."""
    squared = (image - median).square()
    return (squared / (squared + gamma**2)).mean(dim=-1, keepdim=True).clamp_min(floor)


class MedianImages:
    """Per-camera median images of a dataset whose ``metadata["camera_ids"]`` names each image's camera."""

    def __init__(self, dataset: InputDataset, max_frames: int) -> None:
        camera_ids = np.asarray(dataset.metadata["camera_ids"])
        self.medians: Dict[int, UInt8[Tensor, "H W 3"]] = {}
        cameras = np.unique(camera_ids)
        with CONSOLE.status(f"Median images of {len(cameras)} cameras (ray importance sampling, ISG)"):
            for camera in cameras:
                images = np.flatnonzero(camera_ids == camera)
                chosen = images[np.linspace(0, len(images) - 1, min(len(images), max_frames)).round().astype(int)]
                frames = torch.stack([dataset.get_image_uint8(int(i))[..., :3] for i in chosen])
                self.medians[int(camera)] = frames.median(dim=0).values
        self.camera_ids = camera_ids

    def of_image(self, image_idx: int) -> Float[Tensor, "H W 3"]:
        """The median image of the camera of image ``image_idx``, in [0, 1]."""
        return self.medians[int(self.camera_ids[image_idx])].float() / 255.0


class IsgDataset(InputDataset):
    """InputDataset whose items carry ``sampling_weight``, the ISG weight map of their image."""

    def __init__(self, *args, gamma: float, floor: float, max_frames: int, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.gamma, self.floor = gamma, floor
        self.median_images = MedianImages(self, max_frames)

    def get_metadata(self, data: Dict) -> Dict:
        """The weight map of ``data["image"]`` against its camera's median image."""
        median = self.median_images.of_image(int(data["image_idx"]))
        return {SAMPLING_WEIGHT: isg_weight(data["image"][..., :3], median, self.gamma, self.floor)}


@dataclass
class IsgPixelSamplerConfig(PixelSamplerConfig):
    """PixelSampler that draws pixels by the images' ``sampling_weight`` maps, where a batch has them."""

    _target: Type = field(default_factory=lambda: IsgPixelSampler)


class IsgPixelSampler(PixelSampler):
    """Draws a batch's pixels with probability proportional to ``sampling_weight``: first the image (by the sum of
    its weights), then the pixel within it, so no single draw has more categories than one image has pixels
    (``torch.multinomial`` takes at most 2^24). A batch without weights, or with images of different sizes, is
    sampled uniformly, as nerfstudio does."""

    use_weights: bool = True
    """False: draw uniformly even where the images have weights (the datamanager's warm-up, ``isg_start_step``)."""
    weights: Optional[Float[Tensor, "num_images H W 1"]] = None
    """The weights of the image batch being sampled (``collate_image_dataset_batch``)."""

    def collate_image_dataset_batch(self, batch: Dict, num_rays_per_batch: int, keep_full_image: bool = False):
        self.weights = batch.get(SAMPLING_WEIGHT) if self.use_weights else None
        try:
            return super().collate_image_dataset_batch(batch, num_rays_per_batch, keep_full_image)
        finally:
            self.weights = None

    def sample_method(self, batch_size, num_images, image_height, image_width, mask=None, device="cpu"):
        if self.weights is None or mask is not None:
            return super().sample_method(batch_size, num_images, image_height, image_width, mask=mask, device=device)
        return weighted_pixels(self.weights[..., 0].to(device), batch_size)


def weighted_pixels(weights: Float[Tensor, "num_images H W"], count: int) -> Int[Tensor, "count 3"]:
    """``count`` rows (image, y, x) drawn with replacement with probability proportional to ``weights``."""
    num_images, height, width = weights.shape
    flat = weights.reshape(num_images, -1)
    images = torch.multinomial(flat.sum(dim=1), count, replacement=True)
    pixels = torch.empty_like(images)
    per_image = torch.bincount(images, minlength=num_images).tolist()
    for image, drawn in enumerate(per_image):
        if drawn:
            pixels[images == image] = torch.multinomial(flat[image], drawn, replacement=True)
    return torch.stack([images, pixels // width, pixels % width], dim=-1)
