"""On-disk cache of decoded, downscaled frames, so that nerfstudio loads frames as ordinary PNG files.

Videos are decoded one frame at a time (never all in RAM); each requested frame is written as
`<cache>/<key>/<frame:05d>.png`, where the key changes when the source file or the output size changes. The
videos are checked one after another, then written by one thread per core, one video each; the cameras of an image
layout are checked and resized likewise (`gear_nerfstudio.parallel`). PNG compression level 1: a 608x336 frame of
the real capture is written 2.8x faster than at Pillow's default level 6, for 18 % more bytes.
Files are written under a temporary name and renamed, so an interrupted run leaves nothing half-written.
Damaged frames (decoder errors, pictures missing from a video, PNG files that fail their checksums or do not
decode) are found while the cache is built: they stop the run with an error naming the file and the frame, or,
when the user asks, are left out with a warning.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Set, Tuple

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.parallel import available_cores, run_parallel


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
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # runs sharing the cache write their own
    Image.fromarray(rgb).save(tmp, format="PNG", compress_level=1)
    os.replace(tmp, path)


def _resize(rgb: np.ndarray, size: Tuple[int, int]) -> np.ndarray:
    """Area-filter resize to size = (width, height); identity when the size already matches."""
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.BOX))


def _frame_timestamps(container) -> List[int]:
    """Timestamps of the frames a video holds, in display order: one per packet of its first video stream
    (container metadata can be wrong), leaving out packets that an edit list discards (they decode to no frame)."""
    stream = container.streams.video[0]
    return sorted(p.pts for p in container.demux(stream) if p.size > 0 and not p.is_discard)


def video_info(video: Path, cache_dir: Optional[Path] = None) -> VideoInfo:
    """Frame count (from its packets, see `_frame_timestamps`) and size of a video, cached."""
    # "timestamps": counts from before discarded packets were left out are not reused.
    folder = (cache_dir or default_cache_dir()) / _source_key(video, "info|timestamps")
    info_file = folder / "info.json"
    if info_file.exists():
        return VideoInfo(**json.loads(info_file.read_text()))
    import av

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DatasetError(f"{video}: the file has no video stream")
            context = container.streams.video[0].codec_context
            info = VideoInfo(num_frames=len(_frame_timestamps(container)), width=context.width, height=context.height)
    except av.error.FFmpegError as err:
        raise DatasetError(f"{video}: cannot read the video ({err})") from err
    if info.num_frames == 0:
        raise DatasetError(f"{video}: the video has no frames")
    folder.mkdir(parents=True, exist_ok=True)
    tmp = info_file.with_name(f"info.json.{os.getpid()}.tmp")
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


def _damaged(path: Path, frame: int, reason: str) -> str:
    return f"{path}: frame {frame} is damaged: {reason}"


def _stop(message: str) -> DatasetError:
    return DatasetError(f"{message}; replace the file, or leave damaged frames out with --skip-damaged-frames True")


def _warn_skipped(lines: Sequence[str]) -> None:
    """One warning line per left-out frame (printed after the progress bar, unwrapped, paths not read as markup)."""
    for line in lines:
        CONSOLE.print(f"{line}; left out (--skip-damaged-frames)", style="yellow", soft_wrap=True, markup=False)


def cache_video_frames(
    videos: Sequence[Path],
    frames: Sequence[int],
    sizes: Sequence[Tuple[int, int]],
    cache_dir: Optional[Path] = None,
    skip_damaged: bool = False,
) -> List[List[Optional[Path]]]:
    """Decode `frames` (0-based indices) of each video, resized to its sizes[i] = (width, height).

    Returns paths[video][i] for frames[i]; frames already cached (and so checked) are not decoded again. Each video
    is decoded twice: once to find its damaged frames (`_damaged_frames`), once to cache the others. A damaged
    frame stops with a DatasetError naming the video and the frame before anything of that video is cached; with
    `skip_damaged`, its path is None instead, with one warning line.
    """
    cache_dir = cache_dir or default_cache_dir()
    # "checked": frames cached before damaged frames were detected are not reused.
    folders = [cache_dir / _source_key(video, f"{w}x{h}|checked") for video, (w, h) in zip(videos, sizes)]
    paths: List[List[Optional[Path]]] = [[folder / f"{frame:05d}.png" for frame in frames] for folder in folders]
    todo = [i for i, video_paths in enumerate(paths) if not all(p.exists() for p in video_paths)]
    if not todo:
        return paths
    skipped: List[str] = []
    writes: List[Callable[[], None]] = []
    with _progress() as progress:
        task = progress.add_task("Checking and decoding video frames", total=2 * len(todo) * len(frames))
        for i in todo:  # one video at a time: `_decoder_reports` hears every thread's decoder
            timestamps = _video_timestamps(videos[i])
            if max(frames) >= len(timestamps):
                raise DatasetError(f"{videos[i]}: the video has {len(timestamps)} frames, not {max(frames) + 1}")
            damaged = _damaged_frames(videos[i], timestamps, set(frames))
            progress.advance(task, len(frames))
            if damaged and not skip_damaged:
                first = min(damaged)
                more = f" ({len(damaged) - 1} more frames of the window are damaged)" if len(damaged) > 1 else ""
                raise _stop(_damaged(videos[i], first, damaged[first]) + more)
            targets = {frame: path for frame, path in zip(frames, paths[i]) if frame not in damaged}
            folders[i].mkdir(parents=True, exist_ok=True)
            writes.append(functools.partial(_write_frames, videos[i], timestamps, targets, sizes[i]))
            for frame in sorted(damaged):
                paths[i][frames.index(frame)] = None
                skipped.append(_damaged(videos[i], frame, damaged[frame]))
        run_parallel(writes, available_cores(), lambda: progress.advance(task, len(frames)))
    _warn_skipped(skipped)
    return paths


def _video_timestamps(video: Path) -> List[int]:
    import av

    try:
        with av.open(str(video)) as container:
            return _frame_timestamps(container)
    except av.error.FFmpegError as err:
        raise DatasetError(f"{video}: cannot read the video ({err})") from err


def _decoded(video: Path) -> Iterator[Tuple[Any, list, Optional[str]]]:
    """The packets of a video's first video stream in decode order (the last one empty, to flush), each with the
    pictures that decoding it returns and the error it raised, if any. One decoder thread: each packet is decoded
    (and its errors reported) before the next, and h264's error concealment, which slice threads turn off, runs
    and reports what it conceals."""
    import av

    try:
        with av.open(str(video)) as container:
            stream = container.streams.video[0]
            stream.thread_count = 1
            for packet in container.demux(stream):
                try:
                    pictures, error = stream.decode(packet), None
                except av.error.FFmpegError as err:
                    pictures, error = [], str(err)
                yield packet, pictures, error
    except av.error.FFmpegError as err:
        raise DatasetError(f"{video}: cannot read the video ({err})") from err


@contextmanager
def _decoder_reports() -> Iterator[List[Tuple[int, str, str]]]:
    """ffmpeg's messages at level INFO or worse, from every thread, repeats included; PyAV's logging settings are
    restored afterwards (PyAV drops ffmpeg's messages by default)."""
    import av.logging

    level, skip_repeated = av.logging.get_level(), av.logging.get_skip_repeated()
    av.logging.set_level(av.logging.INFO)
    av.logging.set_skip_repeated(False)
    try:
        with av.logging.Capture(local=False) as logs:
            yield logs
    finally:
        av.logging.set_level(level)
        av.logging.set_skip_repeated(skip_repeated)


def _damage_report(level: int, message: str) -> bool:
    """Whether an ffmpeg message reports damage: an error, or error concealment (logged at INFO by the error
    resilience of h264, mpeg4, mpeg2 and others; it is what makes ffmpeg print "corrupt decoded frame")."""
    import av.logging

    return level <= av.logging.ERROR or message.startswith("concealing ")


def _damaged_frames(video: Path, timestamps: List[int], wanted: Set[int]) -> Dict[int, str]:
    """The damaged frames among `wanted` (0-based indices), each with what is wrong.

    The decoder's reports (an exception, an ffmpeg error, concealment) are not always about the packet being
    decoded: broken data can decode without a word (HEVC and VP9 often, until a later picture fails; h264 when
    the damage spans two packets and only the second fails), and inter frames are predicted from earlier ones. So
    a report damages its whole group of pictures: the frames decoded from the same key frame, and the next group's
    leading frames (decoded after its key frame, shown before it, predicted from both groups); a report at a key
    frame damages the group before it, too (the packets lie one after the other in the file: the damage may
    start silently at the end of that group). A frame is damaged, too, when the decoder marks its picture corrupt
    or returns no picture for it: an intact stream decodes to one picture per packet, carrying the packet's
    timestamp, and pictures are placed by timestamp. Decoding stops after the first key frame that follows the
    last wanted picture.
    """
    index_of = {pts: i for i, pts in enumerate(timestamps)}
    key_pts: List[Optional[int]] = []  # per group of pictures, its key frame's timestamp
    group_of: Dict[int, int] = {}  # frame index -> group
    reports: Dict[int, Tuple[Optional[int], str]] = {}  # damaged group -> the first report: (frame, message)
    corrupt: Set[int] = set()
    pending = set(wanted)
    seen = 0
    with _decoder_reports() as logs:
        for packet, pictures, error in _decoded(video):
            last = not pending and packet.is_keyframe
            previous = max(len(key_pts) - 1, 0)
            if packet.is_keyframe or not key_pts:
                key_pts.append(packet.pts)
            group = len(key_pts) - 1
            index = index_of.get(packet.pts)
            if index is not None:
                group_of[index] = group
            messages = [message.strip() for level, _, message in logs[seen:] if _damage_report(level, message)]
            seen = len(logs)
            if messages or error:
                for damaged_group in {previous, group}:
                    reports.setdefault(damaged_group, (index, messages[0] if messages else error))
            for picture in pictures:
                index = index_of.get(picture.pts)
                pending.discard(index)
                if picture.is_corrupt:
                    corrupt.add(index)
            if last:
                break
    damaged: Dict[int, str] = {}
    for index in wanted:
        group = group_of[index]
        leading = group > 0 and timestamps[index] < key_pts[group]
        report = reports.get(group) or (reports.get(group - 1) if leading else None)
        if report:
            at, message = report
            damaged[index] = f"the decoder reports '{message}'"
            if at != index:
                where = "at the end of the stream" if at is None else f"at frame {at}"
                damaged[index] += f" {where}, and frames decoded from the same key frame go with it"
        elif index in pending:
            damaged[index] = "the decoder returns no picture for it"
        elif index in corrupt:
            damaged[index] = "the decoder marks its picture corrupt"
    return damaged


def _write_frames(video: Path, timestamps: List[int], targets: Dict[int, Path], size: Tuple[int, int]) -> None:
    """Write the frames `targets` (0-based index -> PNG path, none of them damaged) that are not cached yet."""
    index_of = {pts: i for i, pts in enumerate(timestamps)}
    pending = set(targets)
    for _, pictures, _ in _decoded(video):  # errors were weighed by `_damaged_frames`: none concerns a target
        for picture in pictures:
            index = index_of.get(picture.pts)
            if index in pending:
                pending.discard(index)
                if not targets[index].exists():
                    _write_atomic_png(_resize(picture.to_ndarray(format="rgb24"), size), targets[index])
        if not pending:
            return


def cache_image_frames(
    images: Sequence[Sequence[Path]],
    frames: Sequence[int],
    sizes: Sequence[Tuple[int, int]],
    cache_dir: Optional[Path] = None,
    skip_damaged: bool = False,
) -> List[List[Optional[Path]]]:
    """Check that each image is intact (see `_checked_image`); keep it, or cache a copy resized to sizes[i].

    images[i][j] is camera i's frame number frames[j]; returns the paths to load, in the same layout. A damaged
    image stops with a DatasetError naming the file and the frame; with `skip_damaged`, its path is None instead,
    with one warning line.
    """
    cache_dir = cache_dir or default_cache_dir()
    jobs = [
        functools.partial(_checked_camera, paths, frames, size, cache_dir, skip_damaged)
        for paths, size in zip(images, sizes)
    ]
    with _progress() as progress:
        task = progress.add_task("Checking and caching frames", total=len(images) * len(frames))
        cameras = run_parallel(jobs, available_cores(), lambda: progress.advance(task, len(frames)))
    _warn_skipped([message for _, messages in cameras for message in messages])
    return [paths for paths, _ in cameras]


def _checked_camera(
    images: Sequence[Path], frames: Sequence[int], size: Tuple[int, int], cache_dir: Path, skip_damaged: bool
) -> Tuple[List[Optional[Path]], List[str]]:
    """One camera's frames through `_checked_image`: the paths to load (None for a damaged frame left out) and
    the warning of each frame left out."""
    paths: List[Optional[Path]] = []
    skipped: List[str] = []
    for image, frame in zip(images, frames):
        try:
            paths.append(_checked_image(image, size, cache_dir))
        except (OSError, SyntaxError) as err:
            message = _damaged(image, frame, f"cannot read the image ({err})")
            if not skip_damaged:
                raise _stop(message) from err
            paths.append(None)
            skipped.append(message)
    return paths, skipped


def _checked_image(image: Path, size: Tuple[int, int], cache_dir: Path) -> Path:
    """The image itself when it has the given size, else a cached copy resized to it. Raises OSError or
    SyntaxError when the file is damaged: `verify` checks every chunk's checksum and that the file ends where the
    PNG does, a full decode checks the image data (intact chunks can hold data that was broken before they were
    written). Each version of a file is checked once: the marker (or the resized copy) is cached."""
    folder = cache_dir / _source_key(image, f"{size[0]}x{size[1]}|checked")
    with Image.open(image) as handle:
        resized = handle.size != size
    checked = folder / ("frame.png" if resized else "intact")
    if not checked.exists():
        with Image.open(image) as handle:
            handle.verify()
        with Image.open(image) as handle:
            handle.load()
            folder.mkdir(parents=True, exist_ok=True)
            if resized:
                _write_atomic_png(_resize(np.asarray(handle.convert("RGB")), size), checked)
            else:
                checked.touch()
    return checked if resized else image
