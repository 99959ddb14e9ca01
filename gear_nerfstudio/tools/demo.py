"""`ns-gear-demo`: the whole job on built-in data, through the real nerfstudio commands.

Generates a synthetic scene in the Neural 3D Video format, trains a gear-nerf preset on it with
`ns-train` (CPU by default), evaluates the held-out camera with `ns-eval`, renders a spiral video
sweeping time 0 -> 1 with `ns-render`, writes a fixed-view time sweep with `ns-gear-path` and renders it with
`ns-render camera-path`, and prints where everything is.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Literal

import tyro

from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.tools.commands import run_command
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene


@dataclasses.dataclass
class DemoCommand:
    """Train, evaluate and render gear-nerf on a generated synthetic scene."""

    output: Path = Path("outputs/demo")
    method: str = "gear-nerf-small"
    iterations: int = 1500
    device: Literal["cpu", "cuda"] = "cpu"
    width: int = 64
    height: int = 48
    frames: int = 6
    cameras: int = 8

    def main(self) -> None:
        started = time.time()
        scene = self.output / "scene"
        write_synthetic_scene(
            scene, SyntheticSpec(dataset="n3d", width=self.width, height=self.height, frames=self.frames, cameras=self.cameras)
        )
        print(f"[demo] wrote a synthetic N3D scene ({self.cameras} cameras, {self.frames} frames) to {scene}")

        runs = self.output / "runs"
        run_command(
            [
                "ns-train", self.method,
                "--output-dir", str(runs), "--experiment-name", "demo", "--timestamp", "demo",
                "--max-num-iterations", str(self.iterations), *schedule_options(self.iterations),
                "--steps-per-eval-all-images", "1000000",
                "--machine.device-type", self.device, "--vis", "tensorboard",
                "--pipeline.datamanager.sam-cache-dir", str(self.output / "sam-cache"),
                "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(self.output / "cache"),
            ],
            "demo",
        )
        config = runs / "demo" / self.method / "demo" / "config.yml"
        metrics = self.output / "metrics.json"
        video = self.output / "video.mp4"
        sweep_path, sweep = self.output / "time_sweep.json", self.output / "time_sweep.mp4"
        run_command(["ns-eval", "--load-config", str(config), "--output-path", str(metrics)], "demo")
        run_command(
            [
                "ns-render", "spiral", "--load-config", str(config), "--output-path", str(video),
                "--seconds", "3", "--frame-rate", "10", "--radius", "0.05",
            ],
            "demo",
        )
        run_command(
            [
                "ns-gear-path", "time-sweep", "--load-config", str(config), "--output-path", str(sweep_path),
                "--frames", "30", "--fps", "10",
            ],
            "demo",
        )
        run_command(
            [
                "ns-render", "camera-path", "--load-config", str(config), "--camera-path-filename", str(sweep_path),
                "--output-path", str(sweep),
            ],
            "demo",
        )
        results = json.loads(metrics.read_text())["results"]
        shown = ", ".join(f"{k} {v:.4g}" for k, v in results.items() if not k.endswith("_std"))
        print(f"[demo] held-out camera cam00: {shown}")
        print(f"[demo] video:   {video} (a spiral around cam00 while time runs 0 -> 1)")
        print(f"[demo] video:   {sweep} (cam00 held still while time runs 0 -> 1)")
        print(f"[demo] metrics: {metrics}")
        print(f"[demo] config:  {config}  (open with: ns-viewer --load-config {config})")
        print(f"[demo] done in {time.time() - started:.0f} s")


def entrypoint() -> None:
    tyro.cli(DemoCommand).main()


if __name__ == "__main__":
    entrypoint()
