"""How close recovered cameras come to a known calibration: both as N3D rows (`poses_bounds.npy`), compared after
a similarity alignment (Umeyama). Used by the tests and `benchmarks/process_accuracy.py`."""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

from gear_nerfstudio.data.llff import llff_cameras


def umeyama(source: np.ndarray, target: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimising |s R source + t - target|^2 (Umeyama 1991)."""
    mean_s, mean_t = source.mean(0), target.mean(0)
    covariance = (target - mean_t).T @ (source - mean_s) / len(source)
    u, singular, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u @ vt))
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(singular) @ sign) / ((source - mean_s) ** 2).sum(1).mean()
    return scale, rotation, mean_t - scale * rotation @ mean_s


def pose_errors(recovered: np.ndarray, truth: np.ndarray) -> Dict[str, np.ndarray]:
    """Per camera: centre error (% of the true rig's size) and rotation error (degrees) after a similarity alignment
    of the recovered rig to the true one.

    The similarity is Umeyama's fit of each camera's centre and of two points one rig radius along its viewing and
    down directions: the centres alone leave the rotation about their axis free when they lie near a line or a
    plane (a forward-facing rig).
    """
    rotation, centres = llff_cameras(recovered)
    true_rotation, true_centres = llff_cameras(truth)

    def anchors(rotations: np.ndarray, points: np.ndarray) -> np.ndarray:
        radius = np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean())
        return np.concatenate([points, points + radius * rotations[:, :, 2], points + radius * rotations[:, :, 1]])

    scale, align, shift = umeyama(anchors(rotation, centres), anchors(true_rotation, true_centres))
    aligned = centres @ (scale * align).T + shift
    rig_size = np.linalg.norm(true_centres.max(0) - true_centres.min(0))
    centre = 100 * np.linalg.norm(aligned - true_centres, axis=1) / rig_size
    relative = np.einsum("nji,jk,nkl->nil", true_rotation, align, rotation)
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return {"centre_pct": centre, "rotation_deg": np.degrees(np.arccos(cosine))}
