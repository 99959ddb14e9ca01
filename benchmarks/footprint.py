"""What a scene costs: parameters (all, and in use), gear levels used, checkpoint size and peak RSS of training, on
synthetic scenes (static, mixed, a long low-resolution video). Writes ``<output>/footprint.md``."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import List, Tuple

import torch

from benchmarks.common import BIN, page, run_measured, table, write_report
from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene


@dataclasses.dataclass
class Run:
    """One training run: a label, the preset, the synthetic scene, iterations."""

    name: str
    method: str
    spec: SyntheticSpec
    iterations: int


@dataclasses.dataclass
class Footprint:
    """Train each run of ``runs`` with ns-train and measure what it costs."""

    output: Path = Path("outputs/footprint")

    def runs(self) -> List[Run]:
        """600 iterations on the static and mixed scenes (the gear-update schedule scaled to them), 300 on the long
        video (enough to cycle through the datamanager's image subsets)."""
        short = dict(dataset="n3d", width=64, height=48, frames=6, cameras=6)
        runs = [Run(motion, method, SyntheticSpec(motion=motion, **short), 600)
                for motion in ("static", "mixed") for method in ("gear-nerf-small", "gear-nerf-baseline")]
        long = SyntheticSpec(dataset="n3d", width=32, height=24, frames=300, cameras=20)
        return runs + [Run("long (20 cameras x 300 frames)", "gear-nerf-small", long, 300)]

    def main(self) -> None:
        rows = []
        for run in self.runs():
            total, in_use, gears, checkpoint, rss = self.measure(run)
            rows.append([run.name, run.method, run.iterations, total, in_use, gears, f"{checkpoint / 2**20:.1f}",
                         f"{rss / 2**20:.0f}"])  # fmt: skip
            print(rows[-1], flush=True)
        header = ["scene", "method", "iterations", "parameters", "in use", "gears used", "checkpoint MiB",
                  "peak RSS MiB"]
        write_report(page("What a scene costs", table(header, rows)), self.output / "footprint.md")

    def measure(self, run: Run) -> Tuple[int, int, str, int, int]:
        key = f"{run.spec.motion}-{run.spec.frames}x{run.spec.cameras}"
        scene = self.output / f"scene-{key}"
        if not (scene / "poses_bounds.npy").exists():
            write_synthetic_scene(scene, run.spec)
        runs = self.output / "runs"
        runs.mkdir(parents=True, exist_ok=True)
        command = [
            str(BIN / "ns-train"), run.method, "--output-dir", str(runs), "--experiment-name", key,
            "--timestamp", "run", "--max-num-iterations", str(run.iterations), *schedule_options(run.iterations),
            "--machine.device-type", "cpu",
            "--vis", "tensorboard", "--steps-per-eval-all-images", "1000000", "--steps-per-eval-image", "1000000",
            "--steps-per-eval-batch", "1000000", "neural-3d-video-data", "--data", str(scene),
            "--cache-dir", str(self.output / "cache"),
        ]
        usage = run_measured(command, runs / f"{key}-{run.method}.log")
        folder = runs / key / run.method / "run"
        checkpoint = sorted((folder / "nerfstudio_models").glob("step-*.ckpt"))[-1]
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)["pipeline"]
        field_state = {k[len("_model.field."):]: v for k, v in state.items() if k.startswith("_model.field.")}
        used = field_state["used_columns"].flatten(1).any(dim=1)  # GearField.used_gears
        unused_planes = sum(
            v.numel() for k, v in field_state.items()
            if k.startswith("time_planes.") and not bool(used[int(k.split(".")[1])])
        )
        total = sum(v.numel() for k, v in field_state.items() if v.is_floating_point() and k != "aabb")
        gears = ",".join(str(g + 1) for g in range(len(used)) if bool(used[g]))
        # ru_maxrss is in KiB on Linux.
        return total, total - unused_planes, gears, checkpoint.stat().st_size, usage.ru_maxrss * 1024

