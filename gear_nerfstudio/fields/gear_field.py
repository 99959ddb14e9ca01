"""Serial 4D feature volumes with a gear function (Gear-NeRF, Sec 4.1-4.2, Eq 3-7) as a nerfstudio Field."""

from __future__ import annotations

import math
from enum import Enum
from typing import Dict, List, Literal, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.encodings import SHEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.field_components.mlp import MLP
from nerfstudio.field_components.spatial_distortions import SpatialDistortion
from nerfstudio.fields.base_field import Field

from gear_nerfstudio import distributed
from gear_nerfstudio.fields.appearance import CameraAppearance
from gear_nerfstudio.fields.gear_function import GearFunction, gear_level
from gear_nerfstudio.fields.planes import (
    TIME_PLANE_AXES,
    PlaneTriple,
    bilinear,
    broadcast_times,
    density_activation,
    flat_features,
    init_space_plane,
    init_time_plane,
    normalize_positions,
    space_coords,
    time_coords,
    touched_columns,
)
from gear_nerfstudio.fields.regularisers import l1_time_planes, plane_tv, time_smoothness
from gear_nerfstudio.fields.seen_space import SeenSpace

APPEARANCE = "appearance"
"""Key of each sample's appearance code in ``RaySamples.metadata`` (``sample_points``)."""


def sample_points(
    positions: Float[Tensor, "*bs 3"],
    times: Optional[Float[Tensor, "*bs 1"]] = None,
    directions: Optional[Float[Tensor, "*bs 3"]] = None,
    appearance: Optional[Float[Tensor, "*bs A"]] = None,
) -> RaySamples:
    """Points (with times, viewing directions and appearance codes) as zero-length ray samples, the form a
    nerfstudio Field evaluates."""
    zeros = torch.zeros_like(positions[..., :1])
    directions = torch.ones_like(positions) if directions is None else directions
    frustums = Frustums(origins=positions, directions=directions, starts=zeros, ends=zeros, pixel_area=zeros + 1)
    metadata = None if appearance is None else {APPEARANCE: appearance}
    return RaySamples(frustums=frustums, times=times, metadata=metadata)


def temporal_resolutions(num_gears: int, num_frames: int, gear1_row_fraction: float = 0.0) -> List[int]:
    """Sec 4.4: temporal resolution of each gear's space-time planes.

    Linear interpolation from gear 1's rows, ``gear1_row_fraction * num_frames`` (at least 1; 0 gives the paper's
    1 row), to ``num_frames`` rows at G = N_gear, rounded half up. A single gear is the top gear (plain K-Planes).
    """
    num_frames = max(1, num_frames)
    if not 0.0 <= gear1_row_fraction <= 1.0:
        raise ValueError(f"gear1_row_fraction must lie in [0, 1], got {gear1_row_fraction}")
    if num_gears == 1:
        return [num_frames]
    lowest = max(1, math.floor(gear1_row_fraction * num_frames + 0.5))
    return [
        math.floor(lowest + (num_frames - lowest) * (gear - 1) / (num_gears - 1) + 0.5)
        for gear in range(1, num_gears + 1)
    ]


class GearFieldHeadNames(Enum):
    """Outputs of the gear field beside nerfstudio's density and rgb."""

    SAM = "sam"
    """SAM embedding of each sample before the lift (Sec 4.2)."""
    GEAR_LEVEL = "gear_level"
    """Gear level p of each sample (Eq 5)."""


FieldOutputs = Dict[Union[FieldHeadNames, GearFieldHeadNames], Tensor]


