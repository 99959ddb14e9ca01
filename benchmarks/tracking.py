"""Free-viewpoint tracking (Sec 4.5) from one click, measured against ground-truth object masks.

Writes a synthetic N3D scene with moving spheres, trains a preset with `ns-train`, clicks the fast
sphere at the middle of its ground-truth mask in a training camera at one time, and runs
`ns-gear-track` to the held-out camera cam00 at every frame time. Reports mIoU / accuracy (cam00 at the
clicked time) and t-mIoU / t-accuracy (cam00 at the other times), as the paper's tracking table. For
reference it also decodes the same prompts (the projected click, then the boxes ns-gear-track used) on
the SAM backend's encoder features of cam00's real frames: what the backend gives without the NeRF.

    .venv/bin/python benchmarks/tracking.py --output outputs/tracking

Prints a markdown table and writes it to `<output>/tracking.md`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import tyro
from scipy import ndimage

from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.synthetic.writers import SyntheticSpec, write_synthetic_scene
from gear_nerfstudio.track_metrics import accuracy, iou
from gear_nerfstudio.tracking import segment


@dataclasses.dataclass
class TrackingBenchmark:
    output: Path = Path("outputs/tracking")
    method: str = "gear-nerf-small"
    iterations: int = 1500
    width: int = 64
    height: int = 48
    frames: int = 6
    cameras: int = 8
    motion: str = "mixed"
    click_camera: str = "cam01"
    click_frame: int = 2
    target_object: int = 3
    """Object id to click (mixed scene: 1 static, 2 slow, 3 fast sphere)."""

    def main(self) -> None:
        scene = self.output / "scene"
        spec = SyntheticSpec(
            dataset="n3d", width=self.width, height=self.height, frames=self.frames, cameras=self.cameras,
            motion=self.motion,
        )
        write_synthetic_scene(scene, spec)
        started = time.time()
        config = self.train(scene)
        trained = time.time()
        x, y = self.click_pixel(scene)
        click_time = self.click_frame / (self.frames - 1)
        result_dir = self.output / "track"
        self.ns(
            "ns-gear-track", "--load-config", str(config), "--output-dir", str(result_dir), "--overwrite",
            "--click-camera", self.click_camera, "--click-time", str(click_time), "--positive", str(x), str(y),
            "--target-cameras", "cam00",
        )
        tracked = time.time()
        summary = json.loads((result_dir / "tracking.json").read_text())
        reference = self.reference(scene, summary)
        table = self.table(summary, reference, (x, y), click_time)
        table += (
            f"\n\nTraining {trained - started:.0f} s, tracking (model load, {len(summary['masks'])} masks, "
            f"overlay video) {tracked - trained:.0f} s, wall clock.\n"
        )
        print(table)
        (self.output / "tracking.md").write_text(table)

    def ns(self, *args: str, log: Optional[Path] = None) -> None:
        bin_dir = Path(sys.executable).parent
        env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
        if log is None:
            subprocess.run([str(bin_dir / args[0]), *args[1:]], check=True, env=env)
            return
        with open(log, "w") as handle:
            subprocess.run(
                [str(bin_dir / args[0]), *args[1:]], check=True, env=env, stdout=handle, stderr=subprocess.STDOUT
            )

    def train(self, scene: Path) -> Path:
        runs = self.output / "runs"
        runs.mkdir(parents=True, exist_ok=True)
        self.ns(
            "ns-train", self.method, "--output-dir", str(runs), "--experiment-name", "tracking", "--timestamp",
            "run", "--max-num-iterations", str(self.iterations), "--machine.device-type", "cpu", "--vis",
            "tensorboard", "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(self.output / "cache"),
            log=runs / "train.log",
        )
        return runs / "tracking" / self.method / "run" / "config.yml"

    def click_pixel(self, scene: Path) -> Tuple[float, float]:
        """The pixel centre deepest inside the target object's ground-truth mask at the clicked frame."""
        ids = np.load(scene / "ground_truth" / f"{self.click_camera}.npz")["object_ids"][self.click_frame]
        inside = ids == self.target_object
        if not inside.any():
            raise SystemExit(f"object {self.target_object} is not visible in {self.click_camera} frame {self.click_frame}")
        depth = ndimage.distance_transform_edt(inside)
        row, col = np.unravel_index(int(np.argmax(depth)), depth.shape)
        return col + 0.5, row + 0.5

    def reference(self, scene: Path, summary: Dict) -> Dict[float, Tuple[float, float]]:
        """IoU and accuracy of the same prompts decoded on the encoder features of cam00's real frames."""
        import av

        with av.open(str(scene / "cam00.mp4")) as container:
            frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
        ids = np.load(scene / "ground_truth" / "cam00.npz")["object_ids"]
        backend = BuiltinSamBackend()
        results = {}
        for record in summary["masks"]:
            frame = round(record["time"] * (self.frames - 1))
            embedding = backend.encode(frames[frame])
            prompt = record["prompt"]
            if "points" in prompt:
                mask = segment(backend, embedding, np.array(prompt["points"]), np.array(prompt["labels"]))
            elif prompt["box"] is not None:
                mask = segment(backend, embedding, np.zeros((0, 2)), np.zeros(0), np.array(prompt["box"]))
            else:
                mask = np.zeros(ids.shape[1:], dtype=bool)
            truth = ids[frame] == self.target_object
            results[record["time"]] = (iou(mask, truth), accuracy(mask, truth))
        return results

    def table(self, summary: Dict, reference: Dict, pixel: Tuple[float, float], click_time: float) -> str:
        metrics = summary["metrics"]
        at_click = [v for t, v in reference.items() if t == click_time]
        other = [v for t, v in reference.items() if t != click_time]

        def pct(value) -> str:
            return "n/a" if value is None else f"{100 * value:.1f}"

        def mean(values: List[Tuple[float, float]], index: int):
            return float(np.mean([v[index] for v in values])) if values else None

        lines = [
            f"Click: {self.click_camera} pixel ({pixel[0]}, {pixel[1]}) at time {click_time:.2f} "
            f"(frame {self.click_frame}) on object {self.target_object}; target: held-out cam00, "
            f"{len(summary['times'])} times.",
            "",
            "| masks from | mIoU | Acc. | t-mIoU | t-Acc. |",
            "|---|---|---|---|---|",
            f"| Gear-NeRF rendered SAM features (ns-gear-track) | {pct(metrics['mIoU'])} | {pct(metrics['accuracy'])} "
            f"| {pct(metrics['t-mIoU'])} | {pct(metrics['t-accuracy'])} |",
            f"| same prompts on the encoder features of cam00's real frames | {pct(mean(at_click, 0))} "
            f"| {pct(mean(at_click, 1))} | {pct(mean(other, 0))} | {pct(mean(other, 1))} |",
            "",
            "| time | IoU | Acc. | prompt |",
            "|---|---|---|---|",
        ]
        for record in summary["masks"]:
            kind = "click" if "points" in record["prompt"] else f"box from t={record['prompt']['from_time']:.2f}"
            lines.append(f"| {record['time']:.2f} | {pct(record.get('iou'))} | {pct(record.get('accuracy'))} | {kind} |")
        return "\n".join(lines)


if __name__ == "__main__":
    tyro.cli(TrackingBenchmark).main()
