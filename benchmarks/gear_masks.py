"""Where a trained Gear-NeRF run put its gears, against the people's masks: at every frame of a training camera that
has masks, the share of the people's pixels at gear >= 2 and of the other pixels at gear 1 (Eq 5 at the surface each
pixel sees, ``GearNeRFModel.visible_gear_levels``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gear_masks.py <run>/config.yml \
        ../shared/data/real/panoptic_basketball_video_masks --cameras cam05 cam20

The held-out camera of ``panoptic-video`` (cam00) has no masks, so ``speed_accuracy.py`` cannot score its gear maps;
this scores training cameras instead, rendered at a quarter of their size, or with ``--held-out`` the held-out
camera of a run that held out one with masks (``tracking_real.py`` holds out cam20 of the 31-camera capture;
``ns-eval`` reports the same shares at the held-out camera, ``moving_at_gear_2`` and ``static_at_gear_1``).
Masks are ``<camera>/<frame:05d>.png``, numbered within the loaded window. ``--per-frame`` also prints the shares of
every camera and frame. It measures; it changes nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
import tyro
from nerfstudio.pipelines.base_pipeline import Pipeline
from nerfstudio.utils.eval_utils import eval_setup
from scipy import ndimage

from speed_accuracy import gear_mask_counts, read_mask


def people_mask(masks: Path, camera: str, number: int, shape: Tuple[int, int]) -> np.ndarray:
    """A capture's people mask (``read_mask``) area-resampled to shape (h, w), as bools."""
    mask = torch.from_numpy(read_mask(masks, camera, number))[None, None].float()
    return F.interpolate(mask, size=tuple(shape), mode="area")[0, 0].numpy() > 0.5


def pipeline_gear_shares(
    pipeline: Pipeline, masks: Path, cameras: Sequence[str], scale: float = 0.25, held_out: bool = False
) -> Tuple[float, float]:
    """People's pixels at gear >= 2 and other pixels at gear 1 in a loaded pipeline, over every frame of the given
    training cameras (of the held-out cameras with `held_out`)."""
    frames = frame_gear_counts(pipeline, masks, cameras, scale, held_out)
    return shares(np.sum([counts for _, _, counts in frames], axis=0))


@torch.no_grad()
def frame_gear_counts(
    pipeline: Pipeline, masks: Path, cameras: Sequence[str], scale: float = 0.25, held_out: bool = False
) -> Iterator[Tuple[str, int, np.ndarray]]:
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
            yield name, frame, gear_mask_counts(levels, people)


def shares(counts: np.ndarray) -> Tuple[float, float]:
    """People's pixels at gear >= 2 and other pixels at gear 1, from summed ``gear_mask_counts``."""
    return counts[0] / max(counts[1], 1), counts[2] / max(counts[3], 1)


GEAR_COLOURS = np.array([[0, 0, 0], [150, 150, 150], [40, 90, 230], [250, 150, 30], [220, 30, 30]], np.uint8)
"""Gear map colours: levels 1-4 grey, blue, orange, red."""


@torch.no_grad()
def gear_map_picture(
    pipeline: Pipeline, masks: Path, camera: str, frames: Sequence[int], scale: float = 0.25
) -> np.ndarray:
    """The held-out camera at some frames (numbered within the loaded window): its render above its gear map
    (``GEAR_COLOURS``), the people's true outlines green, as one RGB image."""
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    names, numbers = dataset.metadata["camera_names"], dataset.metadata["frame_numbers"]
    camera_ids, frame_ids = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
    renders, gears = [], []
    for frame in frames:
        index = int(torch.nonzero((camera_ids == names.index(camera)) & (frame_ids == frame))[0, 0])
        view = dataset.cameras[index : index + 1].to(model.device)
        view.rescale_output_resolution(scale)
        outputs = model.render_view(view)
        levels = model.visible_gear_levels(view, outputs).cpu().numpy()
        people = people_mask(masks, camera, int(numbers[frame]), levels.shape)
        outline = people & ~ndimage.binary_erosion(people)
        render = (outputs["rgb"].cpu().numpy().clip(0, 1) * 255).astype(np.uint8)
        gear = GEAR_COLOURS[levels.clip(0, 4)]
        for image in (render, gear):
            image[outline] = (0, 255, 0)
        renders.append(render)
        gears.append(gear)
    return np.concatenate([np.concatenate(renders, 1), np.concatenate(gears, 1)], 0)


def main(
    config: tyro.conf.Positional[Path],
    masks: tyro.conf.Positional[Path],
    cameras: Tuple[str, ...] = ("cam05", "cam20"),
    held_out: bool = False,
    per_frame: bool = False,
) -> None:
    """Print the two shares of one run (with `per_frame`, also those of every camera and frame): of the training
    `cameras`, or with `held_out` of the run's held-out camera."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    if held_out:
        metadata = pipeline.datamanager.eval_dataset.metadata
        cameras = tuple(sorted({metadata["camera_names"][int(i)] for i in metadata["camera_ids"]}))
    frames = frame_gear_counts(pipeline, masks, cameras, held_out=held_out)
    rows = [(f"{camera} frame {frame}", counts) for camera, frame, counts in frames]
    total = (config.parent.name, np.sum([counts for _, counts in rows], axis=0))
    for name, counts in (rows if per_frame else []) + [total]:
        people, static = shares(counts)
        print(f"{name}: people's pixels at gear >= 2: {people:.3f}; other pixels at gear 1: {static:.3f}")


if __name__ == "__main__":
    tyro.cli(main)
