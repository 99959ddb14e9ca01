"""Reading the ground truth that ``write_synthetic_scene`` writes beside a synthetic scene."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np


class GroundTruth:
    """Object masks of a synthetic scene: `<data>/ground_truth/<camera>.npz` (object_ids (T, H, W))."""

    def __init__(self, folder: Path, frame_numbers: List[int], first_frame_number: int):
        self.folder = folder
        self.frame_numbers = frame_numbers
        self.first_frame_number = first_frame_number
        self._ids: Dict[str, np.ndarray] = {}

    @classmethod
    def find(cls, data: Optional[Path], metadata: Dict) -> Optional["GroundTruth"]:
        """The ground truth of a scene folder written by ``write_synthetic_scene``; None for other data."""
        if data is None or not (Path(data) / "ground_truth" / "scene.json").is_file():
            return None
        folder = Path(data) / "ground_truth"
        spec = json.loads((folder / "scene.json").read_text()).get("spec", {})
        return cls(folder, list(metadata.get("frame_numbers", [])), int(spec.get("first_frame_number", 0)))

    def object_ids(self, camera: str, time: float, size: Tuple[int, int]) -> Optional[np.ndarray]:
        """Object ids (H, W) of a camera at a frame time, resampled to `size`; None off the frames."""
        count = len(self.frame_numbers)
        index = round(time * max(count - 1, 1))
        if count == 0 or abs(index / max(count - 1, 1) - time) > 1e-6:
            return None
        if camera not in self._ids:
            path = self.folder / f"{camera}.npz"
            if not path.is_file():
                return None
            with np.load(path) as data:
                self._ids[camera] = data["object_ids"]
        ids = self._ids[camera]
        frame = self.frame_numbers[index] - self.first_frame_number
        if not 0 <= frame < len(ids):
            return None
        rows = ((np.arange(size[0]) + 0.5) * ids.shape[1] / size[0]).astype(np.int64)
        cols = ((np.arange(size[1]) + 0.5) * ids.shape[2] / size[1]).astype(np.int64)
        return ids[frame][rows[:, None], cols[None, :]]
