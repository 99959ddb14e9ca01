"""The motion gate (gear updates, Sec 4.3) against real sensor noise: over-time change of static and moving patches.

The gate counts a loss-map patch as moving when the mean over its pixels of ``frame_change`` (the largest mean
absolute RGB difference to up to ``motion_frames`` other frames of the same camera) reaches
``motion_threshold``. This script computes that statistic exactly as the updater does (same functions, same
loss-map size and patch size) on every training image of a real capture with foreground masks, and splits the
patches into static (no foreground pixel) and moving (at least half foreground), so that the threshold can be
set between the sensor noise of the static scene and the change where people move:

    .venv/bin/python benchmarks/motion_gate.py --data ../shared/data/real/panoptic_basketball \
        --masks ../shared/data/real/panoptic_basketball_masks --results benchmarks/results

Writes ``motion_gate.md`` (percentiles, and the fraction of each kind of patch that passes each threshold).
"""

from __future__ import annotations

import dataclasses
import datetime
import shlex
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F
import tyro
from PIL import Image

THRESHOLDS = (0.01, 0.015, 0.02, 0.03, 0.04, 0.05, 0.08)


@dataclasses.dataclass
class MotionGateBenchmark:
    """Patch statistics of the motion gate on a real capture in the Technicolor layout with foreground masks."""

    data: Path = Path("../shared/data/real/panoptic_basketball")
    """Capture in the Technicolor layout."""
    masks: Path = Path("../shared/data/real/panoptic_basketball_masks")
    """Foreground masks: <camera>/<frame:05d>.png (255 = moving)."""
    held_out_camera: str = "10"
    """Held-out camera (not scored; the gate runs on training views)."""
    near: float = 0.3
    far: float = 7.0
    cache_dir: Path = Path("outputs/motion_gate/frames")
    results: Optional[Path] = None
    """Also write motion_gate.md here (e.g. benchmarks/results)."""

    def main(self) -> None:
        from nerfstudio.data.datasets.base_dataset import InputDataset

        from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
        from gear_nerfstudio.gears.config import GearUpdateConfig
        from gear_nerfstudio.gears.loss_maps import frame_change, patch_means, patch_size_for, resized_image

        config = GearUpdateConfig()
        parser = TechnicolorDataParserConfig(
            data=self.data, near=self.near, far=self.far, held_out_camera=self.held_out_camera, cache_dir=self.cache_dir
        ).setup()
        dataset = InputDataset(parser.get_dataparser_outputs("train"))
        names, numbers = dataset.metadata["camera_names"], dataset.metadata["frame_numbers"]
        static: List[float] = []
        moving: List[float] = []
        ever: Dict[str, torch.Tensor] = {}  # per camera: where any frame has foreground
        for index in range(len(dataset)):
            camera = names[int(dataset.metadata["camera_ids"][index])]
            frame = numbers[int(dataset.metadata["frame_ids"][index])]
            mask_path = self.masks / camera / f"{frame:05d}.png"
            if not mask_path.is_file():
                continue
            width, height = int(dataset.cameras.width[index]), int(dataset.cameras.height[index])
            scale = min(1.0, config.loss_map_size / max(width, height))
            size = (int(height * scale), int(width * scale))  # as Cameras.rescale_output_resolution
            change = frame_change(dataset, index, resized_image(dataset, index, size), config.motion_frames)
            patch = patch_size_for(size, config.patch_size)
            if camera not in ever:
                ever[camera] = patch_means(sum(self.mask(path, size) for path in (self.masks / camera).glob("*.png")), patch)
            change_patches, mask_patches = patch_means(change, patch), patch_means(self.mask(mask_path, size), patch)
            static += change_patches[ever[camera] == 0].tolist()
            moving += change_patches[mask_patches >= 0.5].tolist()
        markdown = self.report(np.array(static), np.array(moving), config, len(dataset))
        out = Path("outputs/motion_gate")
        out.mkdir(parents=True, exist_ok=True)
        (out / "motion_gate.md").write_text(markdown)
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            (self.results / "motion_gate.md").write_text(markdown)
        print(markdown)

    @staticmethod
    def mask(path: Path, size: Tuple[int, int]) -> torch.Tensor:
        """Foreground mask as a float (h, w) map, area-resampled to size."""
        mask = torch.from_numpy(np.array(Image.open(path).convert("L")) > 127).float()[None, None]
        return F.interpolate(mask, size=size, mode="area")[0, 0]

    def report(self, static: np.ndarray, moving: np.ndarray, config, num_images: int) -> str:
        def percentiles(values: np.ndarray, qs: Tuple[float, ...]) -> str:
            return " | ".join(f"{np.percentile(values, q):.4f}" for q in qs)

        qs = (1, 5, 10, 50, 90, 99, 99.9)
        lines = [
            "# Motion gate against real sensor noise",
            "",
            f"Capture `{self.data}`: {num_images} training images (held-out camera {self.held_out_camera}). "
            f"Per image, `frame_change` to up to {config.motion_frames} other frames of its camera at loss-map size "
            f"(longest side {config.loss_map_size}), averaged over {config.patch_size}x{config.patch_size} patches, "
            "exactly as the gear updater computes it. Static: patches with no foreground pixel in any frame of "
            "their camera (the gate compares frames, so a patch that a person crosses at another time changes); "
            "moving: patches at least half foreground in their frame (the masks of the moving people).",
            "",
            "| patches | count | " + " | ".join(f"p{q:g}" for q in qs) + " |",
            "|---|---|" + "---|" * len(qs),
            f"| static | {len(static)} | {percentiles(static, qs)} |",
            f"| moving | {len(moving)} | {percentiles(moving, qs)} |",
            "",
            "| threshold | static patches passing (false moving) | moving patches passing |",
            "|---|---|---|",
        ]
        for threshold in THRESHOLDS:
            lines.append(
                f"| {threshold:g} | {100 * (static >= threshold).mean():.2f} % | {100 * (moving >= threshold).mean():.1f} % |"
            )
        lines += [
            "",
            f"Default `motion_threshold`: {config.motion_threshold:g}.",
            "",
            "```bash",
            ".venv/bin/python benchmarks/motion_gate.py " + shlex.join(sys.argv[1:]),
            "```",
            "",
            f"Date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}.",
            "",
        ]
        return "\n".join(lines)


if __name__ == "__main__":
    tyro.cli(MotionGateBenchmark).main()
