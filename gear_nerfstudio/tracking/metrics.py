"""Mask quality for free-viewpoint tracking, as in the paper's tracking tables (Sec 5).

IoU and pixel accuracy of a predicted mask against the ground-truth mask; mIoU and accuracy average
them over the target views at the clicked time, t-mIoU and t-accuracy over the target views at the
other (novel) time steps. Values are fractions in [0, 1] (the paper prints percentages).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np


def iou(predicted: np.ndarray, truth: np.ndarray) -> float:
    """|P and T| / |P or T|; 1.0 when both masks are empty (they agree everywhere)."""
    predicted, truth = _pair(predicted, truth)
    union = np.count_nonzero(predicted | truth)
    return 1.0 if union == 0 else np.count_nonzero(predicted & truth) / union


def accuracy(predicted: np.ndarray, truth: np.ndarray) -> float:
    """Share of pixels where the predicted mask equals the ground truth."""
    predicted, truth = _pair(predicted, truth)
    return float(np.count_nonzero(predicted == truth)) / predicted.size


def _pair(predicted: np.ndarray, truth: np.ndarray):
    predicted, truth = np.asarray(predicted, dtype=bool), np.asarray(truth, dtype=bool)
    if predicted.shape != truth.shape:
        raise ValueError(f"mask shapes differ: predicted {predicted.shape}, ground truth {truth.shape}")
    return predicted, truth


@dataclass
class MaskScore:
    """The score of one (view, time) mask."""

    view: str
    time: float
    clicked_time: bool
    iou: float
    accuracy: float


def score(view: str, time: float, clicked_time: bool, predicted: np.ndarray, truth: np.ndarray) -> MaskScore:
    return MaskScore(view, time, clicked_time, iou(predicted, truth), accuracy(predicted, truth))


def summarise(scores: Sequence[MaskScore]) -> Dict[str, Optional[float]]:
    """mIoU / accuracy over masks at the clicked time, t-mIoU / t-accuracy over the other times;
    None where there is no mask to average."""

    def mean(values: List[float]) -> Optional[float]:
        return float(np.mean(values)) if values else None

    at_click = [s for s in scores if s.clicked_time]
    other = [s for s in scores if not s.clicked_time]
    return {
        "mIoU": mean([s.iou for s in at_click]),
        "accuracy": mean([s.accuracy for s in at_click]),
        "t-mIoU": mean([s.iou for s in other]),
        "t-accuracy": mean([s.accuracy for s in other]),
        "masks_at_clicked_time": len(at_click),
        "masks_at_other_times": len(other),
    }
