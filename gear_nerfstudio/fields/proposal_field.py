"""Density-only planar field for the optional proposal sampler (K-Planes)."""

from __future__ import annotations

from typing import Dict, Literal, Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn

from nerfstudio.field_components.spatial_distortions import SpatialDistortion

from gear_nerfstudio.fields.planes import (
    PlaneTriple,
    broadcast_times,
    density_activation,
    flat_features,
    init_space_plane,
    init_time_plane,
    normalize_positions,
    space_coords,
    time_coords,
)
from gear_nerfstudio.fields.regularisers import l1_time_planes, plane_tv, time_smoothness
from gear_nerfstudio.fields.seen_space import SeenSpace


class ProposalDensityField(nn.Module):
    """Density-only planar field for the optional proposal sampler (one gear, one resolution).

    Args:
        aabb: scene box.
        resolution: spatial resolution of the planes.
        time_resolution: temporal resolution of the space-time planes.
        feature_dim: plane channels.
        spatial_distortion: contraction for unbounded scenes.
        plane_kernel: plane lookups by "torch" (``grid_sample``) or "warp" (``plane_kernel.py``, same values).
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        resolution: int,
        time_resolution: int,
        feature_dim: int = 8,
        spatial_distortion: Optional[SpatialDistortion] = None,
        plane_kernel: Literal["torch", "warp"] = "torch",
    ) -> None:
        super().__init__()
        if plane_kernel not in ("torch", "warp"):
            raise ValueError(f"plane_kernel must be 'torch' or 'warp', got {plane_kernel!r}")
        self.plane_kernel = plane_kernel
        self.register_buffer("aabb", aabb.clone().float())
        self.spatial_distortion = spatial_distortion
        self.space_planes = PlaneTriple(feature_dim, [(resolution, resolution)], init_space_plane)
        self.time_planes = PlaneTriple(feature_dim, [(max(1, time_resolution), resolution)], init_time_plane)
        self.decoder = nn.Linear(3 * feature_dim, 1)
        self.seen_space: Optional[SeenSpace] = None

    def density_fn(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*rays 1"]] = None
    ) -> Float[Tensor, "*bs 1"]:
        """Density at world positions; per-ray ``times`` broadcast over the samples of each ray. In evaluation
        mode zero outside ``seen_space`` when it is set (`seen_space.SeenSpace`)."""
        shape = positions.shape[:-1]
        x, inside = normalize_positions(positions.reshape(-1, 3), self.aabb, self.spatial_distortion)
        if self.seen_space is not None and not self.training:
            inside = inside & self.seen_space(x)
        t = broadcast_times(times, shape, positions).reshape(-1, 1)
        if self.plane_kernel == "warp":
            from gear_nerfstudio.fields.plane_kernel import one_gear_sums

            space, time = self.space_planes.planes, self.time_planes.planes
            raw = (one_gear_sums(self, x, t[:, 0], space, time, self.decoder.weight[0]) + self.decoder.bias)[:, None]
        else:
            raw = self.decoder(flat_features(self.space_planes(space_coords(x)) * self.time_planes(time_coords(x, t))))
        density = torch.where(inside[:, None], density_activation(raw), torch.zeros_like(raw))
        return density.reshape(*shape, 1)

    def regularisers(self) -> Dict[str, Tensor]:
        """K-Planes regularisers on the proposal planes."""
        space, time = list(self.space_planes.planes), list(self.time_planes.planes)
        return {
            "plane_tv": plane_tv(space, time, 2),
            "l1_time_planes": l1_time_planes(time, 1, space[0]),
            "time_smoothness": time_smoothness(time, 1, space[0]),
        }
