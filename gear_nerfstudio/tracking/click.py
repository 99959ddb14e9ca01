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
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.model_components.ray_samplers import UniformSampler
from torch import Tensor

from gear_nerfstudio.tracking.projection import project

if TYPE_CHECKING:
    from nerfstudio.models.base_model import Model

HIT_ACCUMULATION = 0.5
"""Default accumulated weight a click ray needs to count as meeting a surface."""
CLICK_SAMPLES = 256
"""Uniform samples along a click ray for its median termination depth."""
PROJECTABLE = (CameraType.PERSPECTIVE.value, CameraType.FISHEYE.value)
"""Camera types a point can be projected into."""


class TrackingError(ValueError):
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


def click_point(
    model: "Model",
    camera: Cameras,
    pixel: Tuple[float, float],
    time: float,
    min_accumulation: float = HIT_ACCUMULATION,
) -> Tensor:
    """The 3D world point (3,) where the ray through `pixel` = (x, y) first meets a surface at `time`.

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
    samples = UniformSampler(num_samples=CLICK_SAMPLES, train_stratified=False)(rays)
    positions = samples.frustums.get_positions()
    with torch.no_grad():
        weights = samples.get_weights(model.field.density_fn(positions, samples.times))[0, :, 0]
    accumulation = float(weights.sum())
    if accumulation < min_accumulation:
        raise TrackingError(
            f"the click at pixel (x={x:g}, y={y:g}), time {time:g} hits nothing: the ray's accumulated "
            f"density is {accumulation:.3f} < {min_accumulation:g} (empty sky or outside the scene)"
        )
    median = int(torch.searchsorted(torch.cumsum(weights, 0), torch.tensor([accumulation / 2], device=weights.device)))
    depth = (samples.frustums.starts[0, median] + samples.frustums.ends[0, median]) / 2
    return (rays.origins[0] + rays.directions[0] * depth).detach().cpu().float()


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
