"""Which frames each chunk of a long video models, and which chunks render a given time.

The paper trains every 100 frames of a video as a model of its own. A window of T frames is cut into chunks
of ``chunk_frames`` frames; consecutive chunks share ``overlap`` frames. A chunk's times are its own
(frame index within the chunk / (n - 1)), so a time of the whole video, tau in [0, 1], is first turned into
a frame position f = tau (T - 1), then into each owning chunk's own time.

Where two chunks overlap, the render is a blend whose weight moves linearly from one chunk to the next
across the shared frames (and across the gap between the last frame of one chunk and the first of the next
when they do not overlap), so the video has no jump at a boundary: the weights are continuous in f and sum
to 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Tuple

from gear_nerfstudio.errors import InputError


class ChunkError(InputError):
    """Chunk settings that cannot cut this window."""


@dataclass(frozen=True)
class Chunk:
    """Frames [first, first + count) of the window (0-based positions in the window)."""

    index: int
    first: int
    count: int

    @property
    def last(self) -> int:
        return self.first + self.count - 1

    def local_time(self, position: float) -> float:
        """The chunk's own time of a frame position of the window, clamped to the chunk."""
        if self.count == 1:
            return 0.0
        return min(max((position - self.first) / (self.count - 1), 0.0), 1.0)


def plan_chunks(num_frames: int, chunk_frames: int, overlap: int = 0) -> List[Chunk]:
    """Chunks of ``chunk_frames`` frames, each starting ``chunk_frames - overlap`` frames after the previous
    one; the last ends at the window's last frame and may be shorter. An overlap must be less than half a
    chunk, so that a frame belongs to at most two chunks."""
    if chunk_frames < 1:
        raise ChunkError(f"--chunk-frames must be at least 1, got {chunk_frames}")
    if overlap < 0 or 2 * overlap >= chunk_frames:
        raise ChunkError(f"--overlap must lie in [0, chunk_frames / 2), got {overlap} for {chunk_frames}-frame chunks")
    if num_frames < 1:
        raise ChunkError("the frame window is empty")
    chunks: List[Chunk] = []
    first = 0
    while True:
        count = min(chunk_frames, num_frames - first)
        chunks.append(Chunk(len(chunks), first, count))
        if first + count == num_frames:
            return chunks
        first += chunk_frames - overlap


def _ramp(position: float, previous: Chunk, chunk: Chunk) -> float:
    """Weight of ``chunk`` against ``previous`` at a frame position: 0 at the last frame only ``previous`` holds,
    1 at the first frame only ``chunk`` holds, linear between."""
    start = chunk.first - 1
    span = previous.last - start + 1
    return min(max((position - start) / span, 0.0), 1.0)


def position(time: float, num_frames: int) -> float:
    """Frame position f = tau (T - 1) of a time of the whole video (clamped to [0, 1]). A time within float32
    rounding of a frame's (camera paths store times in float32) is that frame's, so that its chunk renders it at
    exactly the chunk's own time of that frame, as ns-render does."""
    frame = min(max(time, 0.0), 1.0) * (num_frames - 1)
    return float(round(frame)) if abs(frame - round(frame)) <= 1e-6 * num_frames else frame


def owners(chunks: List[Chunk], frame_position: float) -> List[Tuple[Chunk, float, float]]:
    """(chunk, blend weight, chunk's own time) of the chunks that render a frame position of the window."""
    result = []
    for k, chunk in enumerate(chunks):
        rise = 1.0 if k == 0 else _ramp(frame_position, chunks[k - 1], chunk)
        fall = 1.0 if k == len(chunks) - 1 else 1.0 - _ramp(frame_position, chunk, chunks[k + 1])
        weight = rise * fall
        if weight > 0.0:
            result.append((chunk, weight, chunk.local_time(frame_position)))
    return result
