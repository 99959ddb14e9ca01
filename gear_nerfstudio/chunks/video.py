"""Rendering and evaluating a chunked video as one video.

Each time of the whole video is rendered by the chunk that owns it, blended with its neighbour where
chunks share frames (``chunks.plan.owners``). Chunks are loaded one at a time, in order: a frame that needs
two chunks keeps the first one's weighted render until the second one adds its own, so at most the frames
of one overlap are held in memory, however long the video.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from PIL import Image
from torch import Tensor

from gear_nerfstudio.chunks.plan import Chunk, owners, position


def load_chunk(config_path: str, test_mode: str) -> object:
    """A trained chunk's pipeline (nerfstudio's eval_setup: the latest checkpoint, on CUDA when present)."""
    from nerfstudio.utils.eval_utils import eval_setup

    return eval_setup(Path(config_path), test_mode=test_mode)[1]


def render_at(pipeline, camera: Cameras, time: float) -> Tensor:
    """(H, W, 3) render of one camera at a chunk's own time."""
    timed = dataclasses.replace(camera, times=torch.full((1, 1), time))
    return pipeline.model.get_outputs_for_camera(timed.to(pipeline.device))["rgb"].cpu()


class Blender:
    """Sums the weighted renders of each output frame until its weights reach 1."""

    def __init__(self) -> None:
        self.pending: Dict[int, Tuple[Tensor, float]] = {}

    def add(self, frame: int, weight: float, rgb: Tensor) -> Optional[Tensor]:
        """Add one chunk's render; returns the blended frame once every owner has added its render."""
        total, weights = self.pending.pop(frame, (torch.zeros_like(rgb), 0.0))
        total, weights = total + weight * rgb, weights + weight
        if weights < 1.0 - 1e-6:
            self.pending[frame] = (total, weights)
            return None
        return total


def blended_frames(
    configs: List[str], chunks: List[Chunk], num_frames: int, cameras: Cameras
) -> Iterator[Tuple[int, Tensor]]:
    """(index, blended (H, W, 3) render) of every camera of a path, whose ``times`` are times of the whole video;
    frames come out as they are completed, not in path order."""
    times = cameras.times[:, 0].tolist()
    frame_owners = [owners(chunks, position(t, num_frames)) for t in times]
    blender = Blender()
    for chunk, config in zip(chunks, configs):
        wanted = [(i, w, local) for i, found in enumerate(frame_owners) for c, w, local in found if c == chunk]
        if not wanted:
            continue
        pipeline = load_chunk(config, "inference")
        for i, weight, local in wanted:
            done = blender.add(i, weight, render_at(pipeline, cameras[i : i + 1], local))
            if done is not None:
                yield i, done
        del pipeline


def write_png(rgb: Tensor, path: Path) -> None:
    Image.fromarray((rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)).save(path)


def evaluate(configs: List[str], chunks: List[Chunk], num_frames: int, frame_numbers: List[int]) -> Dict:
    """PSNR / SSIM (and LPIPS when its weights are local) of the held-out camera: per chunk (its own renders of
    its frames, as ns-eval of that chunk gives), per frame and overall (the blended renders, each frame once)."""
    blender = Blender()
    per_chunk: List[Dict] = []
    per_frame: Dict[int, Dict[str, float]] = {}
    for chunk, config in zip(chunks, configs):
        pipeline = load_chunk(config, "test")
        dataset = pipeline.datamanager.eval_dataset
        own: List[Dict[str, float]] = []
        for index in range(len(dataset)):
            frame = chunk.first + int(dataset.metadata["frame_ids"][index])
            image = dataset.get_image_float32(index)
            rgb = render_at(pipeline, dataset.cameras[index : index + 1], chunk.local_time(frame))
            own.append(pipeline.model.image_metrics(rgb, image))
            weight = next(w for c, w, _ in owners(chunks, frame) if c == chunk)
            blended = blender.add(frame, weight, rgb)
            if blended is not None:
                per_frame[frame] = pipeline.model.image_metrics(blended, image)
        per_chunk.append(
            {"chunk": chunk.index, "frames": [frame_numbers[chunk.first], frame_numbers[chunk.last]], **mean(own)}
        )
        del pipeline
    frames = [{"frame": frame_numbers[f], **per_frame[f]} for f in sorted(per_frame)]
    return {"results": mean(list(per_frame.values())), "chunks": per_chunk, "frames": frames}


def mean(metrics: List[Dict[str, float]]) -> Dict[str, float]:
    """Mean and standard deviation of each metric over images, named as ns-eval names them."""
    out: Dict[str, float] = {}
    for key in metrics[0] if metrics else ():
        values = np.array([m[key] for m in metrics])
        out[key] = float(values.mean())
        if len(values) > 1:
            out[f"{key}_std"] = float(values.std(ddof=1))
    out["num_images"] = len(metrics)
    return out


def write_json(data: Dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
