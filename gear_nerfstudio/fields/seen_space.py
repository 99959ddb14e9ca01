"""The space the training cameras see: where a render may take the field's density.

A radiance field is fitted only along the training rays. A point that no training camera sees was never fitted, and
one that a single camera sees is fixed only along that camera's rays (any depth that explains its pixels will do).
The factorised planes still give such points a density, and at a novel view it shows as near blobs over the scene
(`benchmarks/results/tracking_real.md`, issue 26: the held-out camera of `panoptic`, where those blobs lay in front of
the people). With ``--pipeline.model.render.min-views`` set (off by default: docs/decisions.md says why),
and always in `ns-gear-track` (its `--min-views`, 4 by default), renders keep the density only where at least that
many training cameras see the point: it projects in front of them and inside their images.
"""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Bool, Float, Int
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.field_components.spatial_distortions import SceneContraction, SpatialDistortion
from torch import Tensor

from gear_nerfstudio.projection import project


def distinct_cameras(cameras: Cameras) -> Cameras:
    """The cameras of a flat Cameras with repeats left out (a fixed rig: one per camera, whatever the frames)."""
    flat = cameras.flatten()
    keys = torch.cat(
        [flat.camera_to_worlds.reshape(len(flat), -1), flat.fx.reshape(-1, 1), flat.fy.reshape(-1, 1),
         flat.cx.reshape(-1, 1), flat.cy.reshape(-1, 1), flat.width.reshape(-1, 1).float(),
         flat.height.reshape(-1, 1).float()], dim=-1,
    )  # fmt: skip
    if flat.distortion_params is not None:
        keys = torch.cat([keys, flat.distortion_params.reshape(len(flat), -1)], dim=-1)
    _, inverse = torch.unique(keys, dim=0, return_inverse=True)
    first = torch.full((int(inverse.max()) + 1,), len(flat), dtype=torch.long).scatter_reduce(
        0, inverse, torch.arange(len(flat)), reduce="amin"
    )
    return flat[first.sort().values]


def views_seeing(cameras: Cameras, positions: Float[Tensor, "*bs 3"]) -> Int[Tensor, "*bs"]:
    """How many of the cameras see each world point: it projects in front of them and inside their image."""
    uv, in_front = project(cameras, positions.reshape(-1, 3))
    width, height = cameras.width.reshape(-1, 1).to(uv), cameras.height.reshape(-1, 1).to(uv)
    u, v = uv[..., 0], uv[..., 1]
    return (in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)).sum(dim=0).reshape(positions.shape[:-1])


def world_positions(
    x: Float[Tensor, "*bs 3"], aabb: Float[Tensor, "2 3"], spatial_distortion: Optional[SpatialDistortion]
) -> Float[Tensor, "*bs 3"]:
    """The inverse of `planes.normalize_positions`: world points at plane coordinates x in [-1, 1]^3, for a box
    or a box contracted with nerfstudio's L-inf SceneContraction (|c| <= 1 stays, else c = (2 - 1/|p|) p/|p|)."""
    if spatial_distortion is not None:
        if not isinstance(spatial_distortion, SceneContraction) or spatial_distortion.order != float("inf"):
            raise ValueError(f"no inverse for the spatial distortion {spatial_distortion!r}")
        contracted = 2.0 * x
        norm = contracted.abs().amax(dim=-1, keepdim=True).clamp(max=2.0 - 1e-3)
        x = torch.where(norm <= 1.0, contracted, contracted / norm / (2.0 - norm))
    return aabb[0] + (x + 1.0) / 2.0 * (aabb[1] - aabb[0])


class SeenSpace:
    """Whether points are seen by at least ``min_views`` of the training cameras (`views_seeing`; all of them when
    there are fewer), looked up on a GRID^3 grid over a field's plane coordinates (`planes.normalize_positions`),
    made once from the cells' centres: a render's millions of samples then cost an indexing instead of a
    projection into every camera."""

    GRID = 128
    """Cells per side: a cell is 1/64 of the scene box's side (of the inner box when contracted)."""

    def __init__(
        self,
        cameras: Cameras,
        min_views: int,
        aabb: Float[Tensor, "2 3"],
        spatial_distortion: Optional[SpatialDistortion] = None,
    ) -> None:
        self.cameras = distinct_cameras(cameras)
        self.min_views = min(min_views, len(self.cameras))  # a rig of one camera renders what that camera sees
        steps = (torch.arange(self.GRID, dtype=torch.float32) + 0.5) / self.GRID * 2.0 - 1.0
        centres = torch.stack(torch.meshgrid(steps, steps, steps, indexing="ij"), dim=-1).reshape(-1, 3)
        cameras_here, box = self.cameras.to("cpu"), aabb.detach().cpu().float()
        counts = torch.cat(
            [views_seeing(cameras_here, world_positions(chunk, box, spatial_distortion)) for chunk in centres.split(1 << 16)]
        )
        self.grid = (counts >= self.min_views).reshape(self.GRID, self.GRID, self.GRID)

    def __call__(self, x: Float[Tensor, "N 3"]) -> Bool[Tensor, "N"]:
        """Whether the points at plane coordinates x (N, 3) in [-1, 1] lie in a seen cell."""
        if self.grid.device != x.device:
            self.grid = self.grid.to(x.device)
        cells = ((x + 1.0) / 2.0 * self.GRID).long().clamp(0, self.GRID - 1)
        return self.grid[cells[:, 0], cells[:, 1], cells[:, 2]]
