"""Click geometry of free-viewpoint tracking (Gear-NeRF Sec 4.5): the 3D point under a click, and its pixel in
another view.

The ray through a clicked pixel is traced and its *median termination depth* gives the 3D point where it first
meets a surface: the ray is sampled densely (CLICK_SAMPLES uniform samples between the model's near and far
planes) and the field's densities give the volume-rendering weights w_i (Eq 1); the depth is the first sample
at which the accumulated weight sum_{j<=i} w_j reaches half the ray's accumulation A = sum_i w_i. Unlike the
expected depth sum_i w_i t_i / A, it does not average a foreground edge with the background behind it, so it
lies on the first surface the ray meets. A ray whose accumulation A stays below `min_accumulation` (default
0.5: it more likely ends nowhere than on a surface; "empty sky", or a ray leaving the scene box) hits nothing.

Every failure a user can cause (time outside [0, 1], a pixel outside the image, a click on nothing, a point
behind or outside a target view) raises `TrackingError` with a message that says which.

A click can also succeed and still miss the object the user meant; `check_click` says so, from the mask that
the clicks give in the clicked view, the depth of that view on SAM's grid (`view_depth`: every cell's ray
traced as a click's is) and the click rays (`ClickHit`). Two warnings:
- the mask covers most of the view: more than MOST_OF_VIEW = half of the image. Such a mask is larger than
  everything else in the view together: what the view mostly shows (wall, floor, sky, or the whole frame
  when the segmenter found no boundary), rarely the one object a user points at;
- the click seems to have hit the background, when any of these holds:
  - the mask is not in front of what surrounds it: less than IN_FRONT = a third of its edge is an occluding
    edge (`occlusion.in_front_share`: beyond the edge the view's depth is further, by more than EDGE_JUMP =
    10 % in inverse depth, than the surface inside would be if it went on). An object is seen against what
    lies behind it, so its silhouette is an occluding edge almost all round (except where it rests on
    something or is itself partly hidden); a piece of wall or floor goes on into its surroundings, or lies
    behind objects, so almost none of its edge is. 10 % is a jump that a continuous surface does not make
    between neighbouring cells once its own slope is continued; a third, not a half, leaves room for masks
    that leak into the background. On the demo scene's trained model (cam01, time 0.4, a click every 3
    pixels) the masks that are a sphere keep 77-100 % of their edge occluding, pieces of wall and floor
    at most 35 %;
  - the mask touches more than MOST_OF_BORDER = half of the image border: the background surrounds the
    objects in front of it, so it runs along the frame; an object cut by the frame reaches one or two sides;
  - a positive click's median depth lies past FAR_BOUND = 95 % of its ray's [near, far] range: the ray
    crossed the whole scene volume, it ends at the far end of the scene (sky, the far bound);
  - on a synthetic scene with ground truth, the clicked pixel shows no object (a fact, not a guess).
The first three depend on no scene, segmenter or camera model: they only use the mask, the view's depth,
the ray's own bounds and the image's border. They are warnings: tracking still runs and writes everything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.model_components.ray_samplers import UniformSampler
from torch import Tensor

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.projection import project
from gear_nerfstudio.sam.occlusion import in_front_share

if TYPE_CHECKING:
    from nerfstudio.models.base_model import Model

HIT_ACCUMULATION = 0.5
"""Default accumulated weight a click ray needs to count as meeting a surface."""
CLICK_SAMPLES = 256
"""Uniform samples along a click ray for its median termination depth."""
DEPTH_CHUNK = 1024
"""Rays traced at once by `view_depth`."""
PROJECTABLE = (CameraType.PERSPECTIVE.value, CameraType.FISHEYE.value)
"""Camera types a point can be projected into."""
MOST_OF_VIEW = 0.5
"""A mask covering more than this share of its image covers most of the view (more than the rest of it)."""
MOST_OF_BORDER = 0.5
"""A clicked-view mask touching more than this share of the image's border pixels is likely the background."""
FAR_BOUND = 0.95
"""A click whose median depth lies past this share of its ray's [near, far] range ends at the far bound."""
IN_FRONT = 1.0 / 3.0
"""A mask in front of its surroundings along less than this share of its edge is likely the background."""


class TrackingError(InputError):
    """A click, camera or time that tracking cannot use; the message says which and why."""


def check_time(time: float, what: str = "time") -> float:
    """Times are in [0, 1] (frame index / (T - 1)); anything else is a TrackingError."""
    if not isinstance(time, (int, float)) or not math.isfinite(time) or not 0.0 <= time <= 1.0:
        raise TrackingError(f"{what} {time} is outside [0, 1] (times are frame index / (frames - 1))")
    return float(time)


