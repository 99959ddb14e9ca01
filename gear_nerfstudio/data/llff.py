"""Rows of Neural 3D Video's `poses_bounds.npy` (LLFF convention) and cameras in OpenCV axes, both ways.

A row is a 3x5 matrix flattened, then near and far: columns 0-2 are the camera-to-world rotation's [down, right,
back] axes = [y, x, -z] of OpenCV's camera axes, column 3 the centre, column 4 [H, W, focal].
"""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np


def llff_row(c2w: np.ndarray, hwf: Sequence[float], near: float, far: float) -> np.ndarray:
    """One (17,) row from a (3, 4) camera-to-world in OpenCV axes, [H, W, focal] and the bounds."""
    pose = np.stack([c2w[:, 1], c2w[:, 0], -c2w[:, 2], c2w[:, 3], np.asarray(hwf, dtype=float)], axis=1)
    return np.concatenate([pose.reshape(-1), [near, far]])


def llff_cameras(poses_bounds: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Camera-to-world rotations (OpenCV axes) and centres of (N, 17) rows."""
    pose = poses_bounds[:, :15].reshape(-1, 3, 5)
    rotation = np.stack([pose[:, :, 1], pose[:, :, 0], -pose[:, :, 2]], axis=-1)
    return rotation, pose[:, :, 3]
