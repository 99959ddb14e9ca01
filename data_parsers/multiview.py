"""What the three multi-view video parsers share: frame window, times, split, scaling, outputs.

Each dataset parser reads its own files into a `ParsedRig` (cameras in nerfstudio conventions, in the
dataset's world units) and says where its frames are; this module turns that into `DataparserOutputs`:

- times: frame index within the loaded window / (T - 1), 0 when T = 1;
- split: train = every camera but the held-out one; val = test = the held-out camera, all frames;
- world: rotated so the mean camera up is +z and the held-out camera looks along -y (the frame nerfstudio's
  spiral path assumes: its cameras come out upright), centred and scaled so the region the cameras observe
  fits the scene box [-1, 1]^3 (forward-facing rigs: their frusta between near and far; rigs that
  surround their scene, such as a dome: the box of the camera centres; unbounded rigs: a ball of
  radius sqrt(near * far) around the rig, with `unbounded` set for the model to contract what lies
  outside);
- metadata: near, far (scaled), unbounded, num_frames, camera_ids and frame_ids per image,
  camera_names and frame_numbers (the dataset's own names and frame numbers);
- each camera's rig index in its `Cameras.metadata` (`RIG_CAMERA`), which rays carry to the model's per-camera
  appearance codes.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data.layouts import layout_hint
from gear_nerfstudio.fields.appearance import RIG_CAMERA
from gear_nerfstudio.model.moving_region import mask_path


@dataclass
class MultiViewVideoDataParserConfig(DataParserConfig):
    """Options shared by the multi-view video parsers."""

    _target: Type = field(default_factory=lambda: MultiViewVideoDataParser)
    data: Path = Path()
    """Scene folder, exactly as the dataset distributes it."""
    frame_start: Optional[int] = None
    """First frame of the window (dataset frame number / 0-based video frame); default: the first."""
    frame_count: Optional[int] = None
    """Number of frames in the window; default: up to the last frame."""
    downscale_factor: int = 1
    """Integer image downscale (area filter); intrinsics are scaled to match."""
    held_out_camera: Optional[str] = None
    """Camera used for val/test; default: the dataset's usual held-out camera."""
    cache_dir: Optional[Path] = None
    """Where decoded/downscaled frames are cached; default ~/.cache/gear-nerfstudio/frames."""
    orientation_method: str = "up"
    """'up': rotate so the mean camera up is +z (nerfstudio's viewer convention); 'none': keep axes."""
    scene_box: Literal["auto", "frusta", "rig"] = "auto"
    """What the scene box fits (bounded rigs): 'frusta', the view frusta from near to far;
    'rig', the camera centres, 10 % larger; 'auto': 'rig' for a rig around its scene."""
    skip_damaged_frames: bool = False
    """Leave damaged frames (decoder errors, broken image files) out, with one warning line each, instead of
    stopping with an error."""
    moving_masks: Optional[Path] = None
    """Masks of the held-out camera's moving region, ``<folder>/<camera>/<frame:05d>.png``
    (non-zero: moving); None: the pixels whose colour changes over the window."""


@dataclass
class ParsedRig:
    """The cameras of a rig in nerfstudio conventions (camera-to-world, OpenGL axes), dataset units."""

    names: List[str]
    camera_to_worlds: np.ndarray  # (N, 3, 4)
    fx: np.ndarray  # (N,)
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: np.ndarray  # (N,) int, of the frames as stored
    height: np.ndarray
    camera_type: CameraType
    distortion: Optional[np.ndarray]  # (N, 6) nerfstudio order [k1, k2, k3, k4, p1, p2]
    near: float
    far: float
    unbounded: bool
    frame_numbers: List[int]  # frames available for every camera, ascending


