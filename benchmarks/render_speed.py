"""Render speed of trained runs: the model's render path against nerfstudio's generic one on the same checkpoint
(seconds per frame, pixels / s, samples per ray), and their difference and PSNR against the held-out frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.models.base_model import Model
from nerfstudio.utils.eval_utils import eval_setup

from benchmarks.common import machine_description, provenance, table, timed, write_report
from gear_nerfstudio.model.metrics import psnr


def render_rows(config: Path, frames: int, repeats: int) -> Dict[str, float]:
    """Render measurements of one run, averaged over ``frames`` held-out frames evenly spaced over the video."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    rows: Dict[str, List[float]] = {}
    for index in np.linspace(0, len(dataset) - 1, frames).round().astype(int).tolist():
        camera = dataset.cameras[index : index + 1].to(model.device)
        rays = camera.generate_rays(camera_indices=0, keep_shape=True)
        truth = dataset.get_image_float32(index)[..., :3].to(model.device)
        with torch.no_grad():
            generic_s, generic = timed(lambda: Model.get_outputs_for_camera_ray_bundle(model, rays), repeats)
            with model.rendering("num_samples"):
                model_s, rendered = timed(lambda: model.get_outputs_for_camera_ray_bundle(rays), repeats)
        difference = (rendered["rgb"] - generic["rgb"]).abs()
        for name, value in {
            "pixels": rays.shape.numel(),
            "generic_s": generic_s,
            "model_s": model_s,
            "samples_per_ray": float(rendered["num_samples"].mean()),
            "generic_psnr": float(psnr(generic["rgb"], truth)),
            "model_psnr": float(psnr(rendered["rgb"], truth)),
            "max_difference": float(difference.max()),
            "difference_psnr": float(psnr(rendered["rgb"], generic["rgb"])),
        }.items():
            rows.setdefault(name, []).append(value)
    return {name: float(np.mean(values)) for name, values in rows.items()}


@dataclasses.dataclass
class RenderSpeed:
    """Measure the render speed of trained runs; print the table, append it to ``--output``."""

    configs: tyro.conf.Positional[Tuple[Path, ...]]
    """config.yml of trained runs."""
    frames: int = 3
    """Held-out frames per run, evenly spaced over the video."""
    repeats: int = 3
    """Timings per render (median)."""
    output: Optional[Path] = None
    """Append the table to this Markdown file."""

    def main(self) -> None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
        lines = [*provenance(machine_description(device)), ""]
        rows = []
        for config in self.configs:
            row = render_rows(config, self.frames, self.repeats)
            rows.append([
                config.parent, f"{row['pixels']:.0f}",
                f"{row['generic_s']:.2f} -> {row['model_s']:.2f} ({row['generic_s'] / row['model_s']:.2f}x)",
                f"{row['pixels'] / row['model_s']:,.0f}", f"{row['samples_per_ray']:.1f}",
                f"{row['generic_psnr']:.3f} / {row['model_psnr']:.3f}",
                f"{row['max_difference']:.2g}, {row['difference_psnr']:.1f}",
            ])  # fmt: skip
            print(rows[-1], flush=True)
        header = ["run", "pixels", "render s / frame: generic -> model (speed-up)", "pixels / s (model)",
                  "samples / ray", "PSNR generic / model (dB)", "model vs generic: max abs diff, PSNR (dB)"]
        write_report("\n".join(lines + table(header, rows)) + "\n\n", self.output, append=True)
