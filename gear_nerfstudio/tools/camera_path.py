"""`ns-gear-path`: camera paths with times, from the dataset's own cameras, for `ns-render camera-path`.

nerfstudio's `ns-render interpolate` drops the cameras' times (every frame is rendered at time 0) and its
viewer's path editor is drawn by hand. This command writes the two paths users of a video ask for, in
nerfstudio's camera-path JSON (``render_time`` per frame), which `ns-render camera-path` renders and
`ns-gear-track --target-camera-path` tracks into:

- ``time-sweep``: one camera of the rig held still while time runs from ``--start-time`` to ``--end-time``
  (default: the held-out camera over the whole window, one path frame per video frame);
- ``through-cameras``: through the named cameras in order (poses interpolated as ``ns-render interpolate``
  does: rotations by slerp, centres linearly) while time runs from ``--start-time`` to ``--end-time``.

Poses come from the run's dataparser (the same normalised world as training); no model is loaded.
"""

from __future__ import annotations

import json
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch
import tyro
import yaml
from nerfstudio.cameras.camera_utils import get_interpolated_poses
from nerfstudio.cameras.cameras import Cameras, CameraType
from typing_extensions import Annotated

from gear_nerfstudio.data_parsers.multiview import cameras_by_name
from gear_nerfstudio.errors import InputError


class PathError(InputError):
    """A camera path that cannot be made from these arguments."""


def rig_cameras(load_config: Path) -> Tuple[Dict[str, Cameras], List[str], int]:
    """One camera per dataset camera name, the held-out names and the number of frames T of the run's window."""
    try:
        config = yaml.load(load_config.read_text(), Loader=yaml.Loader)
        dataparser_config = config.pipeline.datamanager.dataparser
    except (OSError, yaml.YAMLError, AttributeError) as err:
        raise PathError(f"{load_config}: not a readable ns-train config.yml ({err})") from err
    if config.pipeline.datamanager.data is not None:
        dataparser_config.data = config.pipeline.datamanager.data
    dataparser = dataparser_config.setup()
    cameras: Dict[str, Cameras] = {}
    held_out: List[str] = []
    num_frames = 1
    for split in ("train", "test"):
        outputs = dataparser.get_dataparser_outputs(split)
        num_frames = int(outputs.metadata.get("num_frames", 1))
        named = cameras_by_name(outputs.cameras, outputs.metadata)
        if split == "test":
            held_out = [name for name in named if name not in cameras]
        for name, camera in named.items():
            cameras.setdefault(name, camera)
    return cameras, held_out, num_frames


def path_json(cameras: Cameras, poses: torch.Tensor, times: np.ndarray, fps: float) -> dict:
    """nerfstudio's camera-path JSON: `poses` (N, 3, 4) with `cameras[0]`'s image size and field of view."""
    width, height = int(cameras.width[0]), int(cameras.height[0])
    fov = math.degrees(2.0 * math.atan(height / (2.0 * float(cameras.fy[0]))))
    frames = []
    for pose, time in zip(poses, times):
        c2w = np.eye(4)
        c2w[:3] = pose.numpy()
        frames.append({"camera_to_world": c2w.ravel().tolist(), "fov": fov, "aspect": width / height, "render_time": float(time)})
    fisheye = int(cameras.camera_type[0]) == CameraType.FISHEYE.value
    return {
        "camera_type": "fisheye" if fisheye else "perspective",
        "render_width": width,
        "render_height": height,
        "fps": fps,
        "seconds": len(frames) / fps,
        "camera_path": frames,
    }


@dataclass
class PathCommand(ABC):
    """Options shared by both paths."""

    load_config: Path
    """config.yml of an ns-train run."""
    output_path: Path = Path("camera_paths/path.json")
    """Where the camera-path JSON is written."""
    start_time: float = 0.0
    """Time of the first frame, in [0, 1]."""
    end_time: float = 1.0
    """Time of the last frame, in [0, 1]."""
    fps: float = 30.0
    """Frame rate of the rendered video (the datasets are 30 fps)."""

    def main(self) -> None:
        for value in (self.start_time, self.end_time):
            if not 0.0 <= value <= 1.0:
                raise PathError(f"times must lie in [0, 1], got {value}")
        cameras, held_out, num_frames = rig_cameras(self.load_config)
        first, poses = self.poses(cameras, held_out, num_frames)
        times = np.linspace(self.start_time, self.end_time, len(poses))
        self.output_path.parent.mkdir(parents=True, exist_ok=True)
        self.output_path.write_text(json.dumps(path_json(first, poses, times, self.fps), indent=1))
        print(
            f"Wrote {self.output_path}: {len(poses)} frames, time {self.start_time:g} -> {self.end_time:g}. Render it with\n"
            f"  ns-render camera-path --load-config {self.load_config} --camera-path-filename {self.output_path} "
            f"--output-path renders/{self.output_path.stem}.mp4"
        )

    @abstractmethod
    def poses(self, cameras: Dict[str, Cameras], held_out: List[str], num_frames: int) -> Tuple[Cameras, torch.Tensor]:
        """The camera whose image size and field of view the path takes, and the path's poses (N, 3, 4)."""


def named(cameras: Dict[str, Cameras], name: str) -> Cameras:
    if name not in cameras:
        raise PathError(f"unknown camera {name!r}; cameras: {sorted(cameras)}")
    return cameras[name]


@dataclass
class TimeSweep(PathCommand):
    """A fixed view of the whole video: one rig camera, time running from --start-time to --end-time."""

    camera: Optional[str] = None
    """Camera to hold; default: the held-out camera."""
    frames: Optional[int] = None
    """Frames of the path; default: one per video frame in the time range."""

    def poses(self, cameras: Dict[str, Cameras], held_out: List[str], num_frames: int) -> Tuple[Cameras, torch.Tensor]:
        camera = named(cameras, self.camera or held_out[0])
        count = self.frames or max(2, round(abs(self.end_time - self.start_time) * (num_frames - 1)) + 1)
        return camera, camera.camera_to_worlds[0].expand(count, 3, 4)


@dataclass
class ThroughCameras(PathCommand):
    """A path through rig cameras in the given order while time runs from --start-time to --end-time."""

    cameras: Tuple[str, ...] = ()
    """Cameras to pass through, in order (at least two)."""
    frames_per_camera: int = 30
    """Frames from one camera to the next."""

    def poses(self, cameras: Dict[str, Cameras], held_out: List[str], num_frames: int) -> Tuple[Cameras, torch.Tensor]:
        if len(self.cameras) < 2:
            raise PathError("give at least two cameras to pass through (--cameras A B ...)")
        if self.frames_per_camera < 1:
            raise PathError(f"--frames-per-camera must be at least 1, got {self.frames_per_camera}")
        keys = [named(cameras, name).camera_to_worlds[0].numpy() for name in self.cameras]
        poses: List[np.ndarray] = []
        for start, end in zip(keys[:-1], keys[1:]):
            poses += get_interpolated_poses(start, end, steps=self.frames_per_camera + 1)[:-1]
        poses.append(keys[-1])
        return cameras[self.cameras[0]], torch.from_numpy(np.stack(poses)).float()


Commands = Union[
    Annotated[TimeSweep, tyro.conf.subcommand(name="time-sweep")],
    Annotated[ThroughCameras, tyro.conf.subcommand(name="through-cameras")],
]


def entrypoint() -> None:
    """Console script; bad input is reported in one line (``gear_nerfstudio.errors``)."""
    tyro.cli(Commands).main()


if __name__ == "__main__":
    entrypoint()
