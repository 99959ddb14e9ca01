"""Free-viewpoint tracking (Sec 4.5) on real video (CMU Panoptic basketball): one click per person of the foreground
masks, ``ns-gear-track`` into the held-out camera at every frame, scored against its masks (mIoU, t-mIoU)."""

from __future__ import annotations

import dataclasses
import subprocess
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from PIL import Image
from scipy import ndimage

from benchmarks.common import REAL, mean, page, pct, read_mask, table, write_report
from benchmarks.tracking import deepest_pixel, track_click, train_preset
from gear_nerfstudio.tracking.metrics import accuracy, iou

CAPTURE = REAL / "panoptic_basketball"
PERSON_SHARE = 1000 / (320 * 180)
"""Smallest mask component counted as a person, as a share of the image (at 320x180 the ball is 400-600 pixels,
the people 1,300-13,000)."""


def people(masks: Path, camera: str, frame: int) -> List[np.ndarray]:
    """The person components (H, W) bool of a camera's foreground mask at a frame (`read_mask`), largest first."""
    labels, count = ndimage.label(read_mask(masks, camera, frame))
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    return [labels == index + 1 for index in np.argsort(-sizes) if sizes[index] >= PERSON_SHARE * labels.size]


def dataparser(folder: Path, held_out: str, downscale: int, frame_count: Optional[int]) -> List[str]:
    """The dataparser's subcommand and options for a capture in either layout with `held_out` held out, frames
    downscaled by `downscale`, the first `frame_count` frames (all when None)."""
    options = ["--held-out-camera", held_out, "--downscale-factor", str(downscale)]
    if frame_count is not None:
        options += ["--frame-count", str(frame_count)]
    if (folder / "poses_bounds.npy").exists():  # Neural 3D Video layout (camNN.mp4 and poses_bounds.npy)
        return ["neural-3d-video-data", "--data", str(folder), *options]
    return ["technicolor-data", "--data", str(folder), "--near", "0.3", "--far", "7", *options]


def shrink(mask: np.ndarray, factor: int) -> np.ndarray:
    """A mask (H, W) at the size the dataparser gives frames downscaled by `factor` (nearest neighbour)."""
    if factor == 1:
        return mask
    height, width = mask.shape
    return np.asarray(Image.fromarray(mask).resize((width // factor, height // factor), Image.NEAREST))


@dataclasses.dataclass
class TrackingReal:
    """Score tracking through a run trained on a capture."""

    output: Path = Path("outputs/tracking_real")
    capture: Path = CAPTURE
    iterations: int = 3000
    seed: int = 42
    """Training seed (`--machine.seed`; nerfstudio's default is 42)."""
    held_out: str = "00"
    """Held-out camera: it must have masks; camera 00 of panoptic_basketball sees both people at every frame (06,
    the speed benchmark's, sees one)."""
    config: Optional[Path] = None
    """config.yml of a run already trained on the capture with `--held-out` held out (skips training)."""
    click_camera: str = "12"
    click_frame: int = 10
    downscale: int = 1
    """Train on frames downscaled by this factor (the dataparser's --downscale-factor); masks are scored at that
    size."""
    frame_count: Optional[int] = None
    """Train on the first this many frames (the dataparser's --frame-count); all by default."""

    def main(self) -> None:
        self.output.mkdir(parents=True, exist_ok=True)
        masks = self.capture.parent / f"{self.capture.name}_masks"
        frames = len(list((masks / self.held_out).glob("*.png")))
        frames = frames if self.frame_count is None else min(frames, self.frame_count)
        config = self.config or self.train()
        click_time = self.click_frame / (frames - 1)
        clicked_people = people(masks, self.click_camera, self.click_frame)
        held_out = [
            [shrink(person, self.downscale) for person in people(masks, self.held_out, frame)]
            for frame in range(frames)
        ]
        rows, refusals = [], []
        for index, person in enumerate(clicked_people):
            x, y = (value / self.downscale for value in deepest_pixel(person))
            folder, log = self.output / f"track_person{index}", self.output / f"track_person{index}.log"
            try:
                summary = track_click(config, folder, self.click_camera, click_time, (x, y), self.held_out, log)
            except subprocess.CalledProcessError:
                # A refused click is a failed track: no mask at any time.
                rows.append([f"{index} (click {x:.1f}, {y:.1f})", "0.0 | n/a | 0.0 | n/a"])
                refusals.append(f"- person {index}: IoU 0 at every time, `ns-gear-track` refused the click: "
                                f"{refusal(log)}")  # fmt: skip
                continue
            scores = score(folder, summary, held_out, click_time)
            rows.append([f"{index} (click {x:.1f}, {y:.1f})", summary_cells(scores, click_time)])
        lines = [
            f"Run: `{config}`; click in camera {self.click_camera} at time {click_time:.3f} (frame "
            f"{self.click_frame}), one positive click per person at the mask pixel deepest inside them; target: "
            f"held-out camera {self.held_out} at every frame time ({frames}), embedding propagation.",
            "", *table(["person", "mIoU", "Acc.", "t-mIoU", "t-Acc."], rows),
            *([""] if refusals else []), *refusals,
        ]  # fmt: skip
        write_report(page("Tracking on a real capture", lines), self.output / "tracking_real.md")

    def train(self) -> Path:
        options = [
            "--pipeline.datamanager.sam-cache-dir", str(self.output / "sam"),
            *dataparser(self.capture, self.held_out, self.downscale, self.frame_count), "--cache-dir",
            str(self.output / "frames"),
        ]  # fmt: skip
        return train_preset(self.output, self.iterations, self.seed, options)


def refusal(log: Path) -> str:
    """The error that a command wrote to its log: its lines from the one with "error:" on, joined."""
    lines = log.read_text().splitlines()
    start = next((k for k, line in enumerate(lines) if "error:" in line), len(lines) - 1)
    return " ".join(line.strip() for line in lines[start:])


def score(
    folder: Path, summary: Dict, held_out: List[List[np.ndarray]], click_time: float
) -> Dict[float, Tuple[float, float]]:
    """IoU and accuracy of every tracked mask against the clicked person's component in the held-out camera,
    whose person components per frame are `held_out`, by time."""
    frames = len(held_out)
    click_frame = round(click_time * (frames - 1))
    x, y = next(r for r in summary["masks"] if r["time"] == click_time)["prompt"]["points"][0]
    nearest = [float(np.hypot(*(np.argwhere(c) - [y, x]).T).min()) for c in held_out[click_frame]]
    person = {click_frame: held_out[click_frame][int(np.argmin(nearest))]}
    for step in (1, -1):
        for frame in range(click_frame + step, frames if step > 0 else -1, step):
            previous = person[frame - step]
            person[frame] = max(held_out[frame], key=lambda c: np.count_nonzero(c & previous))
    scores = {}
    for record in summary["masks"]:
        predicted = np.asarray(Image.open(folder / record["mask"])) > 0
        target = person[round(record["time"] * (frames - 1))]
        scores[record["time"]] = iou(predicted, target), accuracy(predicted, target)
    return scores


def summary_cells(scores: Dict[float, Tuple[float, float]], click_time: float) -> str:
    """mIoU | Acc. at the clicked time | t-mIoU | t-Acc. at the others (%), from (IoU, accuracy) by time."""
    at_click = [v for t, v in scores.items() if t == click_time]
    other = [v for t, v in scores.items() if t != click_time]
    return " | ".join(pct(mean(values, index)) for values in (at_click, other) for index in (0, 1))