def single_camera(camera: Cameras, time: Optional[float] = None) -> Cameras:
    """A flat Cameras of one camera, with `time` as its time when given."""
    if camera.size != 1:
        raise TrackingError(f"expected a single camera, got a Cameras of shape {tuple(camera.shape)}")
    flat = camera.flatten()
    times = flat.times if time is None else torch.full((1, 1), float(time), device=flat.device)
    return Cameras(
        camera_to_worlds=flat.camera_to_worlds,
        fx=flat.fx,
        fy=flat.fy,
        cx=flat.cx,
        cy=flat.cy,
        width=flat.width,
        height=flat.height,
        distortion_params=flat.distortion_params,
        camera_type=flat.camera_type,
        times=times,
    )


def image_size(camera: Cameras) -> Tuple[int, int]:
    """(H, W) of a single camera."""
    return int(camera.height.reshape(-1)[0]), int(camera.width.reshape(-1)[0])


@dataclass
class ClickHit:
    """Where a click ray first meets a surface: the 3D point and the ray's own numbers."""

    point: Tensor  # (3,) world point
    depth: float  # median termination depth along the (unit) ray direction
    near: float  # the ray's bounds after the model's collider
    far: float
    accumulation: float  # the ray's accumulated weight, in [0, 1]

    @property
    def depth_share(self) -> float:
        """Where the depth lies between the ray's near (0) and far (1) bounds."""
        return (self.depth - self.near) / max(self.far - self.near, 1e-12)

    @property
    def at_far_bound(self) -> bool:
        """Whether the ray ends in the last part of its range (see FAR_BOUND): the far end of the scene."""
        return self.depth_share > FAR_BOUND


def click_point(
    model: "Model",
    camera: Cameras,
    pixel: Tuple[float, float],
    time: float,
    min_accumulation: float = HIT_ACCUMULATION,
) -> Tensor:
    """The 3D world point (3,) where the ray through `pixel` = (x, y) first meets a surface at `time`
    (`trace_click`'s point)."""
    return trace_click(model, camera, pixel, time, min_accumulation).point


def trace_click(
    model: "Model",
    camera: Cameras,
    pixel: Tuple[float, float],
    time: float,
    min_accumulation: float = HIT_ACCUMULATION,
) -> ClickHit:
    """Where the ray through `pixel` = (x, y) first meets a surface at `time`.

    Sec 4.5: trace the ray and take its median termination depth (see the module docstring). Raises
    TrackingError for a time outside [0, 1], a pixel outside the image, or a ray whose accumulation
    stays below `min_accumulation` (it hits nothing).
    """
    time = check_time(time, "click time")
    height, width = image_size(camera)
    x, y = float(pixel[0]), float(pixel[1])
    if not (math.isfinite(x) and math.isfinite(y) and 0.0 <= x < width and 0.0 <= y < height):
        raise TrackingError(f"click pixel (x={x:g}, y={y:g}) is outside the {width}x{height} image")
    camera = single_camera(camera, time).to(model.device)
    rays = model.collider(camera.generate_rays(camera_indices=0, coords=torch.tensor([[y, x]], device=model.device)))
    depths, accumulations = _terminations(model, rays)
    accumulation = float(accumulations[0])
    if accumulation < min_accumulation:
        raise TrackingError(
            f"the click at pixel (x={x:g}, y={y:g}), time {time:g} hits nothing: the ray's accumulated "
            f"density is {accumulation:.3f} < {min_accumulation:g} (empty sky or outside the scene)"
        )
    return ClickHit(
        point=(rays.origins[0] + rays.directions[0] * depths[0]).detach().cpu().float(),
        depth=float(depths[0]),
        near=float(rays.nears.reshape(-1)[0]),
        far=float(rays.fars.reshape(-1)[0]),
        accumulation=accumulation,
    )


def _terminations(model: "Model", rays) -> Tuple[Tensor, Tensor]:
    """Median termination depths (N,) and accumulations (N,) of N rays that went through the model's collider."""
    samples = UniformSampler(num_samples=CLICK_SAMPLES, train_stratified=False)(rays)
    with torch.no_grad():
        weights = samples.get_weights(model.field.density_fn(samples.frustums.get_positions(), samples.times))[..., 0]
    accumulations = weights.sum(dim=-1)
    median = torch.searchsorted(torch.cumsum(weights, dim=-1), accumulations[:, None] / 2).clamp(max=CLICK_SAMPLES - 1)
    middles = (samples.frustums.starts[..., 0] + samples.frustums.ends[..., 0]) / 2
    return torch.gather(middles, 1, median)[:, 0], accumulations


