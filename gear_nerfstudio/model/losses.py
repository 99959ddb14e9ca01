"""Losses of Gear-NeRF training: Eq 2 (colour), Eq 9 (SAM features), the K-Planes regularisers of the field and of
the proposal networks, the proposal (interlevel) and distortion losses, and the sparse depth loss (DS-NeRF) on the
rays through triangulated points."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Sequence

import torch
from torch import Tensor

from nerfstudio.model_components.losses import DepthLossType, MSELoss, depth_loss, distortion_loss, interlevel_loss
from nerfstudio.model_components.renderers import RGBRenderer

from gear_nerfstudio.fields.proposal_field import ProposalDensityField

REGULARISERS = ("plane_tv", "l1_time_planes", "time_smoothness")
"""The K-Planes regularisers (``GearField.regularisers``)."""


@dataclass
class LossWeights:
    """The multiplier of each loss."""

    sam: float = 1.0
    """L_SAM (Eq 9), applied when the batch has "sam_features"."""
    plane_tv: float = 2e-4
    """Total variation of the radiance planes (K-Planes DyNeRF)."""
    l1_time_planes: float = 1e-4
    """L1 deviation of the radiance space-time planes from 1 (K-Planes DyNeRF)."""
    time_smoothness: float = 1e-3
    """Second difference along t of the radiance space-time planes (K-Planes DyNeRF)."""
    plane_tv_proposal: float = 2e-4
    """Plane TV of the proposal networks (K-Planes DyNeRF)."""
    l1_time_planes_proposal: float = 1e-4
    """L1 time planes of the proposal networks (K-Planes DyNeRF)."""
    time_smoothness_proposal: float = 1e-5
    """Time smoothness of the proposal networks (K-Planes DyNeRF)."""
    interlevel: float = 1.0
    """Proposal (interlevel) loss, proposal base sampler only."""
    distortion: float = 0.0
    """Distortion loss (Mip-NeRF 360) on the base samples, proposal base sampler only; 0: off."""
    sparse_depth: float = 0.01
    """DS-NeRF's depth loss on the rays through triangulated points (proposal base sampler only)."""
    sparse_depth_spread: float = 0.02
    """Standard deviation of each point's depth in that loss, as a fraction of the depth."""


class GearLosses:
    """The loss dict of a batch (nerfstudio's ``get_loss_dict``).

    Args:
        weights: the multipliers.
        renderer: the colour renderer, whose background the images are blended with.
        proposal_networks: the proposal density fields (none for the uniform base sampler).
    """

    def __init__(
        self, weights: LossWeights, renderer: RGBRenderer, proposal_networks: Sequence[ProposalDensityField]
    ) -> None:
        self.weights = weights
        self.renderer = renderer
        self.proposal_networks = tuple(proposal_networks)
        self.mse = MSELoss()

    def __call__(self, outputs: Dict[str, Any], batch: Dict[str, Tensor], training: bool) -> Dict[str, Tensor]:
        """Eq 2 (rgb), Eq 9 (sam, when the batch has "sam_features") and, in training, the regularisers (computed
        in the forward pass, ``GearNeRFModel.get_outputs``) and the proposal losses."""
        weights = self.weights
        device = outputs["rgb"].device
        pred_rgb, image = self.renderer.blend_background_for_loss_computation(
            pred_image=outputs["rgb"], pred_accumulation=outputs["accumulation"], gt_image=batch["image"].to(device)
        )
        losses = {"rgb_loss": self.mse(image, pred_rgb)}
        if "sam_features" in batch:
            losses["sam_loss"] = weights.sam * self.mse(batch["sam_features"].to(device), outputs["sam"])
        if not training:
            return losses
        for name in REGULARISERS:
            losses[name] = getattr(weights, name) * outputs[f"regulariser_{name}"]
        if "weights_list" in outputs:
            proposal = [net.regularisers() for net in self.proposal_networks]
            for name in REGULARISERS:
                losses[f"{name}_proposal"] = getattr(weights, f"{name}_proposal") * sum(r[name] for r in proposal)
            losses["interlevel_loss"] = weights.interlevel * interlevel_loss(
                outputs["weights_list"], outputs["ray_samples_list"]
            )
            if weights.sparse_depth > 0 and "sparse_depth" in batch:
                losses["sparse_depth_loss"] = weights.sparse_depth * self.sparse_depth(outputs, batch["sparse_depth"])
            if weights.distortion > 0:
                losses["distortion_loss"] = weights.distortion * distortion_loss(
                    outputs["weights_list"], outputs["ray_samples_list"]
                )
        return losses

    def sparse_depth(self, outputs: Dict[str, Any], target: Tensor) -> Tensor:
        """DS-NeRF's loss (nerfstudio's ``depth_loss``) on the rays with a depth between their near and far planes,
        summed over the sampling levels."""
        target = target.to(outputs["depth"].device)
        frustums = outputs["ray_samples_list"][-1].frustums
        rows = (target[:, 0] > frustums.starts[:, 0, 0]) & (target[:, 0] < frustums.ends[:, -1, 0])
        if not rows.any():
            return target.new_zeros(())
        variance = (self.weights.sparse_depth_spread * target[rows, None]) ** 2  # DS-NeRF's "sigma" is a variance
        return sum(
            depth_loss(
                weights[rows], samples[rows], target[rows], outputs["depth"][rows], variance,
                torch.ones_like(target[rows]), is_euclidean=True, depth_loss_type=DepthLossType.DS_NERF,
            )
            for weights, samples in zip(outputs["weights_list"], outputs["ray_samples_list"])
        )  # fmt: skip
