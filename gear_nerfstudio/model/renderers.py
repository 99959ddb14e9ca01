"""Renderers of the Gear-NeRF outputs beside nerfstudio's colour, depth and accumulation: the SAM feature
map (Eq 8) and the gear level of each ray. Both sum over a ray's packed (split, Sec 4.4) samples, which
costs no padding however unevenly the rays are split."""

from __future__ import annotations

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from gear_nerfstudio.model.split_sampler import SplitRaySamples


class SamRenderer(nn.Module):
    """Eq 8: S(r) = sum_i w_i s_i over the samples of each ray."""

    def forward(
        self, split: SplitRaySamples, weights: Float[Tensor, "rays samples 1"], embeddings: Float[Tensor, "packed C"]
    ) -> Float[Tensor, "rays C"]:
        return split.accumulate(weights, embeddings)


class GearLevelRenderer(nn.Module):
    """The weighted mean gear level sum_i w_i p_i / sum_i w_i of each ray (1 where it accumulates nothing). The
    weights are summed in the same order as w_i p_i, so a ray whose samples share one level gets it exactly."""

    def forward(
        self, split: SplitRaySamples, weights: Float[Tensor, "rays samples 1"], levels: Int[Tensor, "packed"]
    ) -> Float[Tensor, "rays 1"]:
        levels = levels[:, None].to(weights.dtype)
        level_sum, weight_sum = split.accumulate(weights, torch.cat([levels, torch.ones_like(levels)], -1)).unbind(-1)
        return torch.where(weight_sum[:, None] > 1e-6, (level_sum / weight_sum.clamp(min=1e-6))[:, None], 1.0)
