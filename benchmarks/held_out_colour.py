"""How much of a held-out view's error is its camera's colour: PSNR of the held-out renders that a
``speed_accuracy.py`` run folder holds, as they are and after a per-channel gain and offset fitted to the ground
truth (least squares over the whole image, 6 numbers per frame).

    .venv/bin/python benchmarks/held_out_colour.py outputs/sa2/runs/panoptic/gear-nerf-small/gear-nerf-seed42 ...

The fit sees the answer, so its PSNR is a diagnosis (an upper bound of what a colour correction of the held-out
camera could give), never a score. A held-out camera's white balance and exposure are not in the training
images; the model renders it with the mean appearance code of the training cameras.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

import numpy as np
import torch
import tyro
from compare_views import held_out_stems
from PIL import Image

from gear_nerfstudio.model.gear_model import psnr


def colour_fitted(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``render`` with each channel mapped by the gain and offset that best fit ``truth`` (least squares)."""
    fitted = np.empty_like(render)
    for c in range(render.shape[-1]):
        design = np.stack([render[..., c].ravel(), np.ones(render[..., c].size)], axis=1)
        coefficients = np.linalg.lstsq(design, truth[..., c].ravel(), rcond=None)[0]
        fitted[..., c] = (design @ coefficients).reshape(render.shape[:2])
    return np.clip(fitted, 0.0, 1.0)


def main(runs: tyro.conf.Positional[Tuple[Path, ...]]) -> None:
    """Print, per run folder, the mean PSNR over its held-out frames before and after the colour fit."""
    for run in runs:
        scores = []
        for stem in held_out_stems(run):
            truth, render = (np.asarray(Image.open(run / f"{stem}_{kind}.png").convert("RGB"), dtype=np.float64) / 255
                             for kind in ("truth", "render"))  # fmt: skip
            corrected = colour_fitted(render, truth)
            scores.append([float(psnr(torch.from_numpy(image), torch.from_numpy(truth))) for image in (render, corrected)])
        plain, fitted = np.mean(scores, axis=0)
        print(f"{run}: {len(scores)} frames, PSNR {plain:.2f} dB, after the colour fit {fitted:.2f} dB")


if __name__ == "__main__":
    tyro.cli(main)
