"""On-disk cache of decoded, downscaled frames, so that nerfstudio loads frames as ordinary PNG files.

Videos are decoded once, one frame at a time (never all in RAM); each requested frame is written as
`<cache>/<key>/<frame:05d>.png`, where the key changes when the source file or the output size changes.
Files are written under a temporary name and renamed, so an interrupted run leaves nothing half-written.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from gear_nerfstudio.data.errors import DatasetError


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gear-nerfstudio" / "frames"


@dataclass(frozen=True)
class VideoInfo:
    num_frames: int
    width: int
    height: int


def _source_key(path: Path, extra: str) -> str:
    stat = path.stat()
    text = f"{path.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{extra}"
    return hashlib.sha1(text.encode()).hexdigest()[:20]


def _write_atomic_png(rgb: np.ndarray, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    Image.fromarray(rgb).save(tmp, format="PNG")
    os.replace(tmp, path)


def _resize(rgb: np.ndarray, size: Tuple[int, int]) -> np.ndarray:
    """Area-filter resize to size = (width, height); identity when the size already matches."""
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.BOX))


def video_info(video: Path, cache_dir: Optional[Path] = None) -> VideoInfo:
    """Frame count (from its packets; container metadata can be wrong) and size of a video, cached."""
    folder = (cache_dir or default_cache_dir()) / _source_key(video, "info")
    info_file = folder / "info.json"
    if info_file.exists():
        return VideoInfo(**json.loads(info_file.read_text()))
    import av

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DatasetError(f"{video}: the file has no video stream")
            stream = container.streams.video[0]
            count = sum(1 for _ in container.demux(stream) if _.size > 0)
            info = VideoInfo(num_frames=count, width=stream.codec_context.width, height=stream.codec_context.height)
    except av.error.FFmpegError as err:
        raise DatasetError(f"{video}: cannot read the video ({err})") from err
    if info.num_frames == 0:
        raise DatasetError(f"{video}: the video has no frames")
    folder.mkdir(parents=True, exist_ok=True)
    tmp = info_file.with_name("info.json.tmp")
    tmp.write_text(json.dumps(info.__dict__))
    os.replace(tmp, info_file)
    return info


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold blue]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )


def cache_video_frames(
    videos: Sequence[Path],
    frames: Sequence[int],
    sizes: Sequence[Tuple[int, int]],
    cache_dir: Optional[Path] = None,
) -> List[List[Path]]:
    """Decode `frames` (0-based indices) of each video, resized to its sizes[i] = (width, height).

    Returns paths[video][i] for frames[i]. Already cached frames are not decoded again.
    """
    cache_dir = cache_dir or default_cache_dir()
    folders = [cache_dir / _source_key(video, f"{w}x{h}") for video, (w, h) in zip(videos, sizes)]
    paths = [[folder / f"{frame:05d}.png" for frame in frames] for folder in folders]
    todo = [i for i, video_paths in enumerate(paths) if not all(p.exists() for p in video_paths)]
    if not todo:
        return paths
    wanted_total = sum(len(frames) for _ in todo)
    with _progress() as progress:
        task = progress.add_task("Decoding video frames into the cache", total=wanted_total)
        for i in todo:
            folders[i].mkdir(parents=True, exist_ok=True)
            _decode_into(videos[i], dict(zip(frames, paths[i])), sizes[i], lambda: progress.advance(task))
    return paths


def _decode_into(video: Path, targets: Dict[int, Path], size: Tuple[int, int], advance) -> None:
    import av

    last = max(targets)
    index = -1
    try:
        with av.open(str(video)) as container:
            for index, frame in enumerate(container.decode(video=0)):
                if index in targets:
                    if not targets[index].exists():
                        _write_atomic_png(_resize(frame.to_ndarray(format="rgb24"), size), targets[index])
                    advance()
                if index >= last:
                    return
    except av.error.FFmpegError as err:
        raise DatasetError(f"{video}: cannot decode frame {index + 1} ({err})") from err
    raise DatasetError(f"{video}: the video ends after {index + 1} frames, frame {last} was requested")


def cache_image_frames(
    images: Sequence[Sequence[Path]], sizes: Sequence[Tuple[int, int]], cache_dir: Optional[Path] = None
) -> List[List[Path]]:
    """Check that each image decodes; keep it, or cache a copy resized to its camera's sizes[i].

    images[i] are the frames of camera i; returns the paths to load, in the same layout.
    """
    cache_dir = cache_dir or default_cache_dir()
    out: List[List[Path]] = []
    with _progress() as progress:
        task = progress.add_task("Checking and caching frames", total=sum(len(paths) for paths in images))
        for paths, size in zip(images, sizes):
            out.append([])
            for image in paths:
                out[-1].append(_checked_image(image, size, cache_dir))
                progress.advance(task)
    return out


def _checked_image(image: Path, size: Tuple[int, int], cache_dir: Path) -> Path:
    try:
        with Image.open(image) as handle:
            if handle.size == size:
                handle.verify()
                return image
            target = cache_dir / _source_key(image, f"{size[0]}x{size[1]}") / "frame.png"
            if not target.exists():
                target.parent.mkdir(parents=True, exist_ok=True)
                _write_atomic_png(_resize(np.asarray(handle.convert("RGB")), size), target)
            return target
    except (OSError, SyntaxError) as err:
        raise DatasetError(f"{image}: cannot read the image ({err})") from err
