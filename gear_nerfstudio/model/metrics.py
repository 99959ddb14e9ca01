"""Metrics of Gear-NeRF renders: PSNR, SSIM and LPIPS of an image, and the near layer (a held-out view that ends
in front of itself)."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from nerfstudio.model_components.renderers import RGBRenderer
from nerfstudio.utils.rich_utils import CONSOLE

MIN_MSE = 1e-10
"""Floor of the mean squared error in PSNR: a perfect prediction reports 100 dB instead of inf."""


def psnr(prediction: Tensor, target: Tensor) -> Tensor:
    """PSNR in dB for colours in [0, 1], -10 log10(MSE), with the MSE clamped at ``MIN_MSE``.

    Without the floor an exact match (all-black or all-white frames, background pixels) gives log10(0),
    i.e. inf, which poisons every mean over images that ns-eval and the logs take.
    """
    return -10.0 * torch.log10(torch.mean((prediction - target) ** 2).clamp(min=MIN_MSE))


NEAR_LAYER_DEPTH = 0.25
"""A pixel of an evaluation view is in a near layer when its depth is below this share of the training rays'
median depth."""
NEAR_LAYER_WARNING = 0.2
"""Share of an opaque evaluation view (accumulation above 0.9) in a near layer that training reports."""


def near_layer_pixels(depth: Float[Tensor, "*bs 1"], training_depth: Tensor) -> Bool[Tensor, "*bs 1"]:
    """Pixels of a render whose depth is below ``NEAR_LAYER_DEPTH`` x the training rays' median depth: on a rig whose
    cameras see the scene from similar distances, a held-out view that ends that close sees a layer in front of
    itself (none before any training batch has set the reference)."""
    return depth < NEAR_LAYER_DEPTH * training_depth


def near_layer(depth: Float[Tensor, "*bs 1"], training_depth: Tensor) -> float:
    """Share of a render's pixels in a near layer (``near_layer_pixels``)."""
    return float(near_layer_pixels(depth, training_depth).float().mean())


def near_layer_warning(views: List[Tuple[str, Dict[str, float]]], training_depth: float) -> Optional[str]:
    """One line naming the views (label, image metrics) that are opaque (accumulation above 0.9) and have more than
    ``NEAR_LAYER_WARNING`` of their pixels in a near layer; None when there are none."""
    layered = [
        f"{label} ({100 * metrics['near_layer']:.0f} %)"
        for label, metrics in views
        if metrics["near_layer"] > NEAR_LAYER_WARNING and metrics["accumulation"] > 0.9
    ]
    if not layered:
        return None
    return (
        f"Gear-NeRF: an opaque layer sits in front of the camera, closer than {NEAR_LAYER_DEPTH:g} x the training rays' "
        f"median depth ({training_depth:.3g}), in {len(layered)} of {len(views)} evaluation views: {', '.join(layered)}"
    )


def lpips_weights_path() -> Path:
    """Where torchvision keeps the AlexNet weights that torchmetrics' LPIPS needs."""
    from torchvision.models import AlexNet_Weights

    return Path(torch.hub.get_dir()) / "checkpoints" / Path(AlexNet_Weights.DEFAULT.url).name


class ImageMetrics:
    """PSNR, SSIM (and LPIPS when its weights are local) of a render against its image.

    Args:
        renderer: the model's colour renderer, whose background RGBA images are blended with.
    """

    def __init__(self, renderer: RGBRenderer) -> None:
        self.renderer = renderer
        self.lpips_metric: Dict[str, Optional[torch.nn.Module]] = {}
        """torchmetrics LPIPS under "metric" once looked for (None without its weights)."""

    def lpips(self, device: torch.device) -> Optional[torch.nn.Module]:
        """torchmetrics LPIPS if its AlexNet weights are already on disk (never downloads), else None."""
        if "metric" not in self.lpips_metric:
            path = lpips_weights_path()
            if path.is_file():
                from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

                self.lpips_metric["metric"] = LearnedPerceptualImagePatchSimilarity(normalize=True)
            else:
                CONSOLE.log(f"[yellow]LPIPS skipped: AlexNet weights not found at {path} (nothing is downloaded).")
                self.lpips_metric["metric"] = None
        metric = self.lpips_metric["metric"]
        return None if metric is None else metric.to(device)

    def __call__(
        self, rgb: Float[Tensor, "H W 3"], image: Float[Tensor, "H W C"], device: torch.device
    ) -> Dict[str, float]:
        """The metrics on ``device`` (RGBA images are blended with the background first)."""
        from torchmetrics.functional.image import structural_similarity_index_measure

        image = self.renderer.blend_background(image.to(device))
        rgb = rgb.to(device)
        image_nchw = torch.moveaxis(image, -1, 0)[None]
        rgb_nchw = torch.moveaxis(rgb, -1, 0)[None]
        metrics = {
            "psnr": float(psnr(rgb, image)),
            "ssim": float(structural_similarity_index_measure(rgb_nchw, image_nchw, data_range=1.0)),
        }
        lpips = self.lpips(device)
        if lpips is not None:
            metrics["lpips"] = float(lpips(rgb_nchw.clamp(0, 1), image_nchw.clamp(0, 1)))
        return metrics