def view_depth(model: "Model", camera: Cameras, time: float, pixels: Tensor) -> np.ndarray:
    """Median termination depths (...) of the rays through pixel coordinates (..., 2) = (x, y) of a single
    camera at a time, traced as a click is (CLICK_SAMPLES uniform samples): the depth map `in_front_share`
    reads. Unlike the model's own depth output, it is not rounded to the few samples a render uses."""
    camera = single_camera(camera, check_time(time)).to(model.device)
    depths = []
    for chunk in pixels.reshape(-1, 2).split(DEPTH_CHUNK):
        rays = model.collider(camera.generate_rays(camera_indices=0, coords=chunk[:, [1, 0]].to(model.device)))
        depths.append(_terminations(model, rays)[0].cpu())
    return torch.cat(depths).reshape(pixels.shape[:-1]).float().numpy()


def project_prompt(camera: Cameras, point: Tensor) -> Tuple[float, float]:
    """Pixel (x, y) of a world point in a single pinhole or fisheye camera.

    Raises TrackingError when the camera cannot be projected into (equirectangular and the like), the
    point is behind it, or it falls outside the image.
    """
    camera = single_camera(camera)
    if int(camera.camera_type.reshape(-1)[0]) not in PROJECTABLE:
        raise TrackingError(
            f"cannot project into a {CameraType(int(camera.camera_type.reshape(-1)[0])).name.lower()} camera; "
            "tracking supports perspective and fisheye targets"
        )
    point = torch.as_tensor(point, dtype=torch.float32).reshape(1, 3)
    uv, in_front = project(camera.to("cpu"), point)
    coordinates = ", ".join(f"{v:.3f}" for v in point[0].tolist())
    if not bool(in_front[0, 0]):
        raise TrackingError(f"the clicked point ({coordinates}) is behind the camera")
    x, y = (float(v) for v in uv[0, 0])
    height, width = image_size(camera)
    if not (math.isfinite(x) and math.isfinite(y) and 0.0 <= x < width and 0.0 <= y < height):
        raise TrackingError(
            f"the clicked point ({coordinates}) projects to pixel (x={x:.1f}, y={y:.1f}), outside the "
            f"{width}x{height} image"
        )
    return x, y


def view_share(mask: np.ndarray) -> float:
    """Share of the image's pixels inside a mask (H, W)."""
    return float(np.count_nonzero(mask)) / max(mask.size, 1)


def border_share(mask: np.ndarray) -> float:
    """Share of the image's border pixels (its outermost rows and columns) inside a mask (H, W)."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape[0] <= 2 or mask.shape[1] <= 2:
        return view_share(mask)
    border = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(np.count_nonzero(border)) / border.size


def check_click(
    view: str,
    time: float,
    mask: np.ndarray,
    cells: np.ndarray,
    depth: np.ndarray,
    pixels: Sequence[Tuple[float, float]],
    labels: Sequence[int],
    hits: Sequence[ClickHit],
    truth_background: Optional[bool] = None,
) -> Tuple[Dict[str, Any], List[str]]:
    """The numbers and warning lines (see the module docstring) of the clicks' mask in the clicked view.

    `mask` (H, W) is the decoder's mask for the clicks, `cells` (rows, cols) the same mask on the grid of
    the rendered `depth` (rows, cols); `truth_background` whether the ground truth shows no object at the
    first positive click (None without ground truth).
    """
    numbers: Dict[str, Any] = {
        "mask_share": view_share(mask),
        "mask_border_share": border_share(mask),
        "mask_in_front_share": in_front_share(cells, depth),
    }
    where = f"the mask at the clicked view {view} (time {time:g})"
    warnings = []
    if numbers["mask_share"] > MOST_OF_VIEW:
        warnings.append(
            f"{where} covers {100 * numbers['mask_share']:.0f}% of the image (more than half): it is more likely "
            "the background or the whole frame than one object; click inside the object, or add --negative "
            "clicks on what is not it"
        )
    reasons = []
    front = numbers["mask_in_front_share"]
    if front is not None and front < IN_FRONT:
        reasons.append(
            f"{where} is in front of its surroundings along {100 * front:.0f}% of its edge (an object's along "
            "most of it)"
        )
    if numbers["mask_border_share"] > MOST_OF_BORDER:
        reasons.append(
            f"{where} touches {100 * numbers['mask_border_share']:.0f}% of the image border (an object's less "
            "than half)"
        )
    for (x, y), label, hit in zip(pixels, labels, hits):
        if label and hit.at_far_bound:
            reasons.append(
                f"the ray of the click at (x={x:g}, y={y:g}) ends at its far bound (depth {hit.depth:.3g}, "
                f"{100 * hit.depth_share:.0f}% of the way from near {hit.near:.3g} to far {hit.far:.3g})"
            )
    if truth_background:
        reasons.append("the scene's ground truth shows no object at the clicked pixel")
    if reasons:
        warnings.append("the click seems to have hit the background: " + "; ".join(reasons))
    numbers["background"] = bool(reasons)
    return numbers, warnings
