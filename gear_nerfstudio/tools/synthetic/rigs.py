"""Camera rigs shaped like the three datasets' rigs, in their native camera models."""

from __future__ import annotations

import math
from typing import List

import numpy as np

from gear_nerfstudio.tools.synthetic.scene import RigCamera, look_at

SCENE_TARGET = np.array([0.0, -0.1, -3.0])


def technicolor_rig(rows: int, cols: int, width: int, height: int) -> List[RigCamera]:
    """A planar rows x cols grid of pinhole cameras (row-major order), like the Technicolor 4x4 rig.

    Intrinsics differ a little per camera (off-centre principal point, pixel aspect ratio != 1) so that
    a parser that mixes up fx/fy or cu/cv fails the tests.
    """
    cameras = []
    spacing = 0.14
    for row in range(rows):
        for col in range(cols):
            index = row * cols + col
            centre = np.array([(col - (cols - 1) / 2) * spacing, ((rows - 1) / 2 - row) * spacing, 0.0])
            f = 0.95 * width * (1.0 + 0.01 * (index % 3))
            aspect = 1.0 + 0.2 * ((index % 2) - 0.5)
            cameras.append(
                RigCamera(
                    name=f"{index:02d}",
                    rotation=look_at(centre, SCENE_TARGET),
                    centre=centre,
                    fx=f,
                    fy=f * aspect,
                    cx=width / 2 + 0.7 * ((index % 4) - 1.5),
                    cy=height / 2 - 0.5 * ((index % 3) - 1),
                    width=width,
                    height=height,
                )
            )
    return cameras


def n3d_rig(count: int, width: int, height: int) -> List[RigCamera]:
    """Pinhole cameras on a horizontal arc facing the scene; cam00 is the central one.

    N3D's poses_bounds.npy stores one focal and puts the principal point at the image centre.
    """
    cameras = []
    focal = 0.9 * width
    for index in range(count):
        # 0, +1, -1, +2, -2, ... steps from the centre of the arc.
        step = (index + 1) // 2 * (1 if index % 2 else -1)
        angle = math.radians(7.0 * step)
        centre = SCENE_TARGET + 3.0 * np.array([math.sin(angle), 0.0, math.cos(angle)])
        centre[1] += 0.05 * ((index % 3) - 1)
        cameras.append(
            RigCamera(
                name=f"cam{index:02d}",
                rotation=look_at(centre, SCENE_TARGET),
                centre=centre,
                fx=focal,
                fy=focal,
                cx=width / 2,
                cy=height / 2,
                width=width,
                height=height,
            )
        )
    return cameras


def immersive_rig(count: int, width: int, height: int) -> List[RigCamera]:
    """Outward-looking fisheye cameras on a spherical cap, like the DeepView rig; camera_0001 central."""
    k1, k2 = 0.08, -0.01
    theta_edge = math.radians(65.0)
    focal = (width / 2) / (theta_edge * (1 + k1 * theta_edge**2 + k2 * theta_edge**4))
    cameras = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for index in range(count):
        # Spread viewing directions within 30 degrees of -z on a sunflower pattern; index 0 is central.
        polar = math.radians(30.0) * math.sqrt(index / max(count - 1, 1))
        azimuth = golden * index
        direction = np.array(
            [math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth), -math.cos(polar)]
        )
        centre = 0.4 * direction + np.array([0.0, 0.0, -0.4])
        up = (0.0, 1.0, 0.0)
        cameras.append(
            RigCamera(
                name=f"camera_{index + 1:04d}",
                rotation=look_at(centre, centre + direction, up),
                centre=centre,
                fx=focal,
                fy=focal,
                cx=width / 2 + 0.3,
                cy=height / 2 - 0.2,
                width=width,
                height=height,
                fisheye=(k1, k2),
            )
        )
    return cameras
