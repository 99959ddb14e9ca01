"""Held-out PSNR and render time of a trained run with and without `--pipeline.model.min-views` (issue 26).

Renders the held-out camera at the given frames through the path `ns-eval` takes
(`get_outputs_for_camera_ray_bundle`), once with the density only where `--min-views` training cameras see and once
over all space (`model.all_space()`), and prints a markdown row per frame and their means.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/seen_space.py outputs/<run>/config.yml --frames 0 5 10 15 19
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path
from typing import List

import numpy as np
import torch
import tyro


@dataclasses.dataclass
class SeenSpaceBenchmark:
    config: tyro.conf.Positional[Path]
    """config.yml of a trained run."""
    frames: List[int] = dataclasses.field(default_factory=lambda: [0, 5, 10, 15, 19])
    """Frame indices of the held-out camera to render."""
    min_views: int = 2
    """`--pipeline.model.min-views` of the "seen" renders (the run's own setting is ignored)."""

    def main(self) -> None:
        from nerfstudio.utils.eval_utils import eval_setup

        from gear_nerfstudio.model.gear_model import psnr

        torch.set_num_threads(1)
        _, pipeline, _, _ = eval_setup(self.config, test_mode="test")
        model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
        model.config.min_views = self.min_views
        model.see_from(pipeline.datamanager.train_dataparser_outputs.cameras)
        frame_ids = dataset.metadata["frame_ids"].tolist()
        print("| frame | PSNR, seen | PSNR, all space | render s, seen | render s, all space |\n|---|---|---|---|---|")
        totals = []
        for frame in self.frames:
            index = frame_ids.index(frame)
            camera = dataset.cameras[index : index + 1].to(model.device)
            truth = dataset[index]["image"][..., :3].to(model.device)
            row = []
            for space in (contextlib.nullcontext(), model.all_space()):
                rays = camera.generate_rays(camera_indices=0, keep_shape=True)
                started = time.perf_counter()
                with space:
                    rgb = model.get_outputs_for_camera_ray_bundle(rays)["rgb"].clamp(0, 1)
                seconds = time.perf_counter() - started
                row.append((float(psnr(rgb, truth)), seconds))
            totals.append(row)
            print(f"| {frame} | {row[0][0]:.2f} | {row[1][0]:.2f} | {row[0][1]:.1f} | {row[1][1]:.1f} |")
        means = np.mean(np.array(totals), axis=0)
        print(f"| mean | {means[0][0]:.2f} | {means[1][0]:.2f} | {means[0][1]:.1f} | {means[1][1]:.1f} |")


if __name__ == "__main__":
    tyro.cli(SeenSpaceBenchmark).main()
