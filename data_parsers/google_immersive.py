"""Google Immersive light-field video (DeepView): `camera_XXXX.mp4` + `models.json`.

models.json is a list of cameras with `name, width, height, position` (centre), `orientation`
(axis-angle of the world-to-camera rotation, OpenCV axes), `focal_length, principal_point,
pixel_aspect_ratio` (fy = focal * aspect), `radial_distortion [k1, k2(, k3)]` and
`projection_type` 'fisheye': theta_d = theta (1 + k1 theta^2 + k2 theta^4 (+ k3 theta^6)), which is
nerfstudio's CameraType.FISHEYE with distortion [k1, k2, k3, 0, 0, 0]. Held out: camera_0001.
The rig looks outward at an unbounded scene: the files carry no bounds, so near/far come from the
config (published per scene, e.g. Horse 0.5 / 45, Flames 1 / 10).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Type

import numpy as np
from nerfstudio.cameras.cameras import CameraType
from nerfstudio.utils.rich_utils import CONSOLE
from scipy.spatial.transform import Rotation

from gear_nerfstudio.data_parsers.multiview import MultiViewVideoDataParserConfig, ParsedRig
from gear_nerfstudio.data_parsers.video_rig import VideoRigDataParser
from gear_nerfstudio.data.errors import DatasetError

VIDEO_PATTERN = re.compile(r"^camera_\d{4}\.mp4$")
REQUIRED_KEYS = (
    "name",
    "width",
    "height",
    "position",
    "orientation",
    "focal_length",
    "principal_point",
    "pixel_aspect_ratio",
    "radial_distortion",
    "projection_type",
)


@dataclass
class GoogleImmersiveDataParserConfig(MultiViewVideoDataParserConfig):
    """Google Immersive (DeepView) fisheye multi-view videos."""

    _target: Type = field(default_factory=lambda: GoogleImmersiveDataParser)
    near: float = 0.5
    """Near bound in the calibration's units (models.json carries none)."""
    far: float = 45.0
    """Far bound; the scene is treated as unbounded beyond sqrt(near * far) around the rig."""


class GoogleImmersiveDataParser(VideoRigDataParser):
    config: GoogleImmersiveDataParserConfig
    default_held_out = "camera_0001"
    parser_name = "google-immersive-data"

    def read_rig(self) -> ParsedRig:
        folder = self.config.data
        if not folder.is_dir():
            raise DatasetError(f"{folder}: the scene folder does not exist")
        models = _read_models(folder / "models.json")
        videos = {p.stem: p for p in folder.iterdir() if VIDEO_PATTERN.match(p.name)}
        if not videos:
            raise DatasetError(f"{folder}: no videos named camera_XXXX.mp4")
        without_video = [m["name"] for m in models if m["name"] not in videos]
        without_model = sorted(set(videos) - {m["name"] for m in models})
        if without_video:
            CONSOLE.print(f"[yellow]{folder}: skipping cameras in models.json without a video: {without_video}")
        if without_model:
            CONSOLE.print(f"[yellow]{folder}: skipping videos with no entry in models.json: {without_model}")
        models = sorted((m for m in models if m["name"] in videos), key=lambda m: m["name"])
        if not models:
            raise DatasetError(f"{folder / 'models.json'}: no camera matches a video file")
        infos = self.open_videos(folder, [videos[m["name"]] for m in models])

        n = len(models)
        c2w = np.zeros((n, 3, 4))
        fx, fy, cx, cy, distortion = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 6))
        for i, (model, info) in enumerate(zip(models, infos)):
            rotation_cv = Rotation.from_rotvec(model["orientation"]).as_matrix().T  # camera-to-world
            c2w[i, :, :3] = rotation_cv * np.array([1.0, -1.0, -1.0])  # OpenCV -> OpenGL axes
            c2w[i, :, 3] = model["position"]
            sx, sy = info.width / model["width"], info.height / model["height"]
            fx[i] = model["focal_length"] * sx
            fy[i] = model["focal_length"] * model["pixel_aspect_ratio"] * sy
            cx[i] = model["principal_point"][0] * sx
            cy[i] = model["principal_point"][1] * sy
            distortion[i, : len(model["radial_distortion"])] = model["radial_distortion"]
        return ParsedRig(
            names=[m["name"] for m in models],
            camera_to_worlds=c2w,
            fx=fx,
            fy=fy,
            cx=cx,
            cy=cy,
            width=np.array([info.width for info in infos]),
            height=np.array([info.height for info in infos]),
            camera_type=CameraType.FISHEYE,
            distortion=distortion,
            near=self.config.near,
            far=self.config.far,
            unbounded=True,
            frame_numbers=list(range(infos[0].num_frames)),
        )


def _read_models(path: Path) -> List[dict]:
    if not path.is_file():
        raise DatasetError(f"{path}: the camera file is missing")
    try:
        models = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"{path}: cannot read the camera file ({err})") from err
    if not isinstance(models, list) or not models:
        raise DatasetError(f"{path}: expected a non-empty list of cameras")
    for index, model in enumerate(models):
        if not isinstance(model, dict):
            raise DatasetError(f"{path}: entry {index} is not an object")
        missing = [key for key in REQUIRED_KEYS if key not in model]
        if missing:
            raise DatasetError(f"{path}: camera {model.get('name', index)!r} lacks {missing}")
        if model["projection_type"] != "fisheye":
            raise DatasetError(
                f"{path}: camera {model['name']!r} has projection_type {model['projection_type']!r}; "
                "only 'fisheye' is supported"
            )
        if len(model["radial_distortion"]) > 3 or len(model["orientation"]) != 3 or len(model["position"]) != 3:
            raise DatasetError(f"{path}: camera {model['name']!r} has malformed orientation/position/distortion")
    return models
