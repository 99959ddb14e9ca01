"""Indices spread evenly over a range: the frames of a window, the views of a dataset."""

from __future__ import annotations

from typing import List

import numpy as np


def evenly_spread(total: int, count: int) -> List[int]:
    """Up to ``count`` distinct indices of ``range(total)`` spread evenly, the first and last included."""
    return sorted({int(round(i)) for i in np.linspace(0, total - 1, min(count, total))})
