"""Where a Gear-NeRF run loses to its one-gear baseline, frame by frame: the held-out camera's PSNR at every frame of
the window for both runs, and how much of the static surface that camera sees the gear function (Eq 4-5) puts at
gear >= 2 at each frame.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gear_flicker.py <gear-nerf run>/config.yml <one-gear run>/config.yml

The static surface is the held-out view's visible surface at the middle frame where the Gear-NeRF run puts it at
gear 1 (``GearNeRFModel.visible_gear_levels``). The same points are then given each frame's time. A share well
above the other frames' means that the gear function raised that surface at that frame alone. The script prints a
markdown table and the mean PSNR difference (Gear-NeRF minus one gear) on the frames where the share is at least
``FLICKER_SHARE`` and on the others. It diagnoses; it changes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Tuple

import numpy as np
import torch
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.model.gear_model import GearNeRFModel, psnr

FLICKER_SHARE = 0.1
"""A frame at which at least this share of the static surface is at gear >= 2 counts as a flicker frame."""


def held_out(config: Path) -> Tuple[GearNeRFModel, InputDataset]:
    """A trained run's model and its held-out (evaluation) dataset."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    return pipeline.model, pipeline.datamanager.eval_dataset


def frame_psnrs(model: GearNeRFModel, dataset: InputDataset) -> List[float]:
    """Held-out PSNR of one run at every frame of its evaluation split."""
    values = []
    for index in range(len(dataset)):
        outputs = model.get_outputs_for_camera(dataset.cameras[index : index + 1])
        values.append(float(psnr(outputs["rgb"], dataset.get_image_float32(index)[..., :3].to(outputs["rgb"]))))
    return values


@torch.no_grad()
def raised_shares(model: GearNeRFModel, dataset: InputDataset) -> List[float]:
    """Per frame, the share of the middle frame's gear-1 surface (held-out view) that is at gear >= 2."""
    middle = len(dataset) // 2
    camera = dataset.cameras[middle : middle + 1]
    outputs = model.render_view(camera)
    surface = model.visible_surface(camera, outputs).reshape(-1, 3)
    static = surface[model.visible_gear_levels(camera, outputs).reshape(-1) == 1]
    shares = []
    for t in dataset.cameras.times[:, 0].tolist():
        levels = model.field.gear_levels(static, static.new_full((len(static), 1), t))
        shares.append(float((levels >= 2).float().mean()))
    return shares


def main(gear_nerf: Path, one_gear: Path) -> None:
    model, dataset = held_out(gear_nerf)
    shares, ours = np.array(raised_shares(model, dataset)), np.array(frame_psnrs(model, dataset))
    baseline = np.array(frame_psnrs(*held_out(one_gear)))
    print("| frame | static surface at gear >= 2 | Gear-NeRF PSNR (dB) | one gear PSNR (dB) | difference |")
    print("|---|---|---|---|---|")
    for frame, (share, a, b) in enumerate(zip(shares, ours, baseline)):
        print(f"| {frame} | {share:.3f} | {a:.2f} | {b:.2f} | {a - b:+.2f} |")
    flicker = shares >= FLICKER_SHARE
    difference = ours - baseline
    print(f"\nflicker frames (share >= {FLICKER_SHARE}): {np.nonzero(flicker)[0].tolist()}")
    for label, chosen in (("flicker frames", flicker), ("other frames", ~flicker)):
        mean = f"{difference[chosen].mean():+.2f} dB" if chosen.any() else "missing (no such frame)"
        print(f"Gear-NeRF minus one gear on the {label}: {mean}")
    print(f"mean PSNR: Gear-NeRF {ours.mean():.2f} dB, one gear {baseline.mean():.2f} dB")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
