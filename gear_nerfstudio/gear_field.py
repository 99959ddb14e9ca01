"""Serial 4D feature volumes with a gear function (Gear-NeRF, Sec 4.1-4.2, Eq 3-7).

Conventions shared by every planar field in this module:

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

import math
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from nerfstudio.field_components.activations import trunc_exp
from nerfstudio.field_components.encodings import SHEncoding
from nerfstudio.field_components.mlp import MLP
from nerfstudio.field_components.spatial_distortions import SpatialDistortion

SPACE_PLANE_AXES = ((0, 1), (0, 2), (1, 2))
"""Axes of the spatial planes h_1(x, y), h_2(x, z), h_3(y, z)."""
TIME_PLANE_AXES = (2, 1, 0)
"""Spatial axis of the space-time planes k_1(z, t), k_2(y, t), k_3(x, t) paired with h_1, h_2, h_3."""


def gear_level(g: Float[Tensor, "*bs"], num_gears: int) -> Int[Tensor, "*bs"]:
    """Eq 5: p = 1 if g < 1, N_gear if g >= N_gear, ceil(g) otherwise.

    -inf maps to 1, +inf to N_gear; NaN maps to 1 (the lowest gear, i.e. no extra sampling).
    """
    return torch.ceil(torch.nan_to_num(g, nan=1.0).clamp(1.0, float(num_gears))).long()


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


def temporal_resolutions(num_gears: int, num_frames: int) -> List[int]:
    """Sec 4.4: temporal resolution of each gear's space-time planes.

    Linear interpolation from 1 (G = 1) to ``num_frames`` (G = N_gear), rounded half up, at least 1.
    With a single gear, that gear is the top gear and gets ``num_frames`` rows (plain K-Planes).
    """
    num_frames = max(1, num_frames)
    if num_gears == 1:
        return [num_frames]
    return [
        max(1, math.floor(1 + (num_frames - 1) * (gear - 1) / (num_gears - 1) + 0.5))
        for gear in range(1, num_gears + 1)
    ]


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
    return torch.stack([x[:, list(axes)] for axes in SPACE_PLANE_AXES])


def time_coords(x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "3 N 2"]:
    """Coordinates of each sample on the space-time planes (z, t), (y, t), (x, t)."""
    t = t * 2.0 - 1.0
    return torch.stack([torch.cat([x[:, axis : axis + 1], t], dim=-1) for axis in TIME_PLANE_AXES])


def touched_columns(u: Float[Tensor, "N"], resolution: int) -> Bool[Tensor, "resolution"]:
    """Cells along one spatial axis of a plane of ``resolution`` cells (``align_corners=True``, border-clamped)
    that bilinear sampling at coordinates u in [-1, 1] reads."""
    position = (u.clamp(-1.0, 1.0) + 1.0) * 0.5 * (resolution - 1)
    low = position.floor().long().clamp(0, resolution - 1)
    touched = torch.zeros(resolution, dtype=torch.bool, device=u.device)
    touched[low] = True
    touched[(low + 1).clamp(max=resolution - 1)] = True
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

    def forward(self, coords: Float[Tensor, "3 N 2"]) -> Float[Tensor, "3 N out"]:
        """Features of the three planes, resolutions concatenated (out = C * num_resolutions)."""
        grid = coords[:, :, None, :]
        features = [
            F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)[..., 0]
            for plane in self.planes
        ]
        return torch.cat(features, dim=1).transpose(1, 2)


def init_space_plane(plane: Tensor) -> None:
    """Spatial planes start uniform in (0.1, 0.5), as in K-Planes."""
    nn.init.uniform_(plane, 0.1, 0.5)


def init_time_plane(plane: Tensor) -> None:
    """Space-time planes start at 1, the identity of the Hadamard product, as in K-Planes."""
    nn.init.ones_(plane)


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


def per_plane_sum(terms: List[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """Sum of per-triple terms (each the mean over its three planes) divided by the triples of one K-Planes
    field: K-Planes' normalisation per plane, so every plane weighs the same whatever other planes exist."""
    total = torch.stack(terms).sum() if terms else like.new_zeros(())
    return total / triples_per_field


