"""Neural 3D Video (DyNeRF): `camXX.mp4` + `poses_bounds.npy` (N, 17), LLFF convention.

Rows of poses_bounds.npy follow the sorted existing videos. `P = a[:, :15].reshape(N, 3, 5)`:
columns 0-2 are the camera-to-world rotation with axes [down, right, back], column 3 the centre,
column 4 `[H, W, focal]` at the calibrated resolution; `a[:, 15:17]` are near and far. OpenGL axes
are [right, up, back] = [P1, -P0, P2]; cx = W/2, cy = H/2. Intrinsics are scaled to the video size.
Held out: cam00. coffee_martini's cam13 is not synchronised and is excluded by default.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Optional, Tuple, Type

import numpy as np
from nerfstudio.cameras.cameras import CameraType

from gear_nerfstudio.data_parsers.multiview import MultiViewVideoDataParserConfig, ParsedRig
from gear_nerfstudio.data_parsers.video_rig import VideoRigDataParser
from gear_nerfstudio.data.errors import DatasetError

VIDEO_PATTERN = re.compile(r"^cam\d{2}\.mp4$")
UNSYNCHRONISED = {"coffee_martini": ("cam13",)}


@dataclass
class Neural3DVideoDataParserConfig(MultiViewVideoDataParserConfig):
    """Neural 3D Video (DyNeRF) multi-view videos."""

    _target: Type = field(default_factory=lambda: Neural3DVideoDataParser)
    exclude_cameras: Optional[Tuple[str, ...]] = None
    """Cameras to leave out; default: the known unsynchronised ones (coffee_martini: cam13)."""


class Neural3DVideoDataParser(VideoRigDataParser):
    config: Neural3DVideoDataParserConfig
    default_held_out = "cam00"
    parser_name = "neural-3d-video-data"

    def read_rig(self) -> ParsedRig:
        folder = self.config.data
        if not folder.is_dir():
            raise DatasetError(f"{folder}: the scene folder does not exist")
        videos = sorted(p for p in folder.iterdir() if VIDEO_PATTERN.match(p.name))
        if not videos:
            raise DatasetError(f"{folder}: no videos named camXX.mp4")
        poses_path = folder / "poses_bounds.npy"
        if not poses_path.is_file():
            raise DatasetError(f"{poses_path}: the poses file is missing")
        try:
            poses_bounds = np.load(poses_path)
        except (OSError, ValueError) as err:
            raise DatasetError(f"{poses_path}: cannot read the poses file ({err})") from err
        if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
            raise DatasetError(f"{poses_path}: shape {poses_bounds.shape}, expected (N, 17)")
        if len(poses_bounds) != len(videos):
            raise DatasetError(
                f"{poses_path}: {len(poses_bounds)} pose rows, but {len(videos)} videos camXX.mp4 "
                f"({videos[0].name}..{videos[-1].name}); rows must follow the sorted videos"
            )

        excluded = self.config.exclude_cameras
        if excluded is None:
            excluded = UNSYNCHRONISED.get(folder.name, ())
        keep = [i for i, v in enumerate(videos) if v.stem not in excluded]
        videos = [videos[i] for i in keep]
        poses_bounds = poses_bounds[keep]

        infos = self.open_videos(folder, videos)

        pose = poses_bounds[:, :15].reshape(-1, 3, 5)
        c2w = np.concatenate([pose[:, :, 1:2], -pose[:, :, 0:1], pose[:, :, 2:4]], axis=2)
        calib_h, calib_w, focal = pose[:, 0, 4], pose[:, 1, 4], pose[:, 2, 4]
        width = np.array([info.width for info in infos])
        height = np.array([info.height for info in infos])
        return ParsedRig(
            names=[v.stem for v in videos],
            camera_to_worlds=c2w,
            fx=focal * width / calib_w,
            fy=focal * height / calib_h,
            cx=width / 2.0,
            cy=height / 2.0,
            width=width,
            height=height,
            camera_type=CameraType.PERSPECTIVE,
            distortion=None,
            near=float(poses_bounds[:, 15].min()),
            far=float(poses_bounds[:, 16].max()),
            unbounded=False,
            frame_numbers=list(range(infos[0].num_frames)),
        )