class GearField(Field):
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
        gear1_row_fraction: gear 1's rows as a fraction of ``num_frames`` when ``time_resolutions`` is None.
        geo_feat_dim: features passed from the density MLP to the colour MLP.
        hidden_dim: width of the density and SAM MLPs.
        hidden_dim_color: width of the colour MLP.
        sam_dim: dimension of SAM encoder features.
        sam_head_dim: dimension predicted per sample before the lift; None predicts ``sam_dim`` directly.
        spatial_distortion: contraction for unbounded scenes, None for bounded scenes.
        appearance_dim: channels of the per-camera appearance codes that enter the colour MLP; 0 for none.
        num_cameras: cameras of the rig (codes); trained_cameras: those with training images.
        initial_density: density (per scene unit) the field starts from everywhere: the density MLP's output bias
            is set to log(initial_density) + 1; None keeps PyTorch's initialisation (raw outputs near 0, so sigma
            near exp(-1)).
        plane_kernel: how ``gear_features`` and the gear function look up their planes: "torch" (``grid_sample``) or
            "warp" (the fused kernels of ``plane_kernel.py``, same values).
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        num_frames: int,
        num_gears: int = 4,
        feature_dim: int = 32,
        resolutions: Sequence[int] = (64, 128, 256, 512),
        gear_feature_dim: int = 32,
        gear_resolution: int = 64,
        gear_time_resolution: Optional[int] = None,
        time_resolutions: Optional[Sequence[int]] = None,
        gear1_row_fraction: float = 0.0,
        geo_feat_dim: int = 15,
        hidden_dim: int = 64,
        hidden_dim_color: int = 64,
        sam_dim: int = 256,
        sam_head_dim: Optional[int] = 32,
        spatial_distortion: Optional[SpatialDistortion] = None,
        appearance_dim: int = 0,
        num_cameras: int = 0,
        trained_cameras: Sequence[int] = (),
        initial_density: Optional[float] = None,
        plane_kernel: Literal["torch", "warp"] = "torch",
    ) -> None:
        super().__init__()
        if num_gears < 1:
            raise ValueError(f"num_gears must be >= 1, got {num_gears}")
        if plane_kernel not in ("torch", "warp"):
            raise ValueError(f"plane_kernel must be 'torch' or 'warp', got {plane_kernel!r}")
        self.plane_kernel = plane_kernel
        if initial_density is not None and not initial_density > 0:
            raise ValueError(f"initial_density must be > 0, got {initial_density}")
        self.register_buffer("aabb", aabb.clone().float())
        self.seen_space: Optional[SeenSpace] = None
        self.num_gears = num_gears
        self.feature_dim = feature_dim
        self.geo_feat_dim = geo_feat_dim
        self.spatial_distortion = spatial_distortion
        if time_resolutions is None:
            self.time_resolutions = temporal_resolutions(num_gears, num_frames, gear1_row_fraction)
        elif len(time_resolutions) != num_gears or min(time_resolutions) < 1:
            raise ValueError(f"time_resolutions needs {num_gears} values >= 1 (one per gear), got {time_resolutions}")
        else:
            self.time_resolutions = [int(rows) for rows in time_resolutions]

        self.space_planes = PlaneTriple(feature_dim, [(r, r) for r in resolutions], init_space_plane)
        self.time_planes = nn.ModuleList(
            PlaneTriple(feature_dim, [(t_res, r) for r in resolutions], init_time_plane)
            for t_res in self.time_resolutions
        )
        self.register_buffer("gear_rows", torch.tensor(self.time_resolutions, dtype=torch.float32), persistent=False)
        self.resolutions = [int(r) for r in resolutions]
        # Columns (spatial cells) of each gear's space-time planes that a training sample has touched, per
        # gear, resolution and plane. A gear with none gets no gradient, no regulariser and so no optimizer step
        # or state (a static scene stays in gear 1 and never pays for time); a column that a gear touches for
        # the first time inherits the lower gear's (``inherit_columns``).
        self.register_buffer(
            "used_columns", torch.zeros(num_gears, len(resolutions), 3, max(resolutions), dtype=torch.bool)
        )
        self.used_gears_seen: Tuple[Optional[Tensor], int, List[bool]] = (None, -1, [])
        """(used_columns tensor, its version, used_gears) when last read on the host (``gears_in_use``)."""
        self.basis = nn.Linear(3 * feature_dim * len(resolutions), feature_dim, bias=False)
        # The gear function's initial values come from a fork of the random stream, so that the modules after it (and
        # so the radiance field) start the same whatever its channels M' (`gear_feature_dim`).
        with torch.random.fork_rng(devices=[]):
            gear_rows = max(1, gear_time_resolution or num_frames)
            self.gear_function = GearFunction(gear_feature_dim, gear_resolution, gear_rows, plane_kernel)

        self.direction_encoding = SHEncoding(levels=4, implementation="torch")
        self.density_net = MLP(
            in_dim=feature_dim, num_layers=2, layer_width=hidden_dim, out_dim=1 + geo_feat_dim, implementation="torch"
        )
        if initial_density is not None:
            with torch.no_grad():
                self.density_net.layers[-1].bias[0] = math.log(initial_density) + 1.0
        self.appearance = CameraAppearance(num_cameras, appearance_dim, trained_cameras) if appearance_dim else None
        self.color_net = MLP(
            in_dim=self.direction_encoding.get_out_dim() + geo_feat_dim + appearance_dim,
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
        return self.basis(flat_features(products))

    def gear_features(
        self, x: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"], levels: Int[Tensor, "N"]
    ) -> Float[Tensor, "N M"]:
        """Eq 3, 6-7: f = sum_G m_G f^G = sum_j B_j (h_j ⊙ k_j^p) with each sample's own gear p, every gear in one
        lookup per resolution: the gears' space-time planes are stacked along time (``stacked_time_planes``) and a
        sample's time coordinate points into its gear's rows. In training the stack holds the gears in use only (a
        gear without samples gets no gradient); the samples' columns are claimed first (``claim_columns``)."""
        if self.training and torch.is_grad_enabled():
            new = self.claim_columns(x, levels)
            # the field's one host sync: after the claims, the gears in use and the gears with newly used columns
            # (under DDP both include the other processes' claims, so every process decides alike)
            used, renewed = torch.stack([self.used_gears, new.flatten(1).any(dim=1)]).tolist()
            self.used_gears_seen = (self.used_columns, self.used_columns._version, used)
            self.inherit_new_columns(new, renewed)
            if not any(used):  # no sample on any process yet: nothing to look up
                return x.new_zeros(len(x), self.feature_dim)
            stacked = self.used_gears
        else:
            used, stacked = [True] * self.num_gears, torch.ones_like(self.gear_rows)
        gears = [gear for gear in range(1, self.num_gears + 1) if used[gear - 1]]
        # each stacked gear takes its rows and two frame rows; its first row follows the frame row above it
        block = (self.gear_rows + 2) * stacked
        first_rows = block.cumsum(0) - block + 1
        if self.plane_kernel == "warp":
            from gear_nerfstudio.fields.plane_kernel import pack_planes, packed_once, plane_products

            packed = packed_once(
                self, [*self.space_planes.planes, *(p for gear in gears for p in self.time_planes[gear - 1].planes)],
                lambda: pack_planes(self.space_planes.planes, self.stacked_time_planes(gears)),
            )
            products = plane_products(x, t[:, 0], levels, packed, first_rows, self.gear_rows)
            return products @ self.basis.weight.T
        planes = self.stacked_time_planes(gears)
        row = first_rows[levels - 1] + t[:, 0] * (self.gear_rows[levels - 1] - 1)
        y = row * (2.0 / (planes[0].shape[-2] - 1)) - 1.0
        time = torch.stack([torch.stack([x[:, axis], y], dim=-1) for axis in TIME_PLANE_AXES])
        space = self.space_planes.lookups(space_coords(x))
        # B applied resolution by resolution: no concatenated copy of the features
        basis = self.basis.weight.view(self.feature_dim, 3, len(planes), -1)
        features = sum(
            basis[:, :, r].reshape(self.feature_dim, -1) @ (space[r] * bilinear(plane, time)).flatten(0, 1)
            for r, plane in enumerate(planes)
        )
        return features.T

    def stacked_time_planes(self, gears: Sequence[int]) -> List[Tensor]:
        """Per resolution, the space-time planes of ``gears`` stacked along time in gear order, each gear's rows
        framed by copies of its first and last row (so that rounding at a block's edge reads the same gear)."""
        planes = []
        for r in range(len(self.resolutions)):
            blocks = []
            for gear in gears:
                plane = self.time_planes[gear - 1].planes[r]
                blocks += [plane[:, :, :1], plane, plane[:, :, -1:]]
            planes.append(torch.cat(blocks, dim=2))
        return planes

    def get_density(self, ray_samples: RaySamples) -> Tuple[Float[Tensor, "*bs 1"], Float[Tensor, "*bs E"]]:
        """Density at the samples' positions and times, and what ``get_outputs`` needs of them: the density MLP's
        geometry features, the feature f (Eq 7) and the gear level p (Eq 5), concatenated."""
        positions = ray_samples.frustums.get_positions()
        shape = positions.shape[:-1]
        x, inside = normalize_positions(positions.reshape(-1, 3), self.aabb, self.spatial_distortion)
        t = broadcast_times(ray_samples.times, shape, positions).reshape(-1, 1)
        density, embedding = self.normalised_density(x, t, inside)
        return density.reshape(*shape, 1), embedding.reshape(*shape, embedding.shape[-1])

    def normalised_density(
        self,
        x: Float[Tensor, "N 3"],
        t: Float[Tensor, "N 1"],
        inside: Optional[Bool[Tensor, "N"]] = None,
        levels: Optional[Int[Tensor, "N"]] = None,
    ) -> Tuple[Float[Tensor, "N 1"], Float[Tensor, "N E"]]:
        """``get_density`` at plane coordinates x in [-1, 1]^3 (``normalize_positions``) and times t in [0, 1]:
        zero density where ``inside`` is False, and in evaluation mode outside ``seen_space`` when it is set
        (`seen_space.SeenSpace`); the embedding holds the geometry features, f (Eq 7) and p (Eq 5).
        ``levels``: the samples' gear levels p when the caller has them (Eq 5 otherwise)."""
        if self.seen_space is not None and not self.training:
            seen = self.seen_space(x)
            inside = seen if inside is None else inside & seen
        if levels is None:
            with torch.no_grad():
                levels = gear_level(self.gear_function(x, t), self.num_gears)
        features = self.gear_features(x, t, levels)
        hidden = self.density_net(features)
        density = density_activation(hidden[:, :1])
        if inside is not None:
            density = torch.where(inside[:, None], density, torch.zeros_like(density))
        embedding = torch.cat([hidden[:, 1:], features, levels[:, None].to(features.dtype)], dim=-1)
        return density, embedding

    def get_outputs(self, ray_samples: RaySamples, density_embedding: Optional[Tensor] = None) -> FieldOutputs:
        """Colour (view-dependent, spherical harmonics; with the sample's camera appearance code when the field has
        codes, the mean code when the sample has none), SAM embedding (Sec 4.2) and gear level of each sample."""
        assert density_embedding is not None, "the gear field's outputs need get_density's embedding"
        geometry, features, levels = self.split_embedding(density_embedding)
        return {
            FieldHeadNames.RGB: self.colour(ray_samples, geometry),
            GearFieldHeadNames.SAM: self.sam_net(features),
            GearFieldHeadNames.GEAR_LEVEL: levels,
        }

    def split_embedding(self, density_embedding: Tensor) -> Tuple[Tensor, Tensor, Int[Tensor, "*bs"]]:
        """``get_density``'s embedding as (geometry features, f, gear level p)."""
        geometry, features, levels = density_embedding.split([self.geo_feat_dim, self.feature_dim, 1], dim=-1)
        return geometry, features, levels[..., 0].round().long()

    def colour(self, ray_samples: RaySamples, geometry: Float[Tensor, "*bs G"]) -> Float[Tensor, "*bs 3"]:
        """Colour of each sample from its geometry features and view direction (and appearance code)."""
        inputs = [self.direction_encoding(F.normalize(ray_samples.frustums.directions, dim=-1)), geometry]
        if self.appearance is not None:
            codes = (ray_samples.metadata or {}).get(APPEARANCE)
            inputs.append(self.appearance.mean_code().expand(*geometry.shape[:-1], -1) if codes is None else codes)
        return self.color_net(torch.cat(inputs, dim=-1))

    def density_fn(
        self, positions: Float[Tensor, "*bs 3"], times: Optional[Float[Tensor, "*bs 1"]] = None
    ) -> Float[Tensor, "*bs 1"]:
        """Density at world positions and times (nerfstudio's density_fn, with times)."""
        return self.get_density(sample_points(positions, times))[0]

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
    def claim_columns(self, x: Float[Tensor, "N 3"], levels: Int[Tensor, "N"]) -> Bool[Tensor, "G R 3 C"]:
        """Mark the columns of each gear's space-time planes that samples at x (normalised) of that gear level p
        (Eq 5) touch; returns the columns each gear touched for the first time, which must inherit the lower
        gears' (``inherit_columns``) before the gears are evaluated (Eq 6-7).

        Called once per training forward pass, before any gear is evaluated. Under DDP every process claims what
        any process's batch touched (``distributed.union``), so used_columns and the planes stay the same on every
        process (and DDP's buffer broadcast from the first process loses no claim). No host synchronisation.
        """
        touched = torch.zeros_like(self.used_columns)
        for r, resolution in enumerate(self.resolutions):
            for j, axis in enumerate(TIME_PLANE_AXES):
                touched[:, r, j, :resolution] = touched_columns(x[:, axis], resolution, levels - 1, self.num_gears)
        touched = distributed.union(touched)
        new = touched & ~self.used_columns
        self.used_columns |= touched
        return new

    def gear_assignment(self) -> Dict[str, Tensor]:
        """A copy of what a gear update changes: the gear function g (Eq 4) and the claimed columns."""
        state = {f"gear_function.{k}": v.detach().clone() for k, v in self.gear_function.state_dict().items()}
        return {**state, "used_columns": self.used_columns.clone()}

    @torch.no_grad()
    def restore_gear_assignment(self, assignment: Dict[str, Tensor]) -> None:
        """Undo a gear update: g and the claimed columns as ``gear_assignment`` copied them (columns claimed since
        are released; they inherit again when next claimed)."""
        for key, value in self.gear_function.state_dict().items():
            value.copy_(assignment[f"gear_function.{key}"])
        self.used_columns.copy_(assignment["used_columns"])

    @torch.no_grad()
    def inherit_new_columns(self, new: Bool[Tensor, "G R 3 C"], renewed: Optional[List[bool]] = None) -> None:
        """``inherit_columns`` for every gear above the first with newly claimed columns (``claim_columns``'s
        result); ``renewed``: which gears have any, when the caller has already read them on the host."""
        if renewed is None:
            renewed = new.flatten(1).any(dim=1).tolist()
        for gear in range(2, self.num_gears + 1):
            if renewed[gear - 1]:
                self.inherit_columns(gear, new[gear - 1])

    @torch.no_grad()
    def inherit_columns(self, gear: int, columns: Tensor) -> None:
        """An upshift keeps what the region had learned: the given columns (resolution, plane, cell) of k^gear
        become those of the highest lower gear that has used them (gear 1 otherwise), resampled linearly to
        gear's rows (Sec 4.4's temporal resolutions). A region that moves up a gear then renders as before
        the move, and its new rows start from its motion at the lower temporal resolution.

        The lower gears' used columns must already include the current claims (``claim_columns``). Every plane of
        the gear is rewritten (unchanged where no column is given), so that no host synchronisation is needed."""
        for r, target_plane in enumerate(self.time_planes[gear - 1].planes):
            width = target_plane.shape[-1]
            remaining = columns[r, :, :width]
            inherited = target_plane
            for source in range(gear - 1, 0, -1):
                take = remaining if source == 1 else remaining & self.used_columns[source - 1, r, :, :width]
                remaining = remaining & ~take
                resampled = F.interpolate(
                    self.time_planes[source - 1].planes[r], size=target_plane.shape[-2:], mode="bilinear",
                    align_corners=True,
                )
                inherited = torch.where(take[:, None, None, :], resampled, inherited)
            target_plane.copy_(inherited)

    def gears_in_use(self) -> List[bool]:
        """``used_gears`` on the host, without a device sync when ``used_columns`` has not changed since it was
        last read: ``gear_features`` reads it after each training step's claims, in the same sync as its counts
        of samples per gear, so ``regularisers`` gets it for free every step."""
        tensor, version, used = self.used_gears_seen
        if tensor is not self.used_columns or version != self.used_columns._version:
            used = self.used_gears.tolist()
            self.used_gears_seen = (self.used_columns, self.used_columns._version, used)
        return used

    def used_time_planes(self) -> List[Tensor]:
        """Space-time planes k^G of the gears that have had a training sample."""
        used = self.gears_in_use()
        return [plane for gear, triple in enumerate(self.time_planes) if used[gear] for plane in triple.planes]

    def parameters_in_use(self) -> int:
        """Number of parameters that training updates: everything but the planes of unused gears."""
        used = self.gears_in_use()
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
