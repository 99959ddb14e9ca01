"""Writing the scene in the Neural 3D Video layout: `camXX.mp4`, `poses_bounds.npy`, and a `transforms.json`
summary beside them.

N3D's file has one focal length per camera and no principal point or distortion (cx = W/2, cy = H/2). So each
video is resampled once: through an ideal pinhole camera with the COLMAP camera's mean focal length and its
principal point at the centre of a crop that every camera's undistorted image covers (the same width and height
for all cameras). Near and far per camera come from the depths of the sparse points it observes (`near_far`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Sequence, Tuple

import numpy as np

from gear_nerfstudio.data.llff import llff_row
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.process.calibrate import Calibration
from gear_nerfstudio.process.footage import Footage


@dataclass(frozen=True)
class Output:
    """The pinhole camera a video is resampled to."""

    focal: float
    width: int
    height: int


def output_cameras(calibration: Calibration) -> List[Output]:
    """Each camera's pinhole output: its mean focal length and the crop (common to all) that every camera covers."""
    sizes = [_largest_crop(camera) for camera in calibration.cameras]
    width = min(w for w, _ in sizes) // 2 * 2  # even sizes for H.264's 4:2:0 chroma
    height = min(h for _, h in sizes) // 2 * 2
    if width < 16 or height < 16:
        raise InputError(f"the undistorted crop that every camera covers is only {width}x{height} pixels")
    return [Output(float(camera.mean_focal_length()), width, height) for camera in calibration.cameras]


def _pinhole_rays(focal: float, width: int, height: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame rays (z = 1) through pixel positions (u, v) of a centred pinhole (pixel centres at + 0.5)."""
    return np.stack([(u - width / 2) / focal, (v - height / 2) / focal, np.ones_like(u)], axis=-1)


def _largest_crop(camera) -> Tuple[int, int]:
    """The largest crop (the input's aspect) whose pinhole rays all land inside the input image, by bisection."""
    focal = float(camera.mean_focal_length())
    edge = np.linspace(0.0, 1.0, 101)
    low, high = 0.0, 1.5
    for _ in range(30):
        scale = (low + high) / 2
        w, h = scale * camera.width, scale * camera.height
        u = np.concatenate([edge * w, edge * w, np.zeros_like(edge), np.full_like(edge, w)])
        v = np.concatenate([np.zeros_like(edge), np.full_like(edge, h), edge * h, edge * h])
        pixels = camera.img_from_cam(_pinhole_rays(focal, w, h, u, v))
        inside = np.isfinite(pixels).all() and (pixels >= 0).all()
        inside = inside and (pixels[:, 0] <= camera.width).all() and (pixels[:, 1] <= camera.height).all()
        low, high = (scale, high) if inside else (low, scale)
    return int(low * camera.width), int(low * camera.height)


def resampling_map(camera, output: Output) -> Tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (x, y of the input pixel, centres at integers) for every output pixel."""
    v, u = np.mgrid[0 : output.height, 0 : output.width].astype(np.float64) + 0.5
    rays = _pinhole_rays(output.focal, output.width, output.height, u.ravel(), v.ravel())
    pixels = camera.img_from_cam(rays) - 0.5
    shape = (output.height, output.width)
    return pixels[:, 0].reshape(shape).astype(np.float32), pixels[:, 1].reshape(shape).astype(np.float32)


def write_video(
    footage: Footage, first: int, count: int, maps: Tuple[np.ndarray, np.ndarray], path: Path, advance: Callable
) -> None:
    """Resample frames first .. first + count - 1 of a camera and encode them as H.264 (CRF 12, 4:2:0)."""
    import av
    import cv2

    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=footage.frame_rate)
        stream.height, stream.width = maps[0].shape
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "12", "preset": "medium"}
        for rgb in footage.frames(first, count):
            resampled = cv2.remap(rgb, maps[0], maps[1], interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            for packet in stream.encode(av.VideoFrame.from_ndarray(resampled, format="rgb24")):
                container.mux(packet)
            advance()
        for packet in stream.encode():
            container.mux(packet)


def camera_to_world(cam_from_world: np.ndarray) -> np.ndarray:
    """(N, 3, 4) camera-to-world, OpenCV axes, from world-to-camera."""
    rotation = np.transpose(cam_from_world[:, :, :3], (0, 2, 1))
    centre = -np.einsum("nij,nj->ni", rotation, cam_from_world[:, :, 3])
    return np.concatenate([rotation, centre[..., None]], axis=2)


def near_far(depths: np.ndarray) -> Tuple[float, float]:
    """A camera's bounds from the depths of the points it sees: half the 1st percentile (people move nearer than the
    calibration instants show) and 1.2 times the 99th (the farthest points include a few mismatches)."""
    depths = depths[depths > 0]
    return 0.5 * float(np.percentile(depths, 1)), 1.2 * float(np.percentile(depths, 99))


def poses_bounds(c2w: np.ndarray, outputs: Sequence[Output], bounds: Sequence[Tuple[float, float]]) -> np.ndarray:
    """N3D's (N, 17) rows: LLFF rotation columns [down, right, back] and centre, [H, W, focal], near, far."""
    return np.array(
        [llff_row(pose, (o.height, o.width, o.focal), near, far) for pose, o, (near, far) in zip(c2w, outputs, bounds)]
    )


def transforms_frame(name: str, source: Footage, c2w: np.ndarray, output: Output) -> dict:
    """One camera in nerfstudio's transforms.json terms (OpenGL camera-to-world, pinhole intrinsics)."""
    opengl = np.concatenate([c2w[:, 0:1], -c2w[:, 1:2], -c2w[:, 2:3], c2w[:, 3:4]], axis=1)
    return {
        "file_path": f"{name}.mp4",
        "source": source.name,
        "transform_matrix": np.vstack([opengl, [0, 0, 0, 1]]).tolist(),
        "fl_x": output.focal,
        "fl_y": output.focal,
        "cx": output.width / 2,
        "cy": output.height / 2,
        "w": output.width,
        "h": output.height,
    }
