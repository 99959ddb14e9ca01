"""Planes of the planar fields (K-Planes building blocks) and the conventions they share.

* Positions are first mapped by the scene box to [-1, 1]^3 (the identity for the dataparsers' box).
  Unbounded scenes are then contracted with nerfstudio's ``SceneContraction`` (order=inf, into [-2, 2])
  and halved. In bounded scenes, points outside the box get zero density; their plane features are
  clamped to the border (``padding_mode="border"``).
* Times are in [0, 1] and map to [-1, 1] on the temporal axis; with ``align_corners=True`` frame i of T
  sits exactly on row i of a plane with T rows. A plane with one row is constant in time.
* The three planes of one resolution are stored as one ``(3, C, H, W)`` tensor: spatial planes h_j over
  (x, y), (x, z), (y, z) and space-time planes k_j over (z, t), (y, t), (x, t) (W = space, H = time).
"""

from __future__ import annotations

from typing import Callable, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from nerfstudio.field_components.activations import trunc_exp
from nerfstudio.field_components.spatial_distortions import SpatialDistortion

SPACE_PLANE_AXES = ((0, 1), (0, 2), (1, 2))
"""Axes of the spatial planes h_1(x, y), h_2(x, z), h_3(y, z)."""
TIME_PLANE_AXES = (2, 1, 0)
"""Spatial axis of the space-time planes k_1(z, t), k_2(y, t), k_3(x, t) paired with h_1, h_2, h_3."""


MAX_LOG_DENSITY = 80.0
"""Cap on log sigma: exp(80) ~ 5.5e34 is finite in float32 and bfloat16 (exp overflows past 88.7)."""


def density_activation(raw: Tensor) -> Tensor:
    """sigma = exp(raw - 1) (K-Planes' ``trunc_exp``) with log sigma capped at ``MAX_LOG_DENSITY``.

    Eq 1 uses sigma only through alpha = 1 - exp(-sigma delta). An infinite sigma gives sigma delta = NaN on a
    zero-length segment (delta = 0: near = far, a split of such a segment), and that NaN reaches the
    transmittance of every later sample of the ray and the gradients. At the cap, any segment longer than
    1e-33 is already opaque (alpha = 1 in float32), so no rendered value changes.
    """
    return trunc_exp((raw - 1.0).clamp(max=MAX_LOG_DENSITY))


def normalize_positions(
    positions: Float[Tensor, "*bs 3"], aabb: Float[Tensor, "2 3"], spatial_distortion: Optional[SpatialDistortion]
) -> Tuple[Float[Tensor, "*bs 3"], Bool[Tensor, "*bs"]]:
    """Plane coordinates in [-1, 1]^3 and whether each point lies inside the represented volume."""
    x = (positions - aabb[0]) / (aabb[1] - aabb[0]) * 2.0 - 1.0
    if spatial_distortion is not None:
        x = spatial_distortion(x) / 2.0
        return x, torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
    return x, (x.abs() <= 1.0).all(dim=-1)


def broadcast_times(times: Optional[Tensor], shape: torch.Size, like: Tensor) -> Float[Tensor, "*bs 1"]:
    """Times of shape ``(*shape, 1)``: zeros when absent, per-ray times expanded over samples."""
    if times is None:
        return like.new_zeros((*shape, 1))
    while times.dim() < len(shape) + 1:
        times = times.unsqueeze(-2)
    return times.expand(*shape, 1)


def space_coords(x: Float[Tensor, "N 3"]) -> Float[Tensor, "3 N 2"]:
    """Coordinates of each sample on the spatial planes (x, y), (x, z), (y, z)."""
    return torch.stack([torch.stack([x[:, a], x[:, b]], dim=-1) for a, b in SPACE_PLANE_AXES])


def time_coords(x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "3 N 2"]:
    """Coordinates of each sample on the space-time planes (z, t), (y, t), (x, t)."""
    t = t * 2.0 - 1.0
    return torch.stack([torch.cat([x[:, axis : axis + 1], t], dim=-1) for axis in TIME_PLANE_AXES])


def touched_columns(
    u: Float[Tensor, "N"], resolution: int, groups: Int[Tensor, "N"], num_groups: int
) -> Bool[Tensor, "num_groups resolution"]:
    """Cells along one spatial axis of a plane of ``resolution`` cells (``align_corners=True``, border-clamped)
    that bilinear sampling at coordinates u in [-1, 1] reads, per group of samples (row ``groups[i]`` for sample i);
    no host synchronisation."""
    position = (u.clamp(-1.0, 1.0) + 1.0) * 0.5 * (resolution - 1)
    low = position.floor().long().clamp(0, resolution - 1)
    touched = torch.zeros(num_groups, resolution, dtype=torch.bool, device=u.device)
    mark = torch.ones_like(low, dtype=torch.bool)  # a device tensor: assigning the scalar True would upload it
    touched.index_put_((groups, low), mark)
    touched.index_put_((groups, (low + 1).clamp(max=resolution - 1)), mark)
    return touched


class PlaneTriple(nn.Module):
    """Three feature planes at one or more resolutions, sampled bilinearly.

    Args:
        num_channels: feature channels C of every plane.
        shapes: (H, W) of the planes at each resolution.
        init: in-place initialiser applied to each ``(3, C, H, W)`` parameter.
    """

    def __init__(self, num_channels: int, shapes: Sequence[Tuple[int, int]], init: Callable[[Tensor], None]) -> None:
        super().__init__()
        self.planes = nn.ParameterList()
        for height, width in shapes:
            plane = torch.empty(3, num_channels, height, width)
            init(plane)
            self.planes.append(nn.Parameter(plane))

    def forward(self, coords: Float[Tensor, "3 N 2"]) -> Float[Tensor, "3 out N"]:
        """Features of the three planes, resolutions concatenated (out = C * num_resolutions), channels first as
        grid_sample gives them (``flat_features`` feeds them to a linear map without a transposed copy)."""
        lookups = self.lookups(coords)
        return lookups[0] if len(lookups) == 1 else torch.cat(lookups, dim=1)

    def lookups(self, coords: Float[Tensor, "3 N 2"]) -> List[Float[Tensor, "3 C N"]]:
        """Features of the three planes, one tensor per resolution."""
        return [bilinear(plane, coords) for plane in self.planes]


def bilinear(planes: Float[Tensor, "3 C H W"], coords: Float[Tensor, "3 N 2"]) -> Float[Tensor, "3 C N"]:
    """Bilinear lookup of three planes at (W, H) coordinates in [-1, 1] (corners aligned, clamped to the border)."""
    grid = coords[:, :, None, :]
    return F.grid_sample(planes, grid, mode="bilinear", padding_mode="border", align_corners=True)[..., 0]


def flat_features(products: Float[Tensor, "3 out N"]) -> Float[Tensor, "N 3out"]:
    """The three planes' features of each sample side by side (plane-major, as B = [B_1 B_2 B_3] of Eq 3 reads
    them): a transposed view, no copy."""
    return products.reshape(-1, products.shape[-1]).T


def init_space_plane(plane: Tensor) -> None:
    """Spatial planes start uniform in (0.1, 0.5), as in K-Planes."""
    nn.init.uniform_(plane, 0.1, 0.5)


def init_time_plane(plane: Tensor) -> None:
    """Space-time planes start at 1, the identity of the Hadamard product, as in K-Planes."""
    nn.init.ones_(plane)
