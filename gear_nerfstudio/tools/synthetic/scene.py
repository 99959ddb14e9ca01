"""A small dynamic scene rendered by exact ray casting, with ground truth.

The scene is a textured back wall and floor (static), a static sphere and spheres that circle at
clearly different speeds. Cameras here use the datasets' native models (OpenCV axes, world-to-camera
rotation, pinhole or the DeepView fisheye theta_d = theta (1 + k1 theta^2 + k2 theta^4)); this code is
deliberately independent of the dataparsers so that tests can check one against the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple

import numpy as np

MotionKind = Literal["mixed", "static", "slow", "fast"]

WALL_Z = -4.5
FLOOR_Y = -1.0
SKY_RGB = np.array([0.62, 0.74, 0.90])
LIGHT_DIR = np.array([0.35, 0.8, 0.5]) / np.linalg.norm([0.35, 0.8, 0.5])


@dataclass(frozen=True)
class Sphere:
    """A striped sphere whose centre circles in the x-y plane (orbit_radius 0: static)."""

    object_id: int
    name: str
    radius: float
    orbit_centre: Tuple[float, float, float]
    orbit_radius: float
    frames_per_turn: float
    colour_a: Tuple[float, float, float]
    colour_b: Tuple[float, float, float]

    def centre(self, frame: float) -> np.ndarray:
        angle = 2.0 * math.pi * frame / self.frames_per_turn
        offset = self.orbit_radius * np.array([math.cos(angle), math.sin(angle), 0.0])
        return np.asarray(self.orbit_centre, dtype=np.float64) + offset

    @property
    def speed(self) -> float:
        """World units travelled per frame."""
        return 2.0 * math.pi * self.orbit_radius / self.frames_per_turn


def scene_objects(motion: MotionKind = "mixed") -> List[Sphere]:
    """The objects of a scene: 'mixed' has a static, a slow and a fast sphere; the others one kind."""
    static = Sphere(1, "static", 0.38, (-0.85, -0.55, -3.1), 0.0, 1.0, (0.85, 0.75, 0.2), (0.55, 0.3, 0.1))
    slow = Sphere(2, "slow", 0.32, (0.05, 0.35, -2.9), 0.12, 64.0, (0.2, 0.75, 0.3), (0.05, 0.35, 0.15))
    fast = Sphere(3, "fast", 0.28, (0.75, -0.25, -2.6), 0.45, 10.0, (0.9, 0.2, 0.25), (0.35, 0.05, 0.5))
    if motion == "mixed":
        return [static, slow, fast]
    if motion == "static":
        return [static]
    if motion == "slow":
        return [static, slow]
    if motion == "fast":
        return [static, fast]
    raise ValueError(f"unknown motion kind {motion!r}")


@dataclass(frozen=True)
class RigCamera:
    """A camera in the datasets' native convention: OpenCV axes, world-to-camera rotation."""

    name: str
    rotation: np.ndarray  # (3, 3) world-to-camera, rows: right, down, forward
    centre: np.ndarray  # (3,) camera centre in world coordinates
    fx: float
    fy: float
    cx: float  # principal point; pixel (i, j) covers [i, i+1) x [j, j+1)
    cy: float
    width: int
    height: int
    fisheye: Optional[Tuple[float, float]] = None  # (k1, k2)

    @property
    def translation(self) -> np.ndarray:
        """t of x_cam = R x_world + t."""
        return -self.rotation @ self.centre

    def project(self, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) of world points (N, 3) and whether each is in front of the camera."""
        cam = (points - self.centre) @ self.rotation.T
        x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
        if self.fisheye is None:
            a, b = x / z, y / z
            in_front = z > 0
        else:
            k1, k2 = self.fisheye
            r = np.hypot(x, y)
            theta = np.arctan2(r, z)
            theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4)
            scale = np.where(r > 0, theta_d / np.maximum(r, 1e-300), 1.0 / np.maximum(z, 1e-300))
            a, b = x * scale, y * scale
            in_front = theta < math.pi / 2
        return np.stack([self.fx * a + self.cx, self.fy * b + self.cy], axis=-1), in_front

    def rays(self, uv: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """World-space origins and unit directions of rays through pixel coordinates uv (N, 2)."""
        a = (uv[:, 0] - self.cx) / self.fx
        b = (uv[:, 1] - self.cy) / self.fy
        if self.fisheye is None:
            cam = np.stack([a, b, np.ones_like(a)], axis=-1)
        else:
            theta_d = np.hypot(a, b)
            theta = _invert_fisheye(theta_d, *self.fisheye)
            sin_over = np.where(theta_d > 0, np.sin(theta) / np.maximum(theta_d, 1e-300), 1.0)
            cam = np.stack([a * sin_over, b * sin_over, np.cos(theta)], axis=-1)
        dirs = cam @ self.rotation
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        return np.broadcast_to(self.centre, dirs.shape).copy(), dirs


def _invert_fisheye(theta_d: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """Solve theta_d = theta (1 + k1 theta^2 + k2 theta^4) for theta by Newton's method."""
    theta = theta_d.copy()
    for _ in range(30):
        f = theta * (1 + k1 * theta**2 + k2 * theta**4) - theta_d
        df = 1 + 3 * k1 * theta**2 + 5 * k2 * theta**4
        theta = theta - f / df
    return theta


