"""The calibration's self-check, without the truth: a fixed rig's camera does not move between instants. The rig is
calibrated again from other instants (and other COLMAP seeds), CHECKS times; each check is aligned to the first
calibration, and a camera is doubtful when every check disagrees with it: does not register it, places it elsewhere or
turns it (thresholds chosen in benchmarks/results/process_windows.md). One check alone cannot tell which of two
calibrations is off. The focal length each check gives is reported beside."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import numpy as np

from gear_nerfstudio.process.accuracy import rig_differences
from gear_nerfstudio.process.calibrate import Calibration, registered
from gear_nerfstudio.process.write import camera_to_world

CHECKS = 2
"""How many times the rig is calibrated again."""
MOVED_PCT = 1.6
"""A check disagrees with a camera when it places its centre farther than this (% of the rig's size) from the first
calibration,"""
TURNED_DEG = 1.0
"""or turns it by more than this (degrees)."""


@dataclass
class Comparison:
    """One check against the first calibration, for one camera; None where the check did not register it."""

    moved_pct: Optional[float]
    turned_deg: Optional[float]
    focal_change_pct: Optional[float]

    def disagrees(self) -> bool:
        return self.moved_pct is None or self.moved_pct > MOVED_PCT or self.turned_deg > TURNED_DEG

    def __str__(self) -> str:
        if self.moved_pct is None:
            return "not registered"
        return f"moved {self.moved_pct:.1f} %, turned {self.turned_deg:.1f} deg, focal {self.focal_change_pct:+.1f} %"


@dataclass
class Judgement:
    """The self-check's verdict on one camera: doubtful when every check disagrees with it."""

    comparisons: List[Comparison] = field(default_factory=list)

    @property
    def doubtful(self) -> bool:
        return bool(self.comparisons) and all(c.disagrees() for c in self.comparisons)

    @property
    def evidence(self) -> str:
        return "; ".join(f"check {i + 1}: {c}" for i, c in enumerate(self.comparisons))

    def as_dict(self) -> dict:
        return {"doubtful": self.doubtful, "checks": [vars(c) for c in self.comparisons]}


def check_instants(instants: Sequence[int], count: int) -> List[List[int]]:
    """The instants of each check: as many as the first calibration's, spread evenly over the window at CHECKS
    phases between the default first, middle and last frames."""
    step = (count - 1) / len(instants)
    return [
        sorted({min(count - 1, round((i + k / (CHECKS + 1)) * step)) for i in range(len(instants))})
        for k in range(1, CHECKS + 1)
    ]


def judge(first: Calibration, names: Sequence[str], checks: Sequence) -> List[Judgement]:
    """Judge each camera of `first` (calibrated in the order `names`) by the checks' reconstructions (each a
    pycolmap.Reconstruction or None)."""
    judgements = [Judgement() for _ in names]
    for check in checks:
        for judgement, comparison in zip(judgements, compare(first, names, check)):
            judgement.comparisons.append(comparison)
    return judgements


def compare(first: Calibration, names: Sequence[str], check) -> List[Comparison]:
    """Per camera: where a check's reconstruction places it against the first calibration, after a trimmed similarity
    alignment over the cameras both registered."""
    images = registered(check)
    common = [i for i, name in enumerate(names) if name in images]
    comparisons = [Comparison(None, None, None) for _ in names]
    if len(common) < 3:  # too few to align: every camera unconfirmed
        return comparisons
    c2w = camera_to_world(first.cam_from_world[common])
    check_c2w = camera_to_world(np.array([images[names[i]].cam_from_world().matrix() for i in common]))
    differences = rig_differences(check_c2w[:, :, :3], check_c2w[:, :, 3], c2w[:, :, :3], c2w[:, :, 3], trimmed=True)
    for index, moved, turned in zip(common, differences["centre_pct"], differences["rotation_deg"]):
        focal = images[names[index]].camera.mean_focal_length() / first.cameras[index].mean_focal_length()
        comparisons[index] = Comparison(float(moved), float(turned), float(100 * (focal - 1)))
    return comparisons
