"""Do the gear updates (Sec 4.3) put moving objects in higher gears? Measured against ground truth.

For a scene with a static background and one fast object, and for a fully static scene: train a preset
with `ns-train`, render the expected gear level of the held-out camera at every time, and compare with
the ground-truth motion map (pixels of moving objects vs static pixels).

    .venv/bin/python benchmarks/gear_assignment.py --output outputs/gear_assignment

Prints a markdown table (and writes it to `<output>/gear_assignment.md`).
"""

from __future__ import annotations

import dataclasses
import subprocess
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import torch
import tyro

from environment import BIN, command_environment
from gear_nerfstudio.synthetic.writers import SyntheticSpec, write_synthetic_scene


@dataclasses.dataclass
class GearAssignmentBenchmark:
    output: Path = Path("outputs/gear_assignment")
    method: str = "gear-nerf-small"
    iterations: int = 1500
    width: int = 64
    height: int = 48
    frames: int = 6
    cameras: int = 6
    mask_source: str = "sam"
    """'sam' or 'loss_threshold' (the "w/o embedding" ablation)."""
    motion_threshold: float = 0.03
    """The motion gate of the updates; 0 gives the paper's behaviour."""
    motions: Tuple[str, ...] = ("fast", "static")
    """Synthetic scenes to run (motion kinds of `SyntheticSpec`)."""

    def main(self) -> None:
        rows = [
            "| scene | time | object pixels at gear >= 2 | static pixels at gear 1 | samples per ray (mean) |",
            "|---|---|---|---|---|",
        ]
        for motion in self.motions:
            for time, object_fraction, static_fraction, samples in self.run(motion):
                shown = "n/a (no moving object)" if object_fraction is None else f"{object_fraction:.3f}"
                rows.append(f"| {motion} | {time} | {shown} | {static_fraction:.3f} | {samples:.1f} |")
        table = "\n".join(rows)
        print(table)
        (self.output / "gear_assignment.md").write_text(table + "\n")

    def run(self, motion: str) -> List[Tuple[str, Optional[float], float, float]]:
        scene = self.output / f"scene-{motion}"
        spec = SyntheticSpec(
            dataset="n3d", width=self.width, height=self.height, frames=self.frames, cameras=self.cameras, motion=motion
        )
        write_synthetic_scene(scene, spec)
        runs = self.output / "runs"
        runs.mkdir(parents=True, exist_ok=True)
        with open(runs / f"{motion}.log", "w") as log:  # the trainer's log, with one line per gear update
            subprocess.run(
                [
                    str(BIN / "ns-train"), self.method, "--output-dir", str(runs), "--experiment-name", motion,
                    "--timestamp", "run", "--max-num-iterations", str(self.iterations), "--machine.device-type", "cpu",
                    "--vis", "tensorboard", "--pipeline.model.gear-updates.mask-source", self.mask_source,
                    "--pipeline.model.gear-updates.motion-threshold", str(self.motion_threshold),
                    "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(self.output / "cache"),
                ],
                check=True,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=command_environment(),
            )
        return self.measure(runs / motion / self.method / "run" / "config.yml", scene)

    @staticmethod
    def measure(config: Path, scene: Path) -> List[Tuple[str, Optional[float], float, float]]:
        """Per time of the held-out camera and over all times ("all"): fraction of moving-object pixels
        whose rendered expected gear level is >= 1.5, of static pixels below 1.5, and samples per ray."""
        from nerfstudio.utils.eval_utils import eval_setup

        _, pipeline, _, _ = eval_setup(config, test_mode="test")
        dataset = pipeline.datamanager.eval_dataset
        motion = np.load(scene / "ground_truth" / "cam00.npz")["motion"]
        rows = []
        moving: List[np.ndarray] = []
        static: List[np.ndarray] = []
        samples: List[float] = []
        for index in range(len(dataset)):
            camera = dataset.cameras[index : index + 1].to(pipeline.device)
            frame = int(dataset.metadata["frame_ids"][index])
            with torch.no_grad():
                outputs = pipeline.model.get_outputs_for_camera(camera)
            upshifted = outputs["gear_level"][..., 0].cpu().numpy() >= 1.5
            truth = motion[frame] > 0
            moving.append(upshifted[truth])
            static.append(~upshifted[~truth])
            samples.append(float(outputs["num_samples"].mean()))
            rows.append((f"{float(camera.times[0, 0]):.2f}", fraction(moving[-1]), float(static[-1].mean()), samples[-1]))
        rows.append(("all", fraction(np.concatenate(moving)), float(np.concatenate(static).mean()), float(np.mean(samples))))
        return rows


def fraction(selected: np.ndarray) -> Optional[float]:
    """Mean of a boolean array; None when it is empty."""
    return float(selected.mean()) if selected.size else None


if __name__ == "__main__":
    tyro.cli(GearAssignmentBenchmark).main()
