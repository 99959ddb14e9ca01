"""The field's depth cue for the built-in SAM stand-in (issue 26), on views that a trained run renders.

For each run: every training camera of the capture that has masks (`<capture>_masks/<camera>/<frame>.png`, see
`tracking_real.py`), at `--frames` frames evenly spread over the window: `render_embedding` renders the SAM features
and the depth at the cells of SAM's grid (what `ns-gear-track` and the viewer decode), and one positive click per
person, at the mask pixel deepest inside them, is decoded twice: on the features alone (the decoder before the cue)
and with the depth cue. Reports mIoU of the first mask and of the best of the candidate masks, and the time of a
render and of a decode.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/depth_cue.py outputs/<run>/config.yml [more configs]
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import List

import numpy as np
import torch
import tyro

from gear_nerfstudio.sam.interface import Embedding
from gear_nerfstudio.tracking.metrics import iou
from gear_nerfstudio.tracking.propagation import render_embedding
from tracking_real import deepest_pixel, people, shrink


@dataclasses.dataclass
class DepthCueBenchmark:
    configs: tyro.conf.Positional[List[Path]]
    """config.yml of runs trained on a capture that has masks."""
    frames: int = 3
    """Frames per camera, evenly spread over the trained window."""

    def main(self) -> None:
        from nerfstudio.utils.eval_utils import eval_setup

        torch.set_num_threads(1)
        rows = [
            "| run | views | clicks | mIoU, features alone | mIoU, with the depth cue | best of the masks, alone / "
            "with | render ms / view | decode ms, alone / with |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for config in self.configs:
            _, pipeline, _, _ = eval_setup(config, test_mode="test")
            model, backend, dataset = pipeline.model, pipeline.sam_backend, pipeline.datamanager.train_dataset
            metadata = dataset.metadata
            masks = Path(str(pipeline.datamanager.config.dataparser.data).rstrip("/") + "_masks")
            num_frames = int(metadata["num_frames"])
            chosen = {round(k) for k in np.linspace(0, num_frames - 1, min(self.frames, num_frames))}
            scores, renders, decodes, views = [], [], [[], []], 0
            for index, (camera_id, frame_id) in enumerate(zip(metadata["camera_ids"], metadata["frame_ids"])):
                name, number = metadata["camera_names"][int(camera_id)], metadata["frame_numbers"][int(frame_id)]
                if int(frame_id) not in chosen or not (masks / name / f"{number:05d}.png").exists():
                    continue
                camera = dataset.cameras[index : index + 1]
                started = time.perf_counter()
                rendered = render_embedding(model, camera, float(camera.times.reshape(-1)[0]), backend)
                renders.append(time.perf_counter() - started)
                views += 1
                alone = Embedding(rendered.features, rendered.image_size)
                for person in people(masks, name, number):
                    person = shrink(person, person.shape[0] // rendered.image_size[0])  # a run on downscaled frames
                    click = np.array([deepest_pixel(person)])
                    row = []
                    for which, embedding in enumerate((alone, rendered)):
                        started = time.perf_counter()
                        candidates, _ = backend.decode(embedding, click, np.array([1]))
                        decodes[which].append(time.perf_counter() - started)
                        row += [iou(candidates[0], person), max(iou(m, person) for m in candidates)]
                    scores.append(row)
            table = 100 * np.array(scores)
            rows.append(
                f"| `{config}` | {views} | {len(scores)} | {table[:, 0].mean():.1f} | {table[:, 2].mean():.1f} | "
                f"{table[:, 1].mean():.1f} / {table[:, 3].mean():.1f} | {1000 * np.median(renders):.0f} | "
                f"{1000 * np.median(decodes[0]):.0f} / {1000 * np.median(decodes[1]):.0f} |"
            )
        print("\n".join(rows))


if __name__ == "__main__":
    tyro.cli(DepthCueBenchmark).main()
