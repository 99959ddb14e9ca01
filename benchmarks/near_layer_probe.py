"""Where a held-out view's near layer lies: re-render a trained run's held-out camera with the near plane moved
further out, evaluation only (the model is unchanged), and print PSNR and accumulation per near plane.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/near_layer_probe.py <run>/config.yml 0.15 0.2 0.3

A layer that lies between the model's near plane and a given value disappears from the render at that value.
This is a diagnosis, not a fix: a user's renders keep the model's near plane. Scores 4 held-out frames evenly
spaced over the video, full-image PSNR against the ground truth.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.model.gear_model import psnr


def main(config: Path, nears: list) -> None:
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    frames = np.linspace(0, len(dataset) - 1, 4).round().astype(int)
    for near in [model.collider.near_plane, *nears]:
        model.collider.near_plane = near
        psnrs, accumulations = [], []
        for index in frames:
            with torch.no_grad():
                outputs = model.get_outputs_for_camera(dataset.cameras[int(index) : int(index) + 1])
            truth = dataset.get_image_float32(int(index))[..., :3]
            psnrs.append(float(psnr(outputs["rgb"], truth)))
            accumulations.append(float(outputs["accumulation"].mean()))
        print(f"near {near:.3f}: PSNR {np.mean(psnrs):.2f} dB, accumulation {np.mean(accumulations):.3f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), [float(value) for value in sys.argv[2:]])
