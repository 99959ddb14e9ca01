"""Render and training speed of trained runs: full-image seconds per frame, pixels / s and samples per ray of the
model's render path against nerfstudio's generic one (``Model.get_outputs_for_camera_ray_bundle``) on the same
checkpoint, their difference and PSNR against the held-out frames, and training rays / s (``Trainer.train_iteration``,
median of windows of 10 iterations after 5 warm-up ones, on a copy of the model)."""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model
from nerfstudio.utils.eval_utils import eval_setup
from torch import Tensor

from benchmarks.common import machine_description, provenance, table, timed, write_report
from gear_nerfstudio.model.metrics import psnr


def held_out(config: Path, frames: int) -> Tuple[Model, List[Tuple[RayBundle, Tensor]]]:
    """A run's model, and ``frames`` held-out frames evenly spaced over the video: (ray bundle, image) each."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    views = []
    for index in np.linspace(0, len(dataset) - 1, frames).round().astype(int).tolist():
        camera = dataset.cameras[index : index + 1].to(model.device)
        truth = dataset.get_image_float32(index)[..., :3].to(model.device)
        views.append((camera.generate_rays(camera_indices=0, keep_shape=True), truth))
    return model, views


def render_rows(config: Path, frames: int, repeats: int) -> Dict[str, float]:
    """Render measurements of one run, averaged over its held-out frames."""
    model, views = held_out(config, frames)
    rows: Dict[str, List[float]] = {}
    for rays, truth in views:
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


def training_rate(config: Path, windows: int) -> float:
    """Median training rays per second of ``Trainer.train_iteration`` on the run's checkpoint."""
    trainer_config, _, _, _ = eval_setup(config, test_mode="test")
    trainer_config.load_dir = config.parent / "nerfstudio_models"
    trainer_config.output_dir = Path("/tmp/render_speed")  # the run folder is never written
    trainer_config.vis = "tensorboard"
    trainer = trainer_config.setup(local_rank=0, world_size=1)
    trainer.setup()
    rays = trainer.pipeline.datamanager.config.train_num_rays_per_batch
    step = trainer._start_step
    for _ in range(5):
        trainer.train_iteration(step)
        step += 1
    rates = []
    for _ in range(windows):
        start = time.perf_counter()
        for _ in range(10):
            trainer.train_iteration(step)
            step += 1
        rates.append(10 * rays / (time.perf_counter() - start))
    return statistics.median(rates)


@dataclasses.dataclass
class RenderSpeed:
    """Measure the render and training speed of trained runs; print the table, append it to ``--output``."""

    configs: tyro.conf.Positional[Tuple[Path, ...]]
    """config.yml of trained runs."""
    frames: int = 3
    """Held-out frames per run, evenly spaced over the video."""
    repeats: int = 3
    """Timings per render (median)."""
    train_windows: int = 5
    """Windows of 10 training iterations (median)."""
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
                f"{training_rate(config, self.train_windows):,.0f}",
            ])  # fmt: skip
            print(rows[-1], flush=True)
        header = ["run", "pixels", "render s / frame: generic -> model (speed-up)", "pixels / s (model)",
                  "samples / ray", "PSNR generic / model (dB)", "model vs generic: max abs diff, PSNR (dB)",
                  "training rays / s"]  # fmt: skip
        write_report("\n".join(lines + table(header, rows)) + "\n\n", self.output, append=True)
