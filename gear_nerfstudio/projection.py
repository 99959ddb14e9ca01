"""Project world points into nerfstudio cameras (pinhole and fisheye), the inverse of ray generation.

nerfstudio generates a ray at pixel coordinates (u, v) by undistorting ((u - cx)/fx, (v - cy)/fy) with
d(rho) = 1 + k1 rho + k2 rho^2 + k3 rho^3 + k4 rho^4 (rho = a^2 + b^2) and tangential p1, p2; for
FISHEYE the undistorted (a, b) is theta (cos phi, sin phi). This module applies the same model
forwards, so a point projects to the pixel whose ray passes through it.
"""

from __future__ import annotations

from typing import Tuple

import torch
from jaxtyping import Bool, Float
from nerfstudio.cameras.cameras import Cameras, CameraType
from torch import Tensor


def project(cameras: Cameras, points: Float[Tensor, "N 3"]) -> Tuple[Float[Tensor, "C N 2"], Bool[Tensor, "C N"]]:
    """Pixel coordinates of world points in each camera of a flat Cameras, and whether they are in front."""
    c2w = cameras.camera_to_worlds  # (C, 3, 4)
    rotation, centre = c2w[:, :, :3], c2w[:, :, 3]
    local = torch.einsum("cij,cnj->cni", rotation.transpose(1, 2), points[None] - centre[:, None])
    x, y, z = local[..., 0], -local[..., 1], -local[..., 2]  # OpenGL -> OpenCV axes
    fisheye = (cameras.camera_type == CameraType.FISHEYE.value).reshape(-1, 1)
    r = torch.sqrt(x * x + y * y)
    theta = torch.atan2(r, z)
    safe_r = torch.where(r > 0, r, torch.ones_like(r))
    fisheye_scale = torch.where(r > 0, theta / safe_r, 1.0 / z.clamp_min(1e-12))
    pinhole_scale = 1.0 / torch.where(z > 0, z, torch.ones_like(z))
    scale = torch.where(fisheye, fisheye_scale, pinhole_scale)
    a, b = x * scale, y * scale
    if cameras.distortion_params is not None:
        a, b = _distort(a, b, cameras.distortion_params.reshape(-1, 6)[:, None, :])
    u = cameras.fx.reshape(-1, 1) * a + cameras.cx.reshape(-1, 1)
    v = cameras.fy.reshape(-1, 1) * b + cameras.cy.reshape(-1, 1)
    in_front = torch.where(fisheye, theta < torch.pi / 2 + 1e-6, z > 0)
    return torch.stack([u, v], dim=-1), in_front


def _distort(a: Tensor, b: Tensor, params: Tensor) -> Tuple[Tensor, Tensor]:
    k1, k2, k3, k4, p1, p2 = params.unbind(-1)
    rho = a * a + b * b
    d = 1.0 + rho * (k1 + rho * (k2 + rho * (k3 + rho * k4)))
    return (
        a * d + 2 * p1 * a * b + p2 * (rho + 2 * a * a),
        b * d + 2 * p2 * a * b + p1 * (rho + 2 * b * b),
    )
