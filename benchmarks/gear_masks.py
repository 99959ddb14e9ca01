"""Where a trained run put its gears against the people's masks (``GearNeRFModel.visible_gear_levels`` at a quarter
of the cameras' size): the share of the people's pixels at gear >= 2 and of the other pixels at gear 1."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterator, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
import tyro
from nerfstudio.pipelines.base_pipeline import Pipeline
from nerfstudio.utils.eval_utils import eval_setup

from benchmarks.common import gear_mask_counts, read_mask


def people_mask(masks: Path, camera: str, number: int, shape: Tuple[int, int]) -> np.ndarray:
    """A capture's people mask (``read_mask``) area-resampled to shape (h, w), as bools."""
    mask = torch.from_numpy(read_mask(masks, camera, number))[None, None].float()
    return F.interpolate(mask, size=tuple(shape), mode="area")[0, 0].numpy() > 0.5


@torch.no_grad()
def frame_gear_counts(
    pipeline: Pipeline, masks: Path, cameras: Sequence[str], scale: float = 0.25, held_out: bool = False
) -> Iterator[np.ndarray]:
    """Per camera and frame (numbered within the loaded window): ``gear_mask_counts`` of its gear map against the
    people's mask."""
    datamanager = pipeline.datamanager
    model, dataset = pipeline.model, datamanager.eval_dataset if held_out else datamanager.train_dataset
    names, numbers = dataset.metadata["camera_names"], dataset.metadata["frame_numbers"]
    camera_ids, frame_ids = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
    for name in cameras:
        indices = torch.nonzero(camera_ids == names.index(name))[:, 0].tolist() if name in names else []
        if not indices:
            split = "held-out" if held_out else "training"
            present = sorted({names[int(i)] for i in camera_ids})
            raise SystemExit(f"error: {name} is not a {split} camera of this run; its {split} cameras: {present}")
        for index in indices:
            camera = dataset.cameras[index : index + 1].to(model.device)
            camera.rescale_output_resolution(scale)
            levels = model.visible_gear_levels(camera).cpu().numpy()
            frame = int(frame_ids[index])
            people = people_mask(masks, name, int(numbers[frame]), levels.shape)
            yield gear_mask_counts(levels, people)


@dataclasses.dataclass
class GearMasks:
    """Print the two shares of one run."""

    config: tyro.conf.Positional[Path]
    """config.yml of the trained run."""
    masks: tyro.conf.Positional[Path]
    """The capture's mask folder (``<camera>/<frame:05d>.png``)."""
    cameras: Tuple[str, ...] = ("cam05", "cam20")
    """Training cameras to score."""
    held_out: bool = False
    """Score the run's held-out camera(s) instead."""

    def main(self) -> None:
        _, pipeline, _, _ = eval_setup(self.config, test_mode="test")
        cameras = self.cameras
        if self.held_out:
            metadata = pipeline.datamanager.eval_dataset.metadata
            cameras = tuple(sorted({metadata["camera_names"][int(i)] for i in metadata["camera_ids"]}))
        counts = sum(frame_gear_counts(pipeline, self.masks, cameras, held_out=self.held_out))
        people, static = counts[0] / max(counts[1], 1), counts[2] / max(counts[3], 1)
        print(f"{self.config.parent.name}: people's pixels at gear >= 2: {people:.3f}; other pixels at gear 1: "
              f"{static:.3f}")
