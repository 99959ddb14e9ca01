"""Technicolor light-field video: `<Scene>_undist_<frame:05d>_<cam:02d>.png` + `cameras_parameters.txt`.

`cameras_parameters.txt`: one header line, then one row per camera (in camera order):
`f cu cv ar sk qw qx qy qz tx ty tz`, with fx = f, fy = f * ar, cx = cu, cy = cv, and (q, t) the
world-to-camera rotation and translation in OpenCV axes. The held-out view is camera 10.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Type

import numpy as np
from nerfstudio.cameras.cameras import CameraType
from PIL import Image
from scipy.spatial.transform import Rotation

from gear_nerfstudio.data_parsers.multiview import (
    MultiViewVideoDataParser,
    MultiViewVideoDataParserConfig,
    ParsedRig,
)
from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data.frame_cache import cache_image_frames

FRAME_PATTERN = re.compile(r"^(?P<scene>.+)_undist_(?P<frame>\d{5})_(?P<cam>\d{2})\.png$")
CAMERA_COLUMNS = 12


@dataclass
class TechnicolorDataParserConfig(MultiViewVideoDataParserConfig):
    """Technicolor light-field video (4x4 rig, pinhole, PNG frames)."""

    _target: Type = field(default_factory=lambda: TechnicolorDataParser)
    near: float = 0.5
    """Near bound in the calibration's units (the files carry none)."""
    far: float = 20.0
    """Far bound in the calibration's units."""


class TechnicolorDataParser(MultiViewVideoDataParser):
    config: TechnicolorDataParserConfig
    default_held_out = "10"
    parser_name = "technicolor-data"

    def read_rig(self) -> ParsedRig:
        folder = self.config.data
        files = self._frames_by_camera(folder)
        rows = _read_camera_rows(folder / "cameras_parameters.txt")
        if len(rows) != len(files):
            raise DatasetError(
                f"{folder / 'cameras_parameters.txt'}: {len(rows)} camera rows, but frames exist for "
                f"{len(files)} cameras ({', '.join(sorted(f'{c:02d}' for c in files))})"
            )
        expected = set(range(len(rows)))
        if set(files) != expected:
            raise DatasetError(
                f"{folder}: camera numbers in the file names are {sorted(files)}, expected 00..{len(rows) - 1:02d}"
            )
        all_numbers = sorted(set().union(*(set(by_frame) for by_frame in files.values())))
        for cam, by_frame in sorted(files.items()):
            missing = [n for n in all_numbers if n not in by_frame]
            if missing:
                raise DatasetError(f"{folder}: camera {cam:02d} has no frame(s) {missing[:10]} that other cameras have")
        self._files = files

        n = len(rows)
        c2w = np.zeros((n, 3, 4))
        sizes = np.zeros((n, 2), dtype=np.int64)
        for cam, row in enumerate(rows):
            f, cu, cv, ar, sk, qw, qx, qy, qz, tx, ty, tz = row
            if abs(sk) > 1e-6 * abs(f):
                raise DatasetError(f"{folder / 'cameras_parameters.txt'}: camera {cam:02d} has skew {sk}; unsupported")
            world_to_cam = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
            rotation_cv = world_to_cam.T
            c2w[cam, :, :3] = rotation_cv * np.array([1.0, -1.0, -1.0])  # OpenCV -> OpenGL axes
            c2w[cam, :, 3] = -rotation_cv @ np.array([tx, ty, tz])
            sizes[cam] = _image_size(files[cam][all_numbers[0]], all_numbers[0])
        rows_arr = np.asarray(rows)
        return ParsedRig(
            names=[f"{cam:02d}" for cam in range(n)],
            camera_to_worlds=c2w,
            fx=rows_arr[:, 0],
            fy=rows_arr[:, 0] * rows_arr[:, 3],
            cx=rows_arr[:, 1],
            cy=rows_arr[:, 2],
            width=sizes[:, 0],
            height=sizes[:, 1],
            camera_type=CameraType.PERSPECTIVE,
            distortion=None,
            near=self.config.near,
            far=self.config.far,
            unbounded=False,
            frame_numbers=all_numbers,
        )

    def frame_files(
        self, rig: ParsedRig, cameras: Sequence[int], frames: Sequence[int], sizes: Sequence[Tuple[int, int]]
    ) -> List[List[Optional[Path]]]:
        images = [[self._files[cam][n] for n in frames] for cam in cameras]
        return cache_image_frames(images, frames, sizes, self.config.cache_dir, self.config.skip_damaged_frames)

    @staticmethod
    def _frames_by_camera(folder: Path) -> Dict[int, Dict[int, Path]]:
        if not folder.is_dir():
            raise DatasetError(f"{folder}: the scene folder does not exist")
        files: Dict[int, Dict[int, Path]] = {}
        scenes = set()
        for path in folder.iterdir():
            match = FRAME_PATTERN.match(path.name)
            if match:
                scenes.add(match["scene"])
                files.setdefault(int(match["cam"]), {})[int(match["frame"])] = path
        if not files:
            raise DatasetError(f"{folder}: no Technicolor frames named <Scene>_undist_<frame:05d>_<cam:02d>.png")
        if len(scenes) > 1:
            raise DatasetError(f"{folder}: frames of several scenes are mixed: {sorted(scenes)}")
        return files


def _read_camera_rows(path: Path) -> List[List[float]]:
    if not path.is_file():
        raise DatasetError(f"{path}: the camera file is missing")
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: cannot read the camera file ({err})") from err
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != CAMERA_COLUMNS:
            raise DatasetError(
                f"{path}: line {number} has {len(parts)} columns, expected {CAMERA_COLUMNS} "
                "(f cu cv ar sk qw qx qy qz tx ty tz)"
            )
        try:
            rows.append([float(v) for v in parts])
        except ValueError as err:
            raise DatasetError(f"{path}: line {number} is not numeric ({err})") from err
    if not rows:
        raise DatasetError(f"{path}: the camera file has no camera rows after its header line")
    return rows


def _image_size(path: Path, frame: int) -> Tuple[int, int]:
    try:
        with Image.open(path) as image:
            return image.size
    except OSError as err:
        raise DatasetError(f"{path}: frame {frame} is damaged: cannot read the image ({err})") from err
