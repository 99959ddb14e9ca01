"""Free-viewpoint tracking (Sec 4.5) from one click per object of a synthetic scene, with ``ns-gear-track`` into the
held-out cam00 at every frame: mIoU / Acc. at the clicked time, t-mIoU / t-Acc. at the others (the paper's table)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from scipy import ndimage

from benchmarks.common import ns, page, pct, table, write_report
from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

OBJECT_NAMES = {1: "static sphere", 2: "slow sphere", 3: "fast sphere"}


@dataclasses.dataclass
class Tracking:
    """Train (or load) a run on a synthetic scene and score tracking from one click per object."""

    output: Path = Path("outputs/tracking")
    iterations: int = 1500
    seed: int = 42
    """Training seed (`--machine.seed`; nerfstudio's default is 42)."""
    width: int = 64
    height: int = 48
    frames: int = 6
    cameras: int = 8
    config: Optional[Path] = None
    """config.yml of a run already trained on `--scene` (skips writing the scene and training)."""
    scene: Optional[Path] = None
    """The synthetic scene folder of `--config`."""
    click_camera: str = "cam01"
    click_frame: int = 2
    objects: Tuple[int, ...] = (2, 3)
    """Object ids to click, one at a time (mixed scene: 1 static, 2 slow, 3 fast sphere)."""

    def main(self) -> None:
        if self.config is not None:
            if self.scene is None:
                raise SystemExit("--config needs --scene, the synthetic scene it was trained on")
            config, scene = self.config, self.scene
            self.frames = len(np.load(scene / "ground_truth" / "cam00.npz")["object_ids"])
        else:
            scene = self.output / "scene"
            write_synthetic_scene(scene, SyntheticSpec(dataset="n3d", width=self.width, height=self.height,
                                                       frames=self.frames, cameras=self.cameras))
            data = ["neural-3d-video-data", "--data", str(scene), "--cache-dir", str(self.output / "cache")]
            config = train_preset(self.output, self.iterations, self.seed, data)
        click_time = self.click_frame / (self.frames - 1)
        rows = []
        for object_id in self.objects:
            x, y = self.click_pixel(scene, object_id)
            summary = track_click(config, self.output / f"track_{object_id}", self.click_camera, click_time, (x, y),
                                  "cam00")  # fmt: skip
            name = f"{OBJECT_NAMES.get(object_id, object_id)} ({object_id})"
            rows.append([name, *(pct(summary["metrics"][k]) for k in ("mIoU", "accuracy", "t-mIoU", "t-accuracy"))])
        lines = [
            f"Run: `{config}`; click in {self.click_camera} at time {click_time:.2f} (frame {self.click_frame}), "
            "one positive click at the ground-truth pixel deepest inside the object; target: held-out cam00 at "
            f"every frame time ({self.frames}).",
            "", *table(["object", "mIoU", "Acc.", "t-mIoU", "t-Acc."], rows),
        ]  # fmt: skip
        write_report(page("Tracking on a synthetic scene", lines), self.output / "tracking.md")

    def click_pixel(self, scene: Path, object_id: int) -> Tuple[float, float]:
        """The pixel centre deepest inside the object's ground-truth mask at the clicked frame."""
        ids = np.load(scene / "ground_truth" / f"{self.click_camera}.npz")["object_ids"][self.click_frame]
        if not (ids == object_id).any():
            raise SystemExit(f"object {object_id} is not visible in {self.click_camera} frame {self.click_frame}")
        return deepest_pixel(ids == object_id)


def train_preset(output: Path, iterations: int, seed: int, options: List[str]) -> Path:
    """Train gear-nerf-small on the CPU with ns-train (``options`` after its own, the dataparser's last) into
    ``<output>/runs/tracking/gear-nerf-small/run``, its log in ``<output>/runs/train.log``; its config.yml."""
    method = "gear-nerf-small"
    runs = output / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    ns(
        "ns-train", method, "--output-dir", str(runs), "--experiment-name", "tracking", "--timestamp", "run",
        "--max-num-iterations", str(iterations), *schedule_options(iterations), "--machine.device-type", "cpu",
        "--machine.seed", str(seed), "--vis", "tensorboard", *options, log=runs / "train.log",
    )  # fmt: skip
    return runs / "tracking" / method / "run" / "config.yml"


def deepest_pixel(mask: np.ndarray) -> Tuple[float, float]:
    """The pixel centre (x, y) deepest inside a mask."""
    row, col = np.unravel_index(int(np.argmax(ndimage.distance_transform_edt(mask))), mask.shape)
    return col + 0.5, row + 0.5


def track_click(
    config: Path, folder: Path, camera: str, click_time: float, pixel: Tuple[float, float], target: str,
    log: Optional[Path] = None,
) -> Dict:
    """`ns-gear-track` of one positive click at `pixel` of `camera` into the `target` camera(s), written to
    `folder` with its overlay videos, the pictures of the tables (its output to `log` when given); returns its
    tracking.json."""
    ns(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(folder), "--overwrite", "--click-camera",
        camera, "--click-time", str(click_time), "--positive", str(pixel[0]), str(pixel[1]), "--target-cameras",
        target, log=log,
    )  # fmt: skip
    return json.loads((folder / "tracking.json").read_text())