def plane_tv(space_triples: Sequence[Tensor], time_triples: Sequence[Tensor], triples_per_field: int) -> Tensor:
    """K-Planes total variation: mean squared difference of neighbouring cells along both axes of each spatial
    plane and along the spatial axis (W) of each space-time plane, normalised per plane (``per_plane_sum``)."""
    terms = [
        (t[..., 1:, :] - t[..., :-1, :]).square().mean() + (t[..., :, 1:] - t[..., :, :-1]).square().mean()
        for t in space_triples
    ]
    terms += [(t[..., :, 1:] - t[..., :, :-1]).square().mean() for t in time_triples]
    return per_plane_sum(terms, triples_per_field, space_triples[0])


def l1_time_planes(time_triples: Sequence[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """K-Planes L1 penalty: mean |1 - k| of each space-time plane (1 is static), normalised per plane."""
    return per_plane_sum([(1.0 - t).abs().mean() for t in time_triples], triples_per_field, like)


def time_smoothness(time_triples: Sequence[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """K-Planes time smoothness: mean squared second difference along t of each space-time plane (planes with
    fewer than 3 rows have none), normalised per plane."""
    terms = [
        (t[..., 2:, :] - 2.0 * t[..., 1:-1, :] + t[..., :-2, :]).square().mean() for t in time_triples if t.shape[-2] >= 3
    ]
    return per_plane_sum(terms, triples_per_field, like)


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
    """

    def __init__(self, feature_dim: int = 8, resolution: int = 64, time_resolution: int = 1) -> None:
        super().__init__()
        if feature_dim < 2 or feature_dim % 2:
            raise ValueError(f"gear_feature_dim must be even and >= 2, got {feature_dim}")
        self.space_planes = PlaneTriple(feature_dim, [(resolution, resolution)], init_gear_space_plane)
        self.time_planes = PlaneTriple(feature_dim, [(time_resolution, resolution)], init_gear_time_plane)

    def forward(self, x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N"]:
        """g at normalised positions x in [-1, 1]^3 and times t in [0, 1]."""
        products = self.space_planes(space_coords(x)) * self.time_planes(time_coords(x, t))
        return 1.0 + products.sum(dim=(0, 2))


class GearField(nn.Module):
    """Serial 4D feature volumes (Eq 3-7) and the tiny MLP F_theta (density, colour, SAM embedding).

    Spatial planes h_j (multi-resolution, shared by all gears), per-gear space-time planes k_j^G and a
    shared linear map B = [B_1 B_2 B_3] give f^G = sum_j B_j(h_j ⊙ k_j^G) (Eq 3). Resolutions are
    concatenated before B, so B_j maps (M * num_resolutions) -> M (M -> M with one resolution).
    Each sample is evaluated only with the planes of its own gear p(x, t) (Eq 5-7).

    Density is ``trunc_exp(raw - 1)`` (K-Planes), kept finite by ``density_activation``; colour uses
    spherical harmonics of the view direction; the SAM embedding (Sec 4.2) is predicted from f in
    ``sam_head_dim`` channels and lifted to ``sam_dim`` by a learned affine map after rendering (exact by
    linearity of Eq 8, see ``lift_sam``).

    Args:
        aabb: scene box, positions inside map to [-1, 1]^3.
        num_frames: frames T of the loaded window.
        num_gears: N_gear.
        feature_dim: M, the dimension of f.
        resolutions: spatial resolutions of the planes.
        gear_feature_dim: M', channels of the gear function's planes.
        gear_resolution: spatial resolution of the gear function's planes.
        gear_time_resolution: temporal resolution of k'; ``num_frames`` when None.
        time_resolutions: rows of each gear's space-time planes; ``temporal_resolutions`` (Sec 4.4) when None.
        geo_feat_dim: features passed from the density MLP to the colour MLP.
        hidden_dim: width of the density and SAM MLPs.
        hidden_dim_color: width of the colour MLP.
        sam_dim: dimension of SAM encoder features.
        sam_head_dim: dimension predicted per sample before the lift; None predicts ``sam_dim`` directly.
        spatial_distortion: contraction for unbounded scenes, None for bounded scenes.
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        num_frames: int,
        num_gears: int = 4,
        feature_dim: int = 32,
        resolutions: Sequence[int] = (64, 128, 256, 512),
        gear_feature_dim: int = 8,
        gear_resolution: int = 64,
        gear_time_resolution: Optional[int] = None,
        time_resolutions: Optional[Sequence[int]] = None,
        geo_feat_dim: int = 15,
        hidden_dim: int = 64,
        hidden_dim_color: int = 64,
        sam_dim: int = 256,
        sam_head_dim: Optional[int] = 32,
        spatial_distortion: Optional[SpatialDistortion] = None,
    ) -> None:
        super().__init__()
        if num_gears < 1:
            raise ValueError(f"num_gears must be >= 1, got {num_gears}")
        self.register_buffer("aabb", aabb.clone().float())
        self.num_gears = num_gears
        self.feature_dim = feature_dim
        self.spatial_distortion = spatial_distortion
        if time_resolutions is None:
            self.time_resolutions = temporal_resolutions(num_gears, num_frames)
        elif len(time_resolutions) != num_gears or min(time_resolutions) < 1:
            raise ValueError(f"time_resolutions needs {num_gears} values >= 1 (one per gear), got {time_resolutions}")
        else:
            self.time_resolutions = [int(rows) for rows in time_resolutions]

        self.space_planes = PlaneTriple(feature_dim, [(r, r) for r in resolutions], init_space_plane)
        self.time_planes = nn.ModuleList(
            PlaneTriple(feature_dim, [(t_res, r) for r in resolutions], init_time_plane)
            for t_res in self.time_resolutions
        )
        self.resolutions = [int(r) for r in resolutions]
        # Columns (spatial cells) of each gear's space-time planes that a training sample has touched, per
        # gear, resolution and plane. A gear with none gets no gradient, no regulariser and so no optimizer step
        # or state (a static scene stays in gear 1 and never pays for time); a column that a gear touches for
        # the first time inherits the lower gear's (``inherit_columns``).
        self.register_buffer(
            "used_columns", torch.zeros(num_gears, len(resolutions), 3, max(resolutions), dtype=torch.bool)
        )
        self.basis = nn.Linear(3 * feature_dim * len(resolutions), feature_dim, bias=False)
        self.gear_function = GearFunction(gear_feature_dim, gear_resolution, max(1, gear_time_resolution or num_frames))

        self.direction_encoding = SHEncoding(levels=4, implementation="torch")
        self.density_net = MLP(
            in_dim=feature_dim, num_layers=2, layer_width=hidden_dim, out_dim=1 + geo_feat_dim, implementation="torch"
        )
        self.color_net = MLP(
            in_dim=self.direction_encoding.get_out_dim() + geo_feat_dim,
            num_layers=3,
            layer_width=hidden_dim_color,
            out_dim=3,
            out_activation=nn.Sigmoid(),
            implementation="torch",
        )
        self.sam_net = MLP(
            in_dim=feature_dim,
            num_layers=2,
            layer_width=hidden_dim,
            out_dim=sam_head_dim or sam_dim,
            implementation="torch",
        )
        self.sam_lift = nn.Linear(sam_head_dim, sam_dim) if sam_head_dim else None

    def gear_values(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*bs 1"]]
    ) -> Float[Tensor, "*bs"]:
        """Eq 4: differentiable gear value g at world positions and times."""
        shape = positions.shape[:-1]
        x, _ = normalize_positions(positions.reshape(-1, 3), self.aabb, self.spatial_distortion)
        t = broadcast_times(times, shape, positions).reshape(-1, 1)
        return self.gear_function(x, t).reshape(shape)

    @torch.no_grad()
    def gear_levels(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*bs 1"]]
    ) -> Int[Tensor, "*bs"]:
        """Eq 5: integer gear level p at world positions and times."""
        return gear_level(self.gear_values(positions, times), self.num_gears)

    def gear_feature(self, x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"], gear: int) -> Float[Tensor, "N M"]:
        """Eq 3: f^G at normalised positions with the planes of gear ``gear`` (1-based)."""
        products = self.space_planes(space_coords(x)) * self.time_planes[gear - 1](time_coords(x, t))
        return self.basis(products.transpose(0, 1).reshape(x.shape[0], -1))

    def gear_features(
        self, x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"], levels: Int[Tensor, "N"]
    ) -> Float[Tensor, "N M"]:
        """Eq 6-7: f = sum_G m_G f^G, evaluating each sample only with the planes of its own gear."""
        order = torch.argsort(levels)
        counts = torch.bincount(levels, minlength=self.num_gears + 1)[1 : self.num_gears + 1].tolist()
        training = self.training and torch.is_grad_enabled()
        chunks = []
        start = 0
        for gear, count in enumerate(counts, start=1):
            if count:
                index = order[start : start + count]
                if training:
                    self.claim_columns(x[index], gear)
                chunks.append(self.gear_feature(x[index], t[index], gear))
            start += count
        if not chunks:
            return x.new_zeros((0, self.feature_dim))
        sorted_features = torch.cat(chunks)
        return torch.zeros_like(sorted_features).index_copy(0, order, sorted_features)

    def forward(
        self,
        positions: Float[Tensor, "N 3"],
        directions: Float[Tensor, "N 3"],
        times: Optional[Float[Tensor, "N 1"]] = None,
    ) -> Dict[str, Tensor]:
        """Evaluate flat (packed) samples.

        Returns:
            ``density`` (N, 1), ``rgb`` (N, 3), ``sam`` (N, sam_head_dim or sam_dim) and ``gear_level`` (N,).
        """
        x, inside = normalize_positions(positions, self.aabb, self.spatial_distortion)
        t = broadcast_times(times, positions.shape[:-1], positions)
        with torch.no_grad():
            levels = gear_level(self.gear_function(x, t), self.num_gears)
        features = self.gear_features(x, t, levels)

        hidden = self.density_net(features)
        density = torch.where(inside[:, None], density_activation(hidden[:, :1]), torch.zeros_like(hidden[:, :1]))
        encoded_directions = self.direction_encoding(F.normalize(directions, dim=-1))
        rgb = self.color_net(torch.cat([encoded_directions, hidden[:, 1:]], dim=-1))
        return {"density": density, "rgb": rgb, "sam": self.sam_net(features), "gear_level": levels}

    def lift_sam(
        self, rendered: Float[Tensor, "*bs C"], accumulation: Float[Tensor, "*bs 1"]
    ) -> Float[Tensor, "*bs S"]:
        """Eq 8 for s_i = A e_i + b: sum_i w_i s_i = A (sum_i w_i e_i) + b sum_i w_i."""
        if self.sam_lift is None:
            return rendered
        return F.linear(rendered, self.sam_lift.weight) + accumulation * self.sam_lift.bias

    def radiance_parameters(self) -> List[nn.Parameter]:
        """Everything but the gear function: planes h, k^G, B and F_theta."""
        gear_ids = {id(p) for p in self.gear_function.parameters()}
        return [p for p in self.parameters() if id(p) not in gear_ids]

    @property
    def used_gears(self) -> Tensor:
        """(num_gears,) bool: gears whose space-time planes have had a training sample."""
        return self.used_columns.flatten(1).any(dim=1)

    @torch.no_grad()
    def claim_columns(self, x: Float[Tensor, "N 3"], gear: int) -> None:
        """Mark the columns of gear ``gear``'s space-time planes that samples at x (normalised) touch; columns
        touched for the first time inherit the lower gear's (``inherit_columns``) before the gear is evaluated."""
        touched = torch.zeros_like(self.used_columns[0])
        for r, resolution in enumerate(self.resolutions):
            for j, axis in enumerate(TIME_PLANE_AXES):
                touched[r, j, :resolution] = touched_columns(x[:, axis], resolution)
        new = touched & ~self.used_columns[gear - 1]
        if gear > 1 and bool(new.any()):
            self.inherit_columns(gear, new)
        self.used_columns[gear - 1] |= touched

    @torch.no_grad()
    def inherit_columns(self, gear: int, columns: Tensor) -> None:
        """An upshift keeps what the region had learned: the given columns (resolution, plane, cell) of k^gear
        become those of the highest lower gear that has used them (gear 1 otherwise), resampled linearly to
        gear's rows (Sec 4.4's temporal resolutions). A region that moves up a gear then renders as before
        the move, and its new rows start from its motion at the lower temporal resolution."""
        remaining = columns
        for source in range(gear - 1, 0, -1):
            take = remaining if source == 1 else remaining & self.used_columns[source - 1]
            if not bool(take.any()):
                continue
            remaining = remaining & ~take
            for r, (target_plane, source_plane) in enumerate(
                zip(self.time_planes[gear - 1].planes, self.time_planes[source - 1].planes)
            ):
                resampled = F.interpolate(
                    source_plane, size=target_plane.shape[-2:], mode="bilinear", align_corners=True
                )
                mask = take[r, :, : target_plane.shape[-1]][:, None, None, :]
                target_plane.copy_(torch.where(mask, resampled, target_plane))

    def used_time_planes(self) -> List[Tensor]:
        """Space-time planes k^G of the gears that have had a training sample."""
        used = self.used_gears.tolist()
        return [plane for gear, triple in enumerate(self.time_planes) if used[gear] for plane in triple.planes]

    def parameters_in_use(self) -> int:
        """Number of parameters that training updates: everything but the planes of unused gears."""
        used = self.used_gears.tolist()
        unused = {id(plane) for gear, triple in enumerate(self.time_planes) if not used[gear] for plane in triple.planes}
        return sum(p.numel() for p in self.parameters() if id(p) not in unused)

    def regularisers(self) -> Dict[str, Tensor]:
        """K-Planes regularisers on the radiance planes of the used gears, normalised per plane as in K-Planes
        (a field of one gear has 2 x len(resolutions) plane triples, of which len(resolutions) space-time), so
        each plane weighs the same however many gears are in use. The gear function is left alone."""
        space = list(self.space_planes.planes)
        time = self.used_time_planes()
        count = len(self.resolutions)
        return {
            "plane_tv": plane_tv(space, time, 2 * count),
            "l1_time_planes": l1_time_planes(time, count, space[0]),
            "time_smoothness": time_smoothness(time, count, space[0]),
        }


class ProposalDensityField(nn.Module):
    """Density-only planar field for the optional proposal sampler (one gear, one resolution).

    Args:
        aabb: scene box.
        resolution: spatial resolution of the planes.
        time_resolution: temporal resolution of the space-time planes.
        feature_dim: plane channels.
        spatial_distortion: contraction for unbounded scenes.
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        resolution: int,
        time_resolution: int,
        feature_dim: int = 8,
        spatial_distortion: Optional[SpatialDistortion] = None,
    ) -> None:
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.spatial_distortion = spatial_distortion
        self.space_planes = PlaneTriple(feature_dim, [(resolution, resolution)], init_space_plane)
        self.time_planes = PlaneTriple(feature_dim, [(max(1, time_resolution), resolution)], init_time_plane)
        self.decoder = nn.Linear(3 * feature_dim, 1)

    def density_fn(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*rays 1"]] = None
    ) -> Float[Tensor, "*bs 1"]:
        """Density at world positions; per-ray ``times`` broadcast over the samples of each ray."""
        shape = positions.shape[:-1]
        x, inside = normalize_positions(positions.reshape(-1, 3), self.aabb, self.spatial_distortion)
        t = broadcast_times(times, shape, positions).reshape(-1, 1)
        products = self.space_planes(space_coords(x)) * self.time_planes(time_coords(x, t))
        raw = self.decoder(products.transpose(0, 1).reshape(x.shape[0], -1))
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