class MultiViewVideoDataParser(DataParser):
    """Base of the three parsers; subclasses read their files."""

    config: MultiViewVideoDataParserConfig
    includes_time: bool = True
    default_held_out: str = ""
    parser_name: str = ""
    """The parser's ns-train subcommand."""

    def __init__(self, config: MultiViewVideoDataParserConfig):
        super().__init__(config)
        self.includes_time = True

    @abstractmethod
    def read_rig(self) -> ParsedRig:
        """Read the calibration and list the frames, validating both."""

    @abstractmethod
    def frame_files(
        self, rig: ParsedRig, cameras: Sequence[int], frames: Sequence[int], sizes: Sequence[Tuple[int, int]]
    ) -> List[List[Optional[Path]]]:
        """Image files [camera][frame] of the given frame numbers at the given (width, height) sizes; None for a
        damaged frame left out (``skip_damaged_frames``)."""

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        if self.config.downscale_factor < 1:
            raise DatasetError(f"downscale_factor must be >= 1, got {self.config.downscale_factor}")
        try:
            rig = self.read_rig()
        except DatasetError as err:
            raise DatasetError(f"{err}{layout_hint(self.config.data, self.parser_name)}") from err
        frames = self.window(rig)
        held_out_name = self.config.held_out_camera or self.default_held_out
        if held_out_name not in rig.names:
            raise DatasetError(f"{self.config.data}: held-out camera {held_out_name!r} not found; cameras: {rig.names}")
        held_out = rig.names.index(held_out_name)
        if split == "train":
            cameras = [i for i in range(len(rig.names)) if i != held_out]
            if not cameras:
                raise DatasetError(f"{self.config.data}: only the held-out camera {held_out_name!r} is present")
        else:
            cameras = [held_out]

        sizes = self.image_sizes(rig, cameras)
        files = self.frame_files(rig, cameras, frames, sizes)
        kept = torch.tensor([path is not None for camera_files in files for path in camera_files])
        if not kept.any():
            raise DatasetError(f"{self.config.data}: every {split} frame of the window is damaged")

        if split != "train" and self.config.moving_masks is not None:
            for number in frames:
                mask = mask_path(self.config.moving_masks, held_out_name, number)
                if not mask.is_file():
                    raise DatasetError(f"{mask}: no mask of what moves for the held-out camera at frame {number}")

        transform, scale = _normalisation(rig, self.config.orientation_method, self.config.scene_box, held_out)
        c2w = _apply(transform, scale, torch.from_numpy(rig.camera_to_worlds).float())

        T = len(frames)
        cam_ids = torch.tensor([c for c in cameras for _ in range(T)], dtype=torch.long)
        frame_ids = torch.tensor([j for _ in cameras for j in range(T)], dtype=torch.long)
        sx = torch.tensor([w / float(rig.width[c]) for c, (w, _) in zip(cameras, sizes)])
        sy = torch.tensor([h / float(rig.height[c]) for c, (_, h) in zip(cameras, sizes)])
        per_image_sx = sx.repeat_interleave(T)
        per_image_sy = sy.repeat_interleave(T)

        def column(values: np.ndarray, factor: torch.Tensor) -> torch.Tensor:
            return (torch.from_numpy(values).float()[cam_ids] * factor)[:, None]

        distortion = None
        if rig.distortion is not None:
            distortion = torch.from_numpy(rig.distortion).float()[cam_ids]
        cameras_out = Cameras(
            camera_to_worlds=c2w[cam_ids],
            fx=column(rig.fx, per_image_sx),
            fy=column(rig.fy, per_image_sy),
            cx=column(rig.cx, per_image_sx),
            cy=column(rig.cy, per_image_sy),
            width=torch.tensor([w for w, _ in sizes], dtype=torch.long).repeat_interleave(T)[:, None],
            height=torch.tensor([h for _, h in sizes], dtype=torch.long).repeat_interleave(T)[:, None],
            distortion_params=distortion,
            camera_type=rig.camera_type,
            times=(frame_ids.float() / max(T - 1, 1))[:, None],
            metadata={RIG_CAMERA: cam_ids[:, None]},
        )
        return DataparserOutputs(
            image_filenames=[path for camera_files in files for path in camera_files if path is not None],
            cameras=cameras_out[kept],
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
            dataparser_transform=transform,
            dataparser_scale=scale,
            metadata={
                "near": rig.near * scale,
                "far": rig.far * scale,
                "unbounded": rig.unbounded,
                "num_frames": T,
                "camera_ids": cam_ids[kept],
                "frame_ids": frame_ids[kept],
                "camera_names": list(rig.names),
                "frame_numbers": list(frames),
                "moving_masks": self.config.moving_masks,
            },
        )

    def image_sizes(self, rig: ParsedRig, cameras: Sequence[int]) -> List[Tuple[int, int]]:
        """(width, height) of the given cameras' images after ``downscale_factor``."""
        d = self.config.downscale_factor
        return [(int(rig.width[i]) // d, int(rig.height[i]) // d) for i in cameras]

    def window(self, rig: ParsedRig) -> List[int]:
        """Frame numbers of the configured window (``frame_start``, ``frame_count``), checked against the rig's."""
        available = rig.frame_numbers
        start = available[0] if self.config.frame_start is None else self.config.frame_start
        if start not in available:
            raise DatasetError(
                f"{self.config.data}: frame_start {start} is outside the frames present "
                f"({available[0]}..{available[-1]})"
            )
        first = available.index(start)
        count = len(available) - first if self.config.frame_count is None else self.config.frame_count
        if count < 1:
            raise DatasetError(f"{self.config.data}: frame_count must be >= 1, got {count}")
        if first + count > len(available):
            raise DatasetError(
                f"{self.config.data}: the frame window {start}..{start + count - 1} runs past the end "
                f"(last frame present: {available[-1]})"
            )
        window = available[first : first + count]
        if window[-1] - window[0] != count - 1:
            raise DatasetError(f"{self.config.data}: frames are missing inside the window {window[0]}..{window[-1]}")
        return window


def cameras_by_name(cameras: Cameras, metadata: dict) -> Dict[str, Cameras]:
    """The first image's camera of each dataset camera name in a split (metadata ``camera_names`` and
    ``camera_ids``), in the order the images list them."""
    named: Dict[str, Cameras] = {}
    for index, camera_id in enumerate(metadata["camera_ids"].tolist()):
        named.setdefault(metadata["camera_names"][camera_id], cameras[index : index + 1])
    return named


def surrounds_scene(camera_to_worlds: np.ndarray) -> bool:
    """Whether a rig surrounds its scene: some cameras look against each other (their viewing directions are
    more than 90 degrees apart) and the cameras look, on average, towards the middle of the rig."""
    forward = -camera_to_worlds[:, :, 2]
    forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    centres = camera_to_worlds[:, :, 3]
    inward = centres.mean(axis=0) - centres
    inward = inward / np.linalg.norm(inward, axis=-1, keepdims=True).clip(min=1e-9)
    return bool((forward @ forward.T).min() < 0 and (forward * inward).sum(-1).mean() > 0)


def _facing_minus_y(rotation: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """`rotation` followed by the turn about +z that makes the camera look along -y.

    nerfstudio's spiral path takes the start camera's third column (its backward axis, in world coordinates)
    as the up vector of its camera frame; that vector is the camera's own up only when the camera looks along
    -y in a z-up world. A camera looking (almost) straight up or down has no heading to turn.
    """
    backward = rotation @ camera_to_world[:, 2]
    if np.hypot(backward[0], backward[1]) < 1e-6:
        return rotation
    angle = np.arctan2(backward[0], backward[1])
    turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    return turn @ rotation


def _normalisation(
    rig: ParsedRig, orientation_method: str, scene_box: str, reference: int
) -> Tuple[torch.Tensor, float]:
    """Rotation + translation (3x4) and scale that map the observed region into [-1, 1]^3; with orientation
    'up', the camera `reference` (the held-out one, where ns-render's spiral starts) looks along -y."""
    poses = torch.eye(4).repeat(len(rig.names), 1, 1)
    poses[:, :3, :] = torch.from_numpy(rig.camera_to_worlds).float()
    _, orient = camera_utils.auto_orient_and_center_poses(poses, method=orientation_method, center_method="none")
    rotation = orient[:, :3].double().numpy()
    if orientation_method == "up":
        rotation = _facing_minus_y(rotation, rig.camera_to_worlds[reference])
    centres = rig.camera_to_worlds[:, :, 3] @ rotation.T
    around_rig = scene_box == "rig" or (scene_box == "auto" and surrounds_scene(rig.camera_to_worlds))
    if rig.unbounded or around_rig:
        middle = centres.mean(axis=0)
        half = 1.1 * float(np.abs(centres - middle).max())
        if rig.unbounded:
            half = max(float(np.sqrt(rig.near * rig.far)), half)
    else:
        points = [centres]
        for i in range(len(rig.names)):
            w, h = float(rig.width[i]), float(rig.height[i])
            corners = np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, h / 2]])
            dirs = np.stack(
                [(corners[:, 0] - rig.cx[i]) / rig.fx[i], -(corners[:, 1] - rig.cy[i]) / rig.fy[i], -np.ones(5)], -1
            )
            world_dirs = dirs @ (rotation @ rig.camera_to_worlds[i, :, :3]).T
            for depth in (rig.near, rig.far):
                points.append(centres[i] + depth * world_dirs)
        points = np.concatenate(points)
        lo, hi = points.min(axis=0), points.max(axis=0)
        middle = (lo + hi) / 2
        half = float((hi - lo).max() / 2)
    scale = 1.0 / half
    transform = torch.zeros(3, 4)
    transform[:, :3] = torch.from_numpy(rotation).float()
    transform[:, 3] = torch.from_numpy(-middle).float()
    return transform, scale


def _apply(transform: torch.Tensor, scale: float, c2w: torch.Tensor) -> torch.Tensor:
    """Rotate, translate and scale camera-to-world poses (N, 3, 4) into the normalised scene."""
    rotation, offset = transform[:, :3], transform[:, 3]
    out = torch.empty_like(c2w)
    out[:, :, :3] = rotation @ c2w[:, :, :3]
    out[:, :, 3] = ((c2w[:, :, 3] @ rotation.T) + offset) * scale
    return out
