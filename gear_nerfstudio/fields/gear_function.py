"""The gear function g(x, t) (Eq 4) and the gear level p = ceil(g) it assigns (Eq 5)."""

from __future__ import annotations

from typing import Literal

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from gear_nerfstudio.fields.planes import PlaneTriple, space_coords, time_coords

def gear_level(g: Float[Tensor, "*bs"], num_gears: int) -> Int[Tensor, "*bs"]:
    """Eq 5: p = 1 if g < 1, N_gear if g >= N_gear, ceil(g) otherwise.

    -inf maps to 1, +inf to N_gear; NaN maps to 1 (the lowest gear, i.e. no extra sampling).
    """
    return torch.ceil(torch.nan_to_num(g, nan=1.0).clamp(1.0, float(num_gears))).long()


def init_gear_space_plane(plane: Tensor) -> None:
    """h' for Eq 4: first half of the channels uniform in (0.1, 0.5), second half zero."""
    half = plane.shape[1] // 2
    nn.init.uniform_(plane[:, :half], 0.1, 0.5)
    nn.init.zeros_(plane[:, half:])


def init_gear_time_plane(plane: Tensor) -> None:
    """k' for Eq 4: first half of the channels zero, second half uniform in (0.1, 0.5)."""
    half = plane.shape[1] // 2
    nn.init.zeros_(plane[:, :half])
    nn.init.uniform_(plane[:, half:], 0.1, 0.5)


class GearFunction(nn.Module):
    """Eq 4: the continuous gear value g(x, t) from its own planes h'_j, k'_j.

    g = 1 + sum_j 1^T (h'_j(.) ⊙ k'_j(.)). The offset 1 realises the paper's initialisation g = 1
    (Sec 4.3) exactly: h' and k' are initialised on complementary channels (h' is zero where k' is not
    and vice versa), so every product is exactly 0 at the start while dg/dk' = h' and dg/dh' = k' are
    non-zero, i.e. the first gear update already moves both h' and k'.

    Args:
        feature_dim: channels M' of h' and k' (even).
        resolution: spatial resolution of the planes.
        time_resolution: temporal resolution of k'.
        plane_kernel: plane lookups by "torch" (``grid_sample``) or "warp" (``plane_kernel.py``, same values).
    """

    def __init__(
        self,
        feature_dim: int = 8,
        resolution: int = 64,
        time_resolution: int = 1,
        plane_kernel: Literal["torch", "warp"] = "torch",
    ) -> None:
        super().__init__()
        if feature_dim < 2 or feature_dim % 2:
            raise ValueError(f"gear_feature_dim must be even and >= 2, got {feature_dim}")
        self.plane_kernel = plane_kernel
        self.space_planes = PlaneTriple(feature_dim, [(resolution, resolution)], init_gear_space_plane)
        self.time_planes = PlaneTriple(feature_dim, [(time_resolution, resolution)], init_gear_time_plane)

    def forward(self, x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N"]:
        """g at normalised positions x in [-1, 1]^3 and times t in [0, 1]."""
        if self.plane_kernel == "warp":
            from gear_nerfstudio.fields.plane_kernel import one_gear_sums

            space, time = self.space_planes.planes, self.time_planes.planes
            return 1.0 + one_gear_sums(self, x, t[:, 0], space, time, x.new_ones(3 * space[0].shape[1]))
        products = self.space_planes(space_coords(x)) * self.time_planes(time_coords(x, t))
        return 1.0 + products.sum(dim=(0, 1))