def look_at(centre: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera rotation (OpenCV axes) of a camera at centre looking at target."""
    forward = target - centre
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


@dataclass(frozen=True)
class Render:
    """One rendered view: colour and per-pixel ground truth."""

    rgb: np.ndarray  # (H, W, 3) uint8
    object_ids: np.ndarray  # (H, W) uint8, 0 = static background (wall, floor, sky)
    motion: np.ndarray  # (H, W) float32, speed of the visible surface in world units per frame
    depth: np.ndarray  # (H, W) float32, distance along the ray (inf for sky)


@dataclass
class SyntheticScene:
    """Scene content plus a rendering function; deterministic for the same arguments."""

    motion: MotionKind = "mixed"
    supersample: int = 2
    objects: List[Sphere] = field(init=False)

    def __post_init__(self) -> None:
        self.objects = scene_objects(self.motion)

    def object_speeds(self) -> Dict[int, float]:
        return {obj.object_id: obj.speed for obj in self.objects}

    def render(self, camera: RigCamera, frame: int) -> Render:
        """Ray-cast one view at one frame; colour is averaged over supersample^2 rays per pixel."""
        jj, ii = np.mgrid[0 : camera.height, 0 : camera.width]
        centres = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], axis=-1).astype(np.float64)
        colour, ids, motion, depth = self._cast(camera, centres, frame)
        if self.supersample > 1:
            s = self.supersample
            offsets = (np.arange(s) + 0.5) / s - 0.5
            total = np.zeros_like(colour)
            for dy in offsets:
                for dx in offsets:
                    total += self._cast(camera, centres + np.array([dx, dy]), frame)[0]
            colour = total / (s * s)
        shape = (camera.height, camera.width)
        rgb = np.clip(np.round(colour * 255.0), 0, 255).astype(np.uint8).reshape(*shape, 3)
        return Render(
            rgb=rgb,
            object_ids=ids.reshape(shape).astype(np.uint8),
            motion=motion.reshape(shape).astype(np.float32),
            depth=depth.reshape(shape).astype(np.float32),
        )

    def _cast(self, camera: RigCamera, uv: np.ndarray, frame: int):
        origins, dirs = camera.rays(uv)
        n = len(origins)
        best_t = np.full(n, np.inf)
        colour = np.broadcast_to(SKY_RGB, (n, 3)).copy()
        ids = np.zeros(n, dtype=np.int64)
        motion = np.zeros(n)

        # Back wall z = WALL_Z and floor y = FLOOR_Y.
        for axis, level in ((2, WALL_Z), (1, FLOOR_Y)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (level - origins[:, axis]) / dirs[:, axis]
            hit = np.isfinite(t) & (t > 1e-6) & (t < best_t)
            points = origins[hit] + t[hit, None] * dirs[hit]
            normal = np.zeros(3)
            normal[axis] = 1.0  # the wall faces +z, the floor +y
            colour[hit] = _wall_texture(points) if axis == 2 else _floor_texture(points)
            colour[hit] *= 0.45 + 0.55 * max(float(normal @ LIGHT_DIR), 0.0)
            best_t[hit] = t[hit]
            ids[hit] = 0
            motion[hit] = 0.0

        for obj in self.objects:
            centre = obj.centre(frame)
            oc = origins - centre
            b = np.einsum("ij,ij->i", oc, dirs)
            c = np.einsum("ij,ij->i", oc, oc) - obj.radius**2
            disc = b * b - c
            valid = disc >= 0
            t = np.full(n, np.inf)
            t[valid] = -b[valid] - np.sqrt(disc[valid])
            hit = valid & (t > 1e-6) & (t < best_t)
            local = origins[hit] + t[hit, None] * dirs[hit] - centre
            normal = local / obj.radius
            stripes = 0.5 + 0.5 * np.sin(9.0 * (local @ np.array([1.0, 0.7, 0.4])) / obj.radius)
            base = np.outer(stripes, obj.colour_a) + np.outer(1 - stripes, obj.colour_b)
            colour[hit] = base * (0.35 + 0.65 * np.clip(normal @ LIGHT_DIR, 0.0, None))[:, None]
            best_t[hit] = t[hit]
            ids[hit] = obj.object_id
            motion[hit] = obj.speed
        return colour, ids, motion, best_t


def _wall_texture(points: np.ndarray) -> np.ndarray:
    checker = (np.floor(points[:, 0] / 0.45) + np.floor(points[:, 1] / 0.45)) % 2
    hue = 0.5 + 0.5 * np.sin(0.9 * points[:, 0])
    dark = np.stack([0.25 + 0.2 * hue, 0.3 * np.ones_like(hue), 0.45 - 0.2 * hue], axis=-1)
    light = np.stack([0.75 * np.ones_like(hue), 0.7 + 0.15 * hue, 0.6 * np.ones_like(hue)], axis=-1)
    return np.where(checker[:, None] > 0.5, light, dark)


def _floor_texture(points: np.ndarray) -> np.ndarray:
    checker = (np.floor(points[:, 0] / 0.6) + np.floor(points[:, 2] / 0.6)) % 2
    return np.where(checker[:, None] > 0.5, np.array([0.55, 0.5, 0.45]), np.array([0.3, 0.22, 0.18]))
