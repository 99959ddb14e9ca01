"""NeRF-W's evaluation protocol for a held-out camera's appearance, as a diagnosis of a trained run: fit the held-out
camera's appearance code on the left half of its frames, then score the right half, against the model's own choice
(the mean code of the training cameras) on the same right half. Only the code is optimised; the model is unchanged.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/held_out_appearance_fit.py <run>/config.yml [steps [picture.png]]

Scores 4 held-out frames evenly spaced over the video; the fit takes ``steps`` (default 200) Adam steps of 1,024
rays drawn from the left halves of those frames (learning rate 0.01, starting from the mean code). With a picture
path, also writes the first and third of those frames: ground truth, the render with the mean code, the render with
the fitted code.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from compare_views import contact_sheet
from nerfstudio.utils.eval_utils import eval_setup
from PIL import Image

from gear_nerfstudio.fields.appearance import RIG_CAMERA
from gear_nerfstudio.model.gear_model import psnr


def as_image(rgb: torch.Tensor) -> Image.Image:
    return Image.fromarray((rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8))


def main(config: Path, steps: int, picture: Optional[Path]) -> None:
    torch.manual_seed(0)
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    appearance = model.field.appearance
    if appearance is None:
        raise SystemExit(f"error: {config} trains no appearance codes (--pipeline.model.appearance-dim 0)")
    frames = np.linspace(0, len(dataset) - 1, 4).round().astype(int)
    cameras = [dataset.cameras[int(i) : int(i) + 1] for i in frames]
    truths = [dataset.get_image_float32(int(i))[..., :3] for i in frames]
    width = truths[0].shape[1]
    right = slice(width // 2, width)

    def render() -> List[torch.Tensor]:
        with torch.no_grad():
            return [model.get_outputs_for_camera(camera)["rgb"] for camera in cameras]

    def right_half_psnr(renders: List[torch.Tensor]) -> float:
        return float(np.mean([float(psnr(rgb[:, right], truth[:, right])) for rgb, truth in zip(renders, truths)]))

    with_mean = render()
    held = int(cameras[0].metadata[RIG_CAMERA].reshape(-1)[0])
    with torch.no_grad():
        appearance.codes.weight[held] = appearance.mean_code()
        appearance.trained[held] = True  # its rays now read codes[held], which the fit moves
    bundles = [camera.generate_rays(camera_indices=0, keep_shape=True)[:, : width // 2].flatten() for camera in cameras]
    colours = [truth[:, : width // 2].reshape(-1, 3) for truth in truths]
    code = appearance.codes.weight
    for parameter in model.parameters():
        parameter.requires_grad_(parameter is code)
    optimizer = torch.optim.Adam([code], lr=0.01)
    others = torch.ones(len(code), dtype=torch.bool)
    others[held] = False
    for _ in range(steps):
        frame = int(torch.randint(len(bundles), ()))
        rays = torch.randint(len(bundles[frame]), (1024,))
        loss = torch.nn.functional.mse_loss(model(bundles[frame][rays])["rgb"], colours[frame][rays])
        optimizer.zero_grad()
        loss.backward()
        code.grad[others] = 0.0  # only the held-out camera's code moves
        optimizer.step()
    fitted = render()
    if picture is not None:
        rows = [[as_image(truths[k]), as_image(with_mean[k]), as_image(fitted[k])] for k in (0, 2)]
        contact_sheet(["ground truth", "mean code", "code fitted on the left half"], rows).save(picture)
    print(f"{config}: right halves of {len(frames)} held-out frames, mean code {right_half_psnr(with_mean):.2f} dB, "
          f"code fitted on the left halves {right_half_psnr(fitted):.2f} dB")


if __name__ == "__main__":
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 200
    main(Path(sys.argv[1]), steps, Path(sys.argv[3]) if len(sys.argv) > 3 else None)
