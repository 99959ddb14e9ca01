"""The input of `ns-gear-process`: one video per camera, or one folder of frames per camera.

Each camera is named after its file or folder; cameras are listed in sorted order. A video is probed (frame rate,
frame count from its packets, size, one decoded frame); a folder of frames has the frame rate the user gives and
every image's size is read from its header. Decoding errors and a size that changes within one camera stop with an
`InputError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from gear_nerfstudio.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class Footage:
    """One camera's recording."""

    name: str
    """The input file or folder name."""
    path: Path
    frame_rate: Fraction
    num_frames: int
    width: int
    height: int
    images: Tuple[Path, ...] = ()
    """The frames of a folder of frames, in order; empty for a video."""

    @property
    def is_video(self) -> bool:
        return not self.images

    def frames(self, first: int, count: int) -> Iterator[np.ndarray]:
        """RGB frames first .. first + count - 1, each checked to have the camera's size."""
        if self.is_video:
            pictures = _video_frames(self.path, first, count)
        else:
            pictures = (_image(path) for path in self.images[first : first + count])
        produced = 0
        for index, rgb in enumerate(pictures, start=first):
            if rgb.shape[:2] != (self.height, self.width):
                raise InputError(
                    f"{self.path}: frame {index} is {rgb.shape[1]}x{rgb.shape[0]}, the camera's first frame "
                    f"{self.width}x{self.height}; every frame of a camera must have the same size"
                )
            produced += 1
            yield rgb
        if produced < count:
            raise InputError(f"{self.path}: decoding stopped after frame {first + produced - 1} of {first + count - 1}")

    def frames_at(self, indices: Sequence[int]) -> List[np.ndarray]:
        """RGB frames at sorted `indices`: a video is decoded once, up to the last of them."""
        if not self.is_video:
            return [next(self.frames(index, 1)) for index in indices]
        wanted = set(indices)
        span = self.frames(indices[0], indices[-1] - indices[0] + 1)
        return [rgb for index, rgb in enumerate(span, start=indices[0]) if index in wanted]


def read_footage(folder: Path, frame_rate: float) -> List[Footage]:
    """The cameras of `folder`, sorted by name; `frame_rate` applies to folders of frames."""
    if not folder.is_dir():
        raise InputError(f"{folder}: the input folder does not exist")
    entries = sorted(
        p for p in folder.iterdir() if not p.name.startswith(".") and (p.suffix.lower() in VIDEO_SUFFIXES or p.is_dir())
    )
    cameras = [_probe_video(p) if p.is_file() else _probe_frames(p, frame_rate) for p in entries]
    if len(cameras) < 2:
        raise InputError(
            f"{folder}: {len(cameras)} camera(s) found; expected one video ({', '.join(VIDEO_SUFFIXES)}) "
            "or one folder of frames per camera, at least two"
        )
    return cameras


def _probe_video(path: Path) -> Footage:
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(f"{path}: the file has no video stream")
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate
            num_frames = sum(1 for p in container.demux(stream) if p.size > 0 and not p.is_discard)
    except av.error.FFmpegError as err:
        raise InputError(f"{path}: the video does not decode ({err})") from err
    first = next(_video_frames(path, 0, 1), None)
    if first is None or num_frames == 0 or not rate:
        raise InputError(f"{path}: the video does not decode (no frame)")
    return Footage(path.name, path, Fraction(rate), num_frames, first.shape[1], first.shape[0])


def _probe_frames(folder: Path, frame_rate: float) -> Footage:
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise InputError(f"{folder}: the camera folder has no frames ({', '.join(IMAGE_SUFFIXES)})")
    sizes = []
    for path in images:
        try:
            with Image.open(path) as image:
                sizes.append(image.size)
        except OSError as err:
            raise InputError(f"{path}: the frame does not decode ({err})") from err
    for path, size in zip(images, sizes):
        if size != sizes[0]:
            raise InputError(
                f"{path}: {size[0]}x{size[1]}, but {images[0].name} is {sizes[0][0]}x{sizes[0][1]}; every frame of "
                f"camera {folder.name} must have the same size"
            )
    rate = Fraction(frame_rate).limit_denominator(1001)
    return Footage(folder.name, folder, rate, len(images), sizes[0][0], sizes[0][1], tuple(images))


def _video_frames(path: Path, first: int, count: int) -> Iterator[np.ndarray]:
    """Decoded RGB frames first .. first + count - 1 of a video (in display order)."""
    import av

    try:
        with av.open(str(path)) as container:
            for index, picture in enumerate(container.decode(video=0)):
                if index >= first + count:
                    return
                if index >= first:
                    yield picture.to_ndarray(format="rgb24")
    except av.error.FFmpegError as err:
        raise InputError(f"{path}: the video does not decode ({err})") from err


def _image(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))
    except OSError as err:
        raise InputError(f"{path}: the frame does not decode ({err})") from err


def read_audio(footage: Footage, sample_rate: int) -> Optional[np.ndarray]:
    """The first audio track of a video, mixed to mono float32 at `sample_rate`; None when there is none."""
    if not footage.is_video:
        return None
    import av

    try:
        with av.open(str(footage.path)) as container:
            if not container.streams.audio:
                return None
            resampler = av.AudioResampler(format="flt", layout="mono", rate=sample_rate)
            chunks = []
            for frame in container.decode(audio=0):
                chunks.extend(f.to_ndarray().reshape(-1) for f in resampler.resample(frame))
            chunks.extend(f.to_ndarray().reshape(-1) for f in resampler.resample(None))
    except av.error.FFmpegError as err:
        raise InputError(f"{footage.path}: the audio track does not decode ({err})") from err
    return np.concatenate(chunks) if chunks else None


def check_frame_rates(cameras: Sequence[Footage]) -> None:
    """Every camera must have the first camera's frame rate."""
    reference = cameras[0]
    for camera in cameras[1:]:
        if camera.frame_rate != reference.frame_rate:
            raise InputError(
                f"{camera.path}: {float(camera.frame_rate):.3f} frames per second, but {reference.name} has "
                f"{float(reference.frame_rate):.3f}; convert the videos to one frame rate"
            )
