"""A picture of the recovered rig, to check it before training: camera centres, viewing directions, sparse points."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def plot_rig(
    path: Path, c2w: np.ndarray, names: Sequence[str], points: np.ndarray, colors: np.ndarray, doubtful: Sequence[bool]
) -> None:
    """Save a PNG with two views of the rig: in 3D, and from above (along the cameras' mean up direction).

    `c2w` is (N, 3, 4) camera-to-world in OpenCV axes; the first camera (the held-out one) is drawn in red, the
    doubtful ones in orange with a question mark.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres, forward = c2w[:, :, 3], c2w[:, :, 2]
    size = float(np.linalg.norm(centres.max(0) - centres.min(0))) or 1.0
    keep = np.random.default_rng(0).permutation(len(points))[:5000]
    points, colors = points[keep], colors[keep] / 255.0
    # The view holds the cameras and the middle 90 % of the points (far outliers would shrink the rig to a dot).
    extent = np.concatenate([centres, np.percentile(points, [5, 95], axis=0)]) if len(points) else centres
    middle = (extent.max(0) + extent.min(0)) / 2
    half = 0.6 * float((extent.max(0) - extent.min(0)).max()) or 1.0
    inside = (np.abs(points - middle) <= half).all(axis=1)
    points, colors = points[inside], colors[inside]
    # "above": the axis along the mean camera up (-y in OpenCV), then two axes across it.
    up = -c2w[:, :, 1].mean(0)
    up /= np.linalg.norm(up)
    across = np.linalg.svd(np.eye(3) - np.outer(up, up))[0][:, :2]

    figure = plt.figure(figsize=(13, 6))
    axes3d = figure.add_subplot(1, 2, 1, projection="3d")
    axes2d = figure.add_subplot(1, 2, 2)
    arrow = 0.15 * size
    colour = ["orange" if doubt else "red" if i == 0 else "blue" for i, doubt in enumerate(doubtful)]
    names = [f"{name}?" if doubt else name for name, doubt in zip(names, doubtful)]
    axes3d.scatter(*points.T, c=colors, s=1)
    axes3d.scatter(*centres.T, c=colour, s=20)
    axes3d.quiver(*centres.T, *(forward * arrow).T, color=colour)
    flat_points, flat_centres, flat_forward = points @ across, centres @ across, forward @ across
    axes2d.scatter(*flat_points.T, c=colors, s=1)
    axes2d.scatter(*flat_centres.T, c=colour, s=20)
    axes2d.quiver(*flat_centres.T, *(flat_forward * arrow).T, color=colour, angles="xy", scale_units="xy", scale=1)
    for name, centre, flat in zip(names, centres, flat_centres):
        axes3d.text(*centre, name, fontsize=7)
        axes2d.annotate(name, flat, fontsize=7)
    axes3d.set(xlim=(middle[0] - half, middle[0] + half), ylim=(middle[1] - half, middle[1] + half),
               zlim=(middle[2] - half, middle[2] + half))
    axes3d.set_title("cameras (held-out: red, doubtful: orange), views, sparse points")
    axes2d.set_title("seen from above (along the cameras' mean up)")
    axes2d.set_aspect("equal", adjustable="datalim")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
