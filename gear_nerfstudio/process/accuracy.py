"""How far one calibration of a rig lies from another (a known one, or the self-check's second calibration), after
a similarity alignment (Umeyama). Used by the self-check, the tests and `benchmarks/process_accuracy.py`."""

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
    of the recovered rig (N3D rows) to the true one (`rig_differences`, every camera in the fit)."""
    return rig_differences(*llff_cameras(recovered), *llff_cameras(truth))


def rig_differences(
    rotation: np.ndarray, centres: np.ndarray, reference_rotation: np.ndarray, reference_centres: np.ndarray,
    trimmed: bool = False,
) -> Dict[str, np.ndarray]:
    """Per camera: how far its centre lies from the reference's (% of the reference rig's size) and how far it is
    turned (degrees), after a similarity alignment of the rig (camera-to-world rotations, OpenCV axes, and centres)
    to the reference.

    The similarity is Umeyama's fit of each camera's centre and of two points one rig radius along its viewing and
    down directions: the centres alone leave the rotation about their axis free when they lie near a line or a
    plane (a forward-facing rig). `trimmed` fits again without the cameras whose centres lie more than 3 times the
    median distance off, so that a few cameras far off do not make all read as off.
    """

    def anchors(rotations: np.ndarray, points: np.ndarray) -> np.ndarray:
        radius = np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean())
        return np.concatenate([points, points + radius * rotations[:, :, 2], points + radius * rotations[:, :, 1]])

    def fit(keep: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
        return umeyama(anchors(rotation[keep], centres[keep]), anchors(reference_rotation[keep], reference_centres[keep]))

    scale, align, shift = fit(np.ones(len(centres), dtype=bool))
    if trimmed:
        distance = np.linalg.norm(centres @ (scale * align).T + shift - reference_centres, axis=1)
        scale, align, shift = fit(distance <= 3 * np.median(distance))
    aligned = centres @ (scale * align).T + shift
    rig_size = np.linalg.norm(reference_centres.max(0) - reference_centres.min(0))
    centre = 100 * np.linalg.norm(aligned - reference_centres, axis=1) / rig_size
    relative = np.einsum("nji,jk,nkl->nil", reference_rotation, align, rotation)
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return {"centre_pct": centre, "rotation_deg": np.degrees(np.arccos(cosine))}
